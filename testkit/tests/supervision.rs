//! End to end: s3res's own processes. bootstrap is the trusted base: when it dies, however it
//! dies, everything it started dies with it and nothing is left behind.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use s3res_testkit::{
    assert_sink_whole, echo_pipeline, is_recovery_of, procs, EventKind, RecoveryMethod, System,
};

const TIMEOUT_US: u64 = 300_000;

/// A TMR echo pipeline that runs for a minute (the tests end it much earlier).
fn long_running(sys: &System) -> String {
    let echo = format!(
        r#"{{ "exec": "s3res-echo", "args": ["--stateful"], "redundancy": "tmr", "timeout_us": {TIMEOUT_US} }}"#
    );
    echo_pipeline(&sys.path("summary.json"), &echo, 60_000, 1000)
}

/// The live (not zombie) processes of process group `pgid`, but `except`.
fn live_in_group(pgid: i32, except: i32) -> Vec<procs::ProcStat> {
    procs::in_group(pgid)
        .into_iter()
        .filter(|p| !p.is_zombie() && p.pid != except)
        .collect()
}

/// The runtime folder (`s3res-PID-0` in `tmp`) of the bootstrap with this pid.
fn runtime_dir(tmp: &Path, bootstrap: i32) -> PathBuf {
    tmp.join(format!("s3res-{bootstrap}-0"))
}

/// A temp dir of the test's own, for bootstrap's `TMPDIR`: every bootstrap removes the stale
/// runtime folders it finds in its `TMPDIR`, so in the shared one another test's bootstrap,
/// started meanwhile, could remove a folder this test wants to see.
fn private_tmp() -> tempfile::TempDir {
    tempfile::Builder::new()
        .prefix("s3res-tmp-")
        .tempdir()
        .expect("creating a temp dir")
}

/// Sends `sig` to bootstrap mid-run and waits (10 s at most) until no process of the system
/// is left; returns how long that took and bootstrap's pid. bootstrap's `TMPDIR` is `tmp`.
fn kill_bootstrap(sig: i32, tmp: &Path) -> (Duration, i32) {
    kill_bootstrap_of(sig, tmp, None)
}

/// [`kill_bootstrap`] of a system with the description's `inject` object `inject`, if any
/// (the injector running is waited for before the signal).
fn kill_bootstrap_of(sig: i32, tmp: &Path, inject: Option<serde_json::Value>) -> (Duration, i32) {
    let sys = System::new().env("TMPDIR", tmp);
    let mut desc: serde_json::Value =
        serde_json::from_str(&long_running(&sys)).expect("the pipeline is JSON");
    let injects = inject.is_some();
    if let Some(inject) = inject {
        desc["inject"] = inject;
    }
    let mut run = sys.start_json(&desc);
    run.wait_for_replicas("echo", 3);
    if injects {
        s3res_testkit::wait_until("the injector", Duration::from_secs(20), || {
            run.process_named("s3res-inject")
        });
    }
    let (bootstrap, pgid) = (run.pid(), run.pgid());
    let before = live_in_group(pgid, bootstrap);
    // source, voter, three replicas, sink.
    assert!(before.len() >= 6, "the system is not running: {before:?}");
    assert!(runtime_dir(tmp, bootstrap).is_dir(), "no runtime folder");

    s3res_testkit::kill_pid(bootstrap, sig).expect("signal bootstrap");
    let start = Instant::now();
    loop {
        let left = live_in_group(pgid, bootstrap);
        let bootstrap_gone = run.try_status().is_some();
        if left.is_empty() && bootstrap_gone {
            break;
        }
        assert!(
            start.elapsed() < Duration::from_secs(10),
            "10 s after signal {sig} to bootstrap, still running: {left:?} (bootstrap gone: {bootstrap_gone})"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
    let took = start.elapsed();
    eprintln!("signal {sig}: every process of the system gone {took:?} after it reached bootstrap");
    run.assert_nothing_left();
    (took, bootstrap)
}

#[test]
fn sigkill_of_bootstrap_ends_every_process_it_started() {
    let tmp = private_tmp();
    let (_, bootstrap) = kill_bootstrap(libc::SIGKILL, tmp.path());
    // A SIGKILLed bootstrap cannot clean up; the next one removes its runtime folder.
    assert!(
        runtime_dir(tmp.path(), bootstrap).is_dir(),
        "nothing removed the folder yet"
    );
    let sys = System::new().env("TMPDIR", tmp.path());
    let desc = long_running(&sys);
    let mut next = sys.start(&desc);
    next.wait_for_replicas("echo", 3);
    assert!(
        !runtime_dir(tmp.path(), bootstrap).exists(),
        "the next bootstrap did not remove the runtime folder of the dead one"
    );
    next.stop();
}

/// The fault injector a description's `inject` starts ends with a SIGKILLed bootstrap too:
/// it had no parent-death signal, and went on firing faults at the pids of a system that was
/// gone (its seed: 56).
#[test]
fn sigkill_of_bootstrap_ends_its_fault_injector_too() {
    let tmp = private_tmp();
    let inject = serde_json::json!({
        "faults": ["exec"], "rate_hz": 1, "seed": 56, "after_s": 600, "components": ["echo"]
    });
    kill_bootstrap_of(libc::SIGKILL, tmp.path(), Some(inject));
}

/// What an unprotected component started itself (a shell's background job) ends with a
/// SIGKILLed bootstrap too: the kernel's parent-death signal reaches only bootstrap's own
/// children, and the job, re-parented to init, ran on (stop 62 found it). bootstrap's keeper
/// finds every process carrying the run's mark and kills it.
#[test]
fn sigkill_of_bootstrap_ends_what_an_unprotected_component_started() {
    sigkill_ends_the_launchers_job("sleep 600", false);
}

/// The same with the SIGKILL sent to bootstrap's whole process group (`kill -9 %1`, a runner
/// that kills the group) and a job that left the group (`setsid`): the keeper, in a group of
/// its own, is not killed with bootstrap (a review found that it was).
#[test]
fn sigkill_of_bootstraps_group_ends_a_job_that_left_the_group() {
    sigkill_ends_the_launchers_job("setsid sleep 600", true);
}

/// Starts the echo pipeline and a `launcher` that runs `job` in the background, SIGKILLs
/// bootstrap (or its whole group), and waits (10 s at most) until the job and every process
/// of the system are gone.
fn sigkill_ends_the_launchers_job(job: &str, whole_group: bool) {
    let tmp = private_tmp();
    let sys = System::new().env("TMPDIR", tmp.path());
    let mut desc: serde_json::Value =
        serde_json::from_str(&long_running(&sys)).expect("the pipeline is JSON");
    let started = sys.path("job-started");
    desc["components"]["launcher"] = serde_json::json!({
        "exec": "/bin/sh",
        "args": ["-c", format!("{job} & echo $! > {}; wait", started.display())]
    });
    let mut run = sys.start_json(&desc);
    run.wait_for_replicas("echo", 3);
    let job: i32 = s3res_testkit::wait_until("the launcher's job", Duration::from_secs(20), || {
        std::fs::read_to_string(&started).ok()?.trim().parse().ok()
    });
    s3res_testkit::wait_until("the job running", Duration::from_secs(20), || {
        procs::stat(job)
            .filter(|p| !p.is_zombie() && p.comm == "sleep")
            .map(|_| ())
    });
    let (bootstrap, pgid) = (run.pid(), run.pgid());
    if whole_group {
        assert_ne!(
            procs::stat(job).map(|p| p.pgrp),
            Some(pgid),
            "the job left the group"
        );
    }
    let target = if whole_group { -pgid } else { bootstrap };
    s3res_testkit::kill_pid(target, libc::SIGKILL).expect("SIGKILL bootstrap");
    let start = Instant::now();
    loop {
        let job_lives = procs::stat(job).is_some_and(|p| !p.is_zombie());
        let left: Vec<_> = procs::with_env(s3res_testkit::system::MARK_ENV, run.mark())
            .into_iter()
            .filter(|p| !p.is_zombie() && p.pid != bootstrap)
            .collect();
        if !job_lives && left.is_empty() && run.try_status().is_some() {
            break;
        }
        assert!(
            start.elapsed() < Duration::from_secs(10),
            "10 s after bootstrap was SIGKILLed, still running (the launcher's job {job} lives: \
             {job_lives}): {left:?}"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
    eprintln!(
        "the launcher's job and every other process gone {:?} after bootstrap was SIGKILLed",
        start.elapsed()
    );
    run.assert_nothing_left();
}

/// An unprotected component that fails while the rest runs on: each line it wrote is relayed
/// behind `[loader pid N]` (a shell script's lines came bare, and whose `error:` it was could
/// not be told), the live status line names it ("degraded: loader (failed: exit status 3)"; it
/// has no voter to send events, and the line said "degraded: none" after it had died), and the
/// line that reports its failure quotes the last line it wrote that says something. A
/// `replica-rt` component's lines carry its name once, not twice.
#[test]
fn a_failed_unprotected_component_is_named_on_its_lines_the_status_and_the_verdict() {
    let sys = System::new();
    let mut desc: serde_json::Value =
        serde_json::from_str(&long_running(&sys)).expect("the pipeline is JSON");
    desc["components"]["loader"] = serde_json::json!({
        "exec": "/bin/sh",
        "args": ["-c", "echo loading the map >&2; printf 'error: no map file map.bin\\n  (looked in .)\\n' >&2; exit 3"]
    });
    let mut run = sys.start_json(&desc);
    run.wait_for_replicas("echo", 3);
    // Not a terminal: a plain status line every 5 s.
    let said = "degraded: loader (failed: exit status 3)";
    s3res_testkit::wait_until("the status line", Duration::from_secs(30), || {
        run.stderr().contains(said).then_some(())
    });
    run.stop();
    let out = run.wait(Duration::from_secs(30));
    let tail = s3res_testkit::tail(&out.stderr, 30);
    let loader = out
        .stderr
        .lines()
        .find_map(|l| l.strip_suffix("loading the map"))
        .unwrap_or_else(|| panic!("the loader's line is not relayed:\n{tail}"));
    assert!(
        loader.starts_with("[loader pid ") && loader.ends_with("] "),
        "{loader:?}\n{tail}"
    );
    assert!(
        out.stderr.contains(&format!("{loader}  (looked in .)")),
        "{tail}"
    );
    assert!(
        out.stderr.contains(
            "component loader failed: exit status 3; its last stderr line: error: no map file map.bin"
        ),
        "{tail}"
    );
    let source = out
        .stderr
        .lines()
        .find(|l| l.starts_with("[source pid "))
        .unwrap_or_else(|| panic!("the source's lines are not relayed behind its name:\n{tail}"));
    assert_eq!(source.matches("[source pid ").count(), 1, "{source}");
    run.assert_nothing_left();
}

#[test]
fn sighup_of_bootstrap_stops_everything_and_removes_its_runtime_folder() {
    let tmp = private_tmp();
    let (_, bootstrap) = kill_bootstrap(libc::SIGHUP, tmp.path());
    assert!(
        !runtime_dir(tmp.path(), bootstrap).exists(),
        "runtime folder left behind"
    );
}

#[test]
fn sigquit_of_bootstrap_stops_everything_and_removes_its_runtime_folder() {
    let tmp = private_tmp();
    let (_, bootstrap) = kill_bootstrap(libc::SIGQUIT, tmp.path());
    assert!(
        !runtime_dir(tmp.path(), bootstrap).exists(),
        "runtime folder left behind"
    );
}

/// A bootstrap started under another name (a renamed copy, a link: its process name is not
/// `s3res-bootstrap`) is alive all the same, and so is one in another pid namespace sharing
/// `/tmp`: a second bootstrap must not take its runtime folder for a dead one's. That folder
/// holds the voter's socket, through which a fork child reaches its voter: without it (before
/// the lock) the first system's killed replica was rebuilt by exec, its state lost, 2 s after
/// its death. Every bootstrap holds a lock on its folder while it lives; the others remove
/// only folders nobody holds.
#[test]
fn a_second_bootstrap_leaves_a_live_bootstrap_of_another_name_its_runtime_folder() {
    let tmp = private_tmp();
    let link = tmp.path().join("mysat-supervisor");
    std::os::unix::fs::symlink(s3res_testkit::bin_path("s3res-bootstrap"), &link)
        .expect("linking s3res-bootstrap under another name");
    let sys = System::new().env("TMPDIR", tmp.path());
    let desc = long_running(&sys);
    let mut first = sys.start_with(&link, &desc);
    first.wait_for_replicas("echo", 3);
    first.wait_for_answers("echo");
    let comm = std::fs::read_to_string(format!("/proc/{}/comm", first.pid())).unwrap_or_default();
    assert_eq!(
        comm.trim_end(),
        "mysat-superviso",
        "the first bootstrap's process name"
    );
    let folder = runtime_dir(tmp.path(), first.pid());
    assert!(folder.is_dir(), "no runtime folder {}", folder.display());

    let sys = System::new().env("TMPDIR", tmp.path());
    let desc = long_running(&sys);
    let mut second = sys.start(&desc);
    second.wait_for_replicas("echo", 3);
    assert!(
        folder.is_dir(),
        "the second bootstrap removed the runtime folder of the first, which is running"
    );
    // The first system still rebuilds its replicas, again and again (each recovery renews
    // the spare lines of the child and its donor through the voter's socket).
    for slot in [2, 0, 2] {
        let pid = first.replica_pids("echo")[&slot];
        s3res_testkit::kill_pid(pid, libc::SIGKILL).expect("kill a replica");
        let rec = first.wait_for_event(|e| is_recovery_of(e, slot, pid), Duration::from_secs(20));
        assert_eq!(rec.method, Some(RecoveryMethod::Fork), "{rec:?}");
    }
    for run in [&mut second, &mut first] {
        run.stop();
        run.wait(Duration::from_secs(20));
        run.assert_nothing_left();
    }
    assert!(
        !folder.exists(),
        "the first bootstrap left its runtime folder"
    );
}

/// What the test process started below prints once its system runs: bootstrap's pid, the
/// system's mark and its temp dir.
const KILLED_TEST_PROCESS_SAYS: &str = "s3res-test-system-running";

/// The body of the test process that `a_killed_test_process_takes_its_system_with_it` starts
/// and kills: a running system, what identifies it on stdout, then a wait for stdin to end
/// (at once when run alone, with stdin empty: the system is then stopped as usual).
#[test]
#[ignore = "started, and killed mid-run, by a_killed_test_process_takes_its_system_with_it"]
fn a_test_process_killed_with_its_system_running() {
    let sys = System::new();
    let desc = long_running(&sys);
    let mut run = sys.start(&desc);
    run.wait_for_replicas("echo", 3);
    println!(
        "{KILLED_TEST_PROCESS_SAYS} {} {} {}",
        run.pid(),
        run.mark(),
        run.dir().display()
    );
    let mut rest = Vec::new();
    let _ = std::io::Read::read_to_end(&mut std::io::stdin(), &mut rest);
    run.stop();
}

/// A test process started by a test, with what its system left to clean up when the test
/// fails: the test process's group, the system's processes (by mark), its temp dir.
struct KilledTestProcess {
    child: std::process::Child,
    mark: Option<String>,
    dir: Option<PathBuf>,
}

impl Drop for KilledTestProcess {
    fn drop(&mut self) {
        let _ = s3res_testkit::kill_pid(-(self.child.id() as i32), libc::SIGKILL);
        let _ = self.child.wait();
        if let Some(mark) = &self.mark {
            procs::kill_with_env(s3res_testkit::system::MARK_ENV, mark);
        }
        s3res_testkit::system::reap_orphans_here();
        if let Some(dir) = &self.dir {
            let _ = std::fs::remove_dir_all(dir);
        }
    }
}

/// A test process that dies (Ctrl-C on `cargo test`, a time limit's SIGKILL) runs no drop
/// guard; its systems must not outlive it all the same. The test starts this test binary
/// again on `a_test_process_killed_with_its_system_running`, waits until that process's system
/// runs, SIGKILLs the test process alone, and waits (10 s at most) until no process carrying
/// the system's mark lives. (Before the harness tied bootstrap to the test process, the
/// system ran on for its minute.)
#[test]
fn a_killed_test_process_takes_its_system_with_it() {
    use std::io::BufRead as _;
    use std::os::unix::process::CommandExt as _;
    use std::process::{Command, Stdio};

    // Orphans (bootstrap, once its test process is gone) come here to be reaped.
    s3res_testkit::system::reap_orphans_here();
    let exe = std::env::current_exe().expect("the test binary's path");
    let stderr = tempfile::NamedTempFile::new().expect("a file for its stderr");
    let mut child = Command::new(exe)
        .args([
            "--exact",
            "a_test_process_killed_with_its_system_running",
            "--ignored",
            "--nocapture",
            "--test-threads=1",
        ])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(stderr.reopen().expect("reopening the stderr file"))
        .process_group(0)
        .spawn()
        .expect("starting the test binary again");
    let stdout = child.stdout.take().expect("piped stdout");
    let mut test = KilledTestProcess {
        child,
        mark: None,
        dir: None,
    };
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in std::io::BufReader::new(stdout)
            .lines()
            .map_while(Result::ok)
        {
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    // The second test process builds nothing (the binaries are built) but starts a system.
    let deadline = Instant::now() + Duration::from_secs(120);
    let said = loop {
        let left = deadline.saturating_duration_since(Instant::now());
        let Ok(line) = rx.recv_timeout(left) else {
            panic!(
                "the second test process never said its system runs; its stderr:\n{}",
                s3res_testkit::tail(
                    &std::fs::read_to_string(stderr.path()).unwrap_or_default(),
                    30
                )
            );
        };
        // libtest writes `test NAME ... ` on the same line first.
        if let Some((_, rest)) = line.split_once(KILLED_TEST_PROCESS_SAYS) {
            break rest.to_owned();
        }
    };
    let fields: Vec<&str> = said.split_whitespace().collect();
    let [bootstrap, mark, dir] = fields[..] else {
        panic!("unexpected line from the second test process: {said:?}");
    };
    let bootstrap: i32 = bootstrap.parse().expect("bootstrap's pid");
    test.mark = Some(mark.to_owned());
    test.dir = Some(PathBuf::from(dir));
    let running = procs::with_env(s3res_testkit::system::MARK_ENV, mark);
    // bootstrap, source, voter, three replicas, sink.
    assert!(running.len() >= 7, "the system is not running: {running:?}");

    s3res_testkit::kill_pid(test.child.id() as i32, libc::SIGKILL).expect("kill the test process");
    let status = test.child.wait().expect("reaping the test process");
    assert_eq!(
        std::os::unix::process::ExitStatusExt::signal(&status),
        Some(libc::SIGKILL),
        "the second test process ended before it was killed: {status}"
    );
    let start = Instant::now();
    loop {
        let left: Vec<_> = procs::with_env(s3res_testkit::system::MARK_ENV, mark)
            .into_iter()
            .filter(|p| !p.is_zombie())
            .collect();
        if left.is_empty() {
            break;
        }
        assert!(
            start.elapsed() < Duration::from_secs(10),
            "10 s after its test process was killed, its system still runs: {left:?}"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
    eprintln!(
        "every process of the system (bootstrap {bootstrap}) gone {:?} after its test process was killed",
        start.elapsed()
    );
}

/// A voter that stops (SIGSTOP) no longer turns its loop, and its heartbeat stands still:
/// bootstrap kills it after the deadline its plan allows and starts a successor that adopts
/// the replicas; the run then completes with every frame delivered once, in order, the echo's
/// state continuous, and nothing left. (Before the heartbeat the system hung without a word;
/// before voter restarts it stopped.)
#[test]
fn a_stopped_voter_is_replaced_and_the_run_completes() {
    const COUNT: u32 = 3000;
    let sys = System::new();
    let echo = format!(
        r#"{{ "exec": "s3res-echo", "args": ["--stateful"], "redundancy": "tmr", "timeout_us": {TIMEOUT_US} }}"#
    );
    let summary = sys.path("summary.json");
    let desc = echo_pipeline(&summary, &echo, COUNT, 500);
    let mut run = sys.start(&desc);
    run.wait_for_replicas("echo", 3);
    std::thread::sleep(Duration::from_millis(500));
    let voter = run.process_named("s3res-voter").expect("the echo's voter");
    s3res_testkit::kill_pid(voter, libc::SIGSTOP).expect("stop the voter");
    let restart = run.wait_for_event(
        |e| e.kind == EventKind::VoterRestart,
        Duration::from_secs(60),
    );
    let out = run.wait(Duration::from_secs(60));
    assert!(
        out.status.success(),
        "bootstrap: {}\n{}",
        out.status,
        s3res_testkit::tail(&out.stderr, 30)
    );
    let line = format!("the voter of component echo (pid {voter}) died: made no progress for");
    let found = out
        .stderr
        .lines()
        .find(|l| l.contains(&line))
        .unwrap_or_else(|| {
            panic!(
                "no line {line:?}:\n{}",
                s3res_testkit::tail(&out.stderr, 30)
            )
        });
    assert!(
        found.contains("(it is stopped); started voter pid"),
        "{found}"
    );
    assert_ne!(restart.pid, Some(voter), "{restart:?}");
    assert!(
        restart
            .detail
            .as_deref()
            .unwrap_or("")
            .contains("3 of 3 replicas adopted"),
        "{restart:?}"
    );
    assert_sink_whole(&summary, COUNT);
    run.assert_nothing_left();
}

/// A fork child is its donor's child, not the voter's, so `waitpid` cannot tell the voter how
/// it ended; its pidfd can (Linux 6.15+). Its crash event names the signal that killed it.
#[test]
#[cfg_attr(
    not(s3res_pidfd_exit),
    ignore = "needs Linux 6.15+ (a non-parent learns an exit status from the pidfd)"
)]
fn a_fork_child_that_crashes_is_reported_with_its_signal() {
    let sys = System::new();
    let desc = long_running(&sys);
    let mut run = sys.start(&desc);
    run.wait_for_replicas("echo", 3);
    let old = run.replica_pids("echo")[&1];
    s3res_testkit::kill_pid(old, libc::SIGKILL).expect("kill replica 1");
    let rec = run.wait_for_recovery("echo", 1, old);
    assert_eq!(rec.method, Some(RecoveryMethod::Fork), "{rec:?}");
    let child = rec.new_pid.expect("the child's pid");
    s3res_testkit::kill_pid(child, libc::SIGABRT).expect("abort the fork child");
    let crash = run.wait_for_event(
        |e| e.kind == EventKind::Crash && e.pid == Some(child),
        Duration::from_secs(10),
    );
    assert_eq!(crash.signal, Some(libc::SIGABRT), "{crash:?}");
    run.stop();
}

/// A component that cannot run: its description's echo is `echo`, the rest of the pipeline as
/// usual. The system must end on its own, non-zero, with one line that names the component
/// and why, after at most `max_restarts` (10) restarts by exec — not restart forever.
fn cannot_run(echo: &str, why: &[&str]) -> String {
    cannot_run_as(echo, |desc| desc, why)
}

/// The voter's line that says the echo failed on its restart budget.
fn budget_line(stderr: &str) -> &str {
    stderr
        .lines()
        .find(|l| l.contains("failed beyond recovery: component echo restarted a replica by exec"))
        .unwrap_or_else(|| {
            panic!(
                "no line names the failed component:\n{}",
                s3res_testkit::tail(stderr, 30)
            )
        })
}

/// [`cannot_run`], with the pipeline's description changed by `edit` first.
fn cannot_run_as(echo: &str, edit: impl FnOnce(String) -> String, why: &[&str]) -> String {
    let sys = System::new();
    let desc = edit(echo_pipeline(
        &sys.path("summary.json"),
        echo,
        100_000,
        1000,
    ));
    let mut run = sys.start(&desc);
    let start = Instant::now();
    let out = run.wait(Duration::from_secs(60));
    let took = start.elapsed();
    eprintln!("ended {took:?} after start: {}", out.status);
    assert!(
        !out.status.success(),
        "a component that cannot run: {}",
        out.status
    );
    let line = budget_line(&out.stderr);
    for w in why {
        assert!(line.contains(w), "{w:?} not in {line:?}");
    }
    // The budget: never more than 10 restarts by exec within one second.
    let at: Vec<u64> = out
        .events
        .iter()
        .filter(|e| e.kind == EventKind::Recovery && e.method == Some(RecoveryMethod::Exec))
        .map(|e| e.ts_ns)
        .collect();
    eprintln!("{} restarts by exec", at.len());
    for (k, &t) in at.iter().enumerate() {
        let within = at[k..]
            .iter()
            .take_while(|&&u| u - t <= 1_000_000_000)
            .count();
        assert!(within <= 10, "{within} restarts by exec within one second");
    }
    run.assert_nothing_left();
    line.to_owned()
}

#[test]
fn a_replica_that_panics_at_every_start_fails_the_component_in_one_line() {
    // The panic report is relayed whole, every line behind its replica's prefix; the budget's
    // line quotes its last line.
    cannot_run(
        &format!(
            r#"{{ "exec": "s3res-misbehave", "args": ["--mode", "panic", "--replica", "0,1,2", "--at", "0"], "redundancy": "tmr", "timeout_us": {TIMEOUT_US} }}"#
        ),
        &[
            "exited with status 101",
            "max_restarts 10",
            "its last stderr line",
        ],
    );
}

#[test]
fn a_program_that_does_not_speak_the_protocol_fails_the_component_in_one_line() {
    cannot_run(
        &format!(r#"{{ "exec": "cat", "redundancy": "tmr", "timeout_us": {TIMEOUT_US} }}"#),
        // One line that says so and names the three ways to protect a program.
        &[
            "completed the s3res start (its runtime's init never ran)",
            "does not speak the s3res protocol",
            "link replica-rt",
            "libs3res_replica_c",
            "\"runtime\": \"preload\"",
        ],
    );
}

/// A program that neither speaks the protocol nor exits (`sleep`): each replica misses its start
/// deadline without the start handshake; the component fails within its budget, in one line
/// that says the runtime never started.
#[test]
fn a_program_that_hangs_without_starting_the_runtime_fails_in_one_line() {
    cannot_run(
        &format!(
            r#"{{ "exec": "sleep", "args": ["1000"], "redundancy": "tmr", "timeout_us": {TIMEOUT_US} }}"#
        ),
        &[
            "none of its replicas ever answered",
            "its runtime's init never ran",
            "does not speak the s3res protocol",
        ],
    );
}

/// A program that speaks the protocol (its runtime starts: the start handshake says so) but
/// never answers is not told that it does not speak it: the line quotes what it said.
#[test]
fn a_program_that_starts_but_never_answers_is_not_told_it_does_not_speak_the_protocol() {
    let line = cannot_run(
        &format!(
            r#"{{ "exec": "s3res-misbehave", "args": ["--mode", "spin", "--replica", "0,1,2", "--at", "0"], "redundancy": "tmr", "timeout_us": {TIMEOUT_US} }}"#
        ),
        &["hang", "its last stderr line", "misbehaving now"],
    );
    assert!(!line.contains("does not speak"), "{line}");
}

#[test]
fn a_misspelled_port_fails_the_component_in_one_line() {
    // The echo opens `in`; the channels call its input `inn`. Its error report says so in
    // its cause (anyhow's `Caused by:`), which the line quotes with the error.
    cannot_run_as(
        &format!(r#"{{ "exec": "s3res-echo", "redundancy": "tmr", "timeout_us": {TIMEOUT_US} }}"#),
        |desc| desc.replace("\"echo.in\"", "\"echo.inn\""),
        &["exited with status 1", "no input port named \"in\""],
    );
}

/// A replica forked from a donor that had already said its error, and that dies without a
/// word of its own, is quoted with what its donor said: the child's memory is its donor's.
/// (Before, the restart budget's line quoted nothing when the last fault was such a child: a
/// misspelled port's replicas, forked while they symbolized their backtraces, failed so one
/// run in about fifty.) Replica 1 says its last words at frame 20 and answers on; replica 0,
/// killed, is forked from it; replica 1's own process exits silently at frame 120, replaced
/// by a fork of replica 0's child; at frame 220 both fork descendants exit silently, and the
/// budget (max_restarts 1) ends the component.
#[test]
fn a_fork_child_that_dies_without_a_word_is_quoted_with_what_its_donor_said() {
    let sys = System::new();
    let misbehave = format!(
        r#"{{ "exec": "s3res-misbehave", "args": ["--mode", "last-words", "--replica", "1", "--at", "20"], "redundancy": "dmr", "timeout_us": {TIMEOUT_US}, "max_restarts": 1 }}"#
    );
    // 25 frames a second: 4 s between the last words and the donor's exit, to kill and fork.
    let desc = echo_pipeline(&sys.path("summary.json"), &misbehave, 100_000, 25);
    let mut run = sys.start(&desc);
    run.wait_for_replicas("echo", 2);
    let pids = run.replica_pids("echo");
    let said = format!(
        "[echo#1 pid {}] Error: misbehaving on purpose: last words",
        pids[&1]
    );
    let deadline = Instant::now() + Duration::from_secs(30);
    while !run.stderr().contains(&said) {
        if run.try_status().is_some() || Instant::now() >= deadline {
            let out = run.wait(Duration::from_secs(10));
            panic!(
                "replica 1 never said its last words:\n{}",
                s3res_testkit::tail(&out.stderr, 30)
            );
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    s3res_testkit::kill_pid(pids[&0], libc::SIGKILL).expect("kill replica 0");
    let rec = run.wait_for_recovery("echo", 0, pids[&0]);
    assert_eq!(
        rec.donor,
        Some(1),
        "replica 0 forked from replica 1: {rec:?}"
    );
    let out = run.wait(Duration::from_secs(60));
    assert!(!out.status.success(), "{}", out.status);
    let line = budget_line(&out.stderr);
    // The fault it quotes is a fork descendant's, not replica 1's first process.
    assert!(!line.contains(&format!("pid {} ", pids[&1])), "{line}");
    assert!(
        line.contains("exited with status 1")
            && line.contains("its last stderr line: Error: misbehaving on purpose: last words"),
        "{line}"
    );
    run.assert_nothing_left();
}

/// Every line a replica writes to stderr reaches bootstrap's stderr behind
/// `[component#slot pid N]`, written by the voter: a fork child under its own slot and pid,
/// not its donor's. (`-v` makes the replicas log at debug, so the child's injection hook says
/// something.)
#[test]
fn a_fork_child_logs_under_its_own_slot() {
    let count = 4000;
    let sys = System::new().arg("-v");
    let echo = format!(
        r#"{{ "exec": "s3res-echo", "args": ["--stateful"], "redundancy": "tmr", "timeout_us": {TIMEOUT_US} }}"#
    );
    let desc = echo_pipeline(&sys.path("summary.json"), &echo, count, 1000);
    let mut run = sys.start(&desc);
    run.wait_for_replicas("echo", 3);
    let old = run.replica_pids("echo")[&1];
    s3res_testkit::kill_pid(old, libc::SIGKILL).expect("kill replica 1");
    let rec = run.wait_for_recovery("echo", 1, old);
    let child = rec.new_pid.expect("the child's pid");
    assert_eq!(rec.donor, Some(0), "{rec:?}");
    // The child flips a bit of its next frame and logs it (debug): outvoted, and a line.
    s3res_testkit::sigqueue(child, s3res_testkit::signals::INJECT_SDC, 3).expect("sigqueue");
    run.wait_for_event(
        |e| e.kind == EventKind::Sdc && e.pid == Some(child),
        Duration::from_secs(20),
    );
    let out = run.wait(Duration::from_secs(90));
    assert!(out.status.success(), "{}", out.status);
    let own = format!("[echo#1 pid {child}] ");
    let donors = format!("[echo#0 pid {child}] ");
    let lines: Vec<&str> = out
        .stderr
        .lines()
        .filter(|l| l.contains("injected SDC"))
        .collect();
    assert!(
        lines.iter().any(|l| l.starts_with(&own)),
        "no line of the child under {own:?}: {lines:#?}"
    );
    assert!(
        !out.stderr.contains(&donors),
        "the child logged under its donor's slot"
    );
}

/// One Ctrl-C, as a terminal sends it (SIGINT to the whole process group) and as a wrapper
/// such as timeout(1) forwards it once more to bootstrap, is one stop: every component gets its
/// SIGTERM and the time to act on it, and no voter warns that someone else stopped it. Before,
/// the copy was taken for a second stop (every component SIGKILLed at once, its trap cut
/// short), and each voter warned "stop requested, not by bootstrap".
#[test]
fn one_ctrl_c_forwarded_by_a_wrapper_is_one_stop() {
    // The trap takes half a second to save its work.
    let (mut run, flag) = start_with_trapper("sleep 0.5; echo caught > \"$1\"; exit 0");
    s3res_testkit::kill_pid(-run.pgid(), libc::SIGINT).expect("SIGINT to the group");
    // Once bootstrap has taken the first (two pending at once would be one to the kernel),
    // the copy, at once.
    s3res_testkit::wait_until("bootstrap stopping", Duration::from_secs(20), || {
        run.stderr()
            .contains("stopping (signal SIGINT)")
            .then_some(())
    });
    s3res_testkit::kill_pid(run.pid(), libc::SIGINT).expect("SIGINT forwarded");
    let out = run.wait(Duration::from_secs(60));
    assert_eq!(
        out.status.code(),
        Some(130),
        "{}",
        s3res_testkit::tail(&out.stderr, 20)
    );
    assert_eq!(
        std::fs::read_to_string(&flag).ok().as_deref(),
        Some("caught\n"),
        "the component's SIGTERM trap was cut short: {}",
        s3res_testkit::tail(&out.stderr, 20)
    );
    for said in ["second stop signal", "not by bootstrap"] {
        assert!(
            !out.stderr.contains(said),
            "{said:?}: {}",
            s3res_testkit::tail(&out.stderr, 20)
        );
    }
    run.assert_nothing_left();
}

/// A voter whose bootstrap is gone before it asks for its parent-death signal again (here: it
/// is told a bootstrap pid that is not its parent) stops at once, as that signal would have
/// stopped it. Before, it logged that it stopped, then ran its replicas on for as long as its
/// input lasted (a review found this).
#[test]
fn a_voter_whose_bootstrap_is_gone_at_start_stops() {
    let (read_end, write_end) = std::io::pipe().expect("a pipe for bootstrap's stdin");
    let sys = System::new().stdin_pipe(std::os::fd::OwnedFd::from(read_end));
    let wrapper = sys.path("voter.sh");
    std::fs::write(
        &wrapper,
        format!(
            "#!/bin/sh\nS3RES_SUPERVISOR_PID=2147483647 exec {} \"$@\"\n",
            s3res_testkit::bin_path("s3res-voter").display()
        ),
    )
    .unwrap();
    std::fs::set_permissions(
        &wrapper,
        std::os::unix::fs::PermissionsExt::from_mode(0o755),
    )
    .unwrap();
    let sys = sys.env("S3RES_VOTER", &wrapper);
    let desc = format!(
        r#"{{ "name": "orphaned",
  "components": {{ "echo": {{ "exec": "s3res-echo", "redundancy": "tmr", "timeout_us": {TIMEOUT_US} }} }},
  "channels": [ {{ "from": "stdin", "to": "echo.in" }}, {{ "from": "echo.out", "to": "stdout" }} ] }}"#
    );
    let mut run = sys.start(&desc);
    // Its input stays open (the test holds the pipe): only the stop ends it.
    let out = run.wait(Duration::from_secs(30));
    drop(write_end);
    assert!(
        out.stderr
            .contains("bootstrap is gone before this voter started: stopping"),
        "{}",
        s3res_testkit::tail(&out.stderr, 20)
    );
    run.assert_nothing_left();
}

/// `SigBlk` of a process: the signals it blocks, one bit per signal (bit `n - 1` for `n`).
fn blocked_signals(pid: i32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).expect("its status");
    let hex = status
        .lines()
        .find_map(|l| l.strip_prefix("SigBlk:"))
        .expect("a SigBlk line");
    u64::from_str_radix(hex.trim(), 16).expect("hex")
}

fn bit(sig: i32) -> u64 {
    1 << (sig - 1)
}

/// A component catches the SIGTERM that stops it, and the processes s3res starts (a
/// component, a voter's replicas) block only the signals a terminal sends its whole
/// foreground group. Before, they inherited bootstrap's and the voter's masks (SIGTERM and
/// SIGCHLD blocked for their signalfds; `std::process::Command` passes the mask on): a
/// component's SIGTERM trap never ran, every stop waited out the stop timeout and SIGKILLed
/// the components, and what a component started could not be stopped with a plain `kill`.
#[test]
fn a_component_catches_the_sigterm_that_stops_it() {
    let (mut run, flag) = start_with_trapper("echo caught > \"$1\"; exit 0");
    let terminal = bit(libc::SIGHUP) | bit(libc::SIGINT) | bit(libc::SIGQUIT);
    // The source (Rust, no signal handling of its own) blocks exactly the terminal's signals.
    let source = run.process_named("s3res-source").expect("the source");
    assert_eq!(
        blocked_signals(source),
        terminal,
        "the source (pid {source}) blocks {:#x}",
        blocked_signals(source)
    );
    // bash blocks SIGCHLD of its own at moments; SIGTERM is what the trap needs.
    let trapper = run.process_named("trapper.sh").expect("the trapper");
    let blocked = blocked_signals(trapper);
    assert_eq!(
        blocked & bit(libc::SIGTERM),
        0,
        "trapper (pid {trapper}) blocks {blocked:#x}"
    );
    // A replica's life is its voter's: SIGTERM blocked too, SIGCHLD not.
    for (slot, pid) in run.replica_pids("echo") {
        let blocked = blocked_signals(pid);
        assert_eq!(
            blocked & (bit(libc::SIGTERM) | bit(libc::SIGCHLD) | terminal),
            terminal | bit(libc::SIGTERM),
            "echo#{slot} (pid {pid}) blocks {blocked:#x}"
        );
    }
    run.stop();
    let out = run.wait(Duration::from_secs(60));
    assert_eq!(
        std::fs::read_to_string(&flag).ok().as_deref(),
        Some("caught\n"),
        "the component's SIGTERM trap did not run: {}",
        s3res_testkit::tail(&out.stderr, 20)
    );
    assert!(
        !out.stderr.contains("after SIGTERM; killing them"),
        "{}",
        s3res_testkit::tail(&out.stderr, 20)
    );
    run.assert_nothing_left();
}

/// Whether the trapper has set its trap (it touches `FLAG.ready` after).
/// The long-running echo pipeline with one more component, `trapper.sh`: a bash script whose
/// SIGTERM trap runs `on_term` (`$1` is the flag file to write), started and its trap set.
/// Returns the system and the flag's path.
fn start_with_trapper(on_term: &str) -> (s3res_testkit::RunningSystem, PathBuf) {
    let sys = System::new();
    let flag = sys.path("stopped");
    let script = sys.path("trapper.sh");
    std::fs::write(
        &script,
        format!(
            "#!/bin/bash\ntrap '{on_term}' TERM\n: > \"$1.ready\"\nwhile :; do sleep 0.05; done\n"
        ),
    )
    .unwrap();
    std::fs::set_permissions(&script, std::os::unix::fs::PermissionsExt::from_mode(0o755)).unwrap();
    let mut desc: serde_json::Value =
        serde_json::from_str(&long_running(&sys)).expect("the pipeline is JSON");
    desc["components"]["trapper"] = serde_json::json!({
        "exec": script.display().to_string(),
        "args": [flag.display().to_string()],
    });
    let mut run = sys.start_json(&desc);
    run.wait_for_replicas("echo", 3);
    s3res_testkit::wait_until("the trap set", Duration::from_secs(20), || trap_set(&flag));
    (run, flag)
}

fn trap_set(flag: &Path) -> Option<()> {
    let mut ready = flag.as_os_str().to_owned();
    ready.push(".ready");
    Path::new(&ready).exists().then_some(())
}

/// A voter stopped by a signal that bootstrap did not send (a stray `kill`) ends its component
/// alone: it says so, naming the sender, and bootstrap stops the system naming that component.
/// Before, the voter exited 0 as if bootstrap had stopped it, no successor came, and the
/// verdict named only the components starved by it (the source's broken pipe, the sink's
/// missing frames).
#[test]
fn a_voter_stopped_by_a_stray_signal_is_named() {
    let sys = System::new();
    let desc = long_running(&sys);
    let mut run = sys.start(&desc);
    run.wait_for_replicas("echo", 3);
    let voter = run.voter_of("echo").expect("the voter");
    s3res_testkit::kill_pid(voter, libc::SIGTERM).expect("SIGTERM to the voter");
    let out = run.wait(Duration::from_secs(60));
    let me = std::process::id();
    assert!(!out.status.success(), "{}", out.status);
    assert!(
        out.stderr.contains(&format!(
            "s3res-voter: component echo stopped: its voter got signal 15 from pid {me}"
        )),
        "{}",
        s3res_testkit::tail(&out.stderr, 20)
    );
    assert!(
        out.stderr
            .contains(&format!("the voter of component echo (pid {voter})")),
        "{}",
        s3res_testkit::tail(&out.stderr, 20)
    );
    run.assert_nothing_left();
}

/// A round that no replica answers (all three stopped) sends nothing downstream: that frame is
/// lost, and says so — a `lost` event naming the output and the round, and the verdict's
/// frames line. Before, only a log line said it, and the verdict read "0 withheld".
#[test]
fn a_round_no_replica_answered_is_counted_as_a_frame_lost() {
    let sys = System::new();
    let desc = long_running(&sys);
    let mut run = sys.start(&desc);
    // Every replica's runtime runs, none is held to its start deadline.
    wait_for_rounds(&mut run);
    // The source waits while the replicas are stopped one by one (after any round under way
    // has ended): a round begun meanwhile could be answered by some of them, and the rest
    // blamed, never a round that nobody answers.
    let source = run.process_named("s3res-source").expect("the source");
    s3res_testkit::kill_pid(source, libc::SIGSTOP).expect("SIGSTOP the source");
    std::thread::sleep(Duration::from_millis(100));
    let pids: Vec<i32> = run.replica_pids("echo").into_values().collect();
    for &pid in &pids {
        s3res_testkit::kill_pid(pid, libc::SIGSTOP).expect("SIGSTOP a replica");
    }
    s3res_testkit::kill_pid(source, libc::SIGCONT).expect("SIGCONT the source");
    let lost = run.wait_for_event(
        |e| e.kind == EventKind::Lost && e.component == "echo",
        Duration::from_secs(30),
    );
    for &pid in &pids {
        let _ = s3res_testkit::kill_pid(pid, libc::SIGCONT);
    }
    assert_eq!(lost.output.as_deref(), Some("out"), "{lost:?}");
    assert!(lost.round.is_some(), "{lost:?}");
    run.stop();
    let out = run.wait(Duration::from_secs(60));
    assert!(
        out.stderr.contains("lost (no replica answered)"),
        "{}",
        s3res_testkit::tail(&out.stderr, 20)
    );
    run.assert_nothing_left();
}

/// Waits until the echo pipeline's replicas run and its sink has read a hundred frames more
/// (20 bytes each) than when they did.
fn wait_for_rounds(run: &mut s3res_testkit::RunningSystem) {
    run.wait_for_replicas("echo", 3);
    let sink = run.process_named("s3res-sink").expect("the sink");
    let before = bytes_read(sink).expect("the sink's /proc/PID/io");
    s3res_testkit::wait_until("rounds answered", Duration::from_secs(30), || {
        (bytes_read(sink)? >= before + 2000).then_some(())
    });
}

/// Bytes process `pid` has read (`rchar` of `/proc/PID/io`), if it can be read.
fn bytes_read(pid: i32) -> Option<u64> {
    let io = std::fs::read_to_string(format!("/proc/{pid}/io")).ok()?;
    io.lines()
        .find_map(|l| l.strip_prefix("rchar:"))?
        .trim()
        .parse()
        .ok()
}

/// A SIGTERM to the whole process group (what `timeout`, `pkill -g` or a batch system send)
/// reaches bootstrap and everything it started at once: the system stops in order, as on
/// bootstrap's own SIGTERM (status 143) — no replica dies of it behind its voter's back, no
/// component killed by it counts as failed, and no voter calls it a stray stop.
#[test]
fn a_sigterm_to_the_whole_group_stops_the_system_in_order() {
    let sys = System::new();
    let desc = long_running(&sys);
    let mut run = sys.start(&desc);
    wait_for_rounds(&mut run);
    s3res_testkit::kill_pid(-run.pgid(), libc::SIGTERM).expect("SIGTERM to the group");
    let out = run.wait(Duration::from_secs(60));
    let tail = s3res_testkit::tail(&out.stderr, 30);
    assert_eq!(out.status.code(), Some(143), "{tail}");
    assert!(!out.stderr.contains("not from bootstrap"), "{tail}");
    assert!(!out.stderr.contains(" failed: "), "{tail}");
    let faults: Vec<_> = out.events.iter().filter(|e| e.kind.is_fault()).collect();
    assert!(faults.is_empty(), "{faults:#?}\n{tail}");
    run.assert_nothing_left();
}
