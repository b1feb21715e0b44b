//! Unmodified programs (`"runtime": "preload"`, `"framing": "lines"`): programs nobody here
//! wrote — `awk`, `python3 -u`, and a C filter compiled from one file — each keeping a running
//! sum of the numbers it reads on stdin and printing it on stdout, protected under TMR and DMR
//! by the real bootstrap and voter with the preload library injected. Under ≥ 30 SIGKILLs and
//! ≥ 10 SIGSTOPs (and register flips under TMR) every line reaches the end of the pipeline once,
//! in order, and the sums are continuous: the state survived every recovery by fork.
//!
//! Also: what cannot be protected this way is refused with a reason — a statically linked
//! program at `--check`, and a program that starts a second thread at its first recovery.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::Mutex;
use std::time::Duration;

use s3res_testkit::{bin_path, EventKind, RecoveryMethod, Rng, RunningSystem, System};
use serde_json::{json, Value};

const LIMIT: Duration = Duration::from_secs(180);
/// Numbers fed per run, and how fast: long enough for every fault to land mid-stream.
const NUMBERS: u64 = 6000;
const HZ: u64 = 250;
/// Faults per run (the issue asks for at least 30 kills and 10 stops).
const KILLS: usize = 30;
const STOPS: usize = 10;
const REG_FLIPS: usize = 10;

/// One system at a time: three replicas, a voter and two Python helpers already fill the two
/// cores of CI, and a second system beside them only adds hangs that are the machine's.
static ONE_AT_A_TIME: Mutex<()> = Mutex::new(());

/// Feeds `n` numbers (1, 2, 3, ...) as text frames on fd 3 (its port `out`) at `hz`.
const FEED_PY: &str = include_str!("../../scripts/sums/feed.py");

/// Writes each frame arriving on fd 3 (its port `in`) as a line of the file `argv[1]`, as
/// the channel protocol says a reader does: a voter's successor goes on behind `RESUME k`, and
/// a frame numbered below those already written is a repeat, dropped.
const COLLECT_PY: &str = include_str!("../../scripts/sums/collect.py");

/// The Python program under test: a counter of what it has read, printed per line.
const COUNT_PY: &str = r#"
import sys
total = 0
for line in sys.stdin:
    total += int(line)
    print(total)
"#;

/// The C program under test, compiled by the test with the system's C compiler.
const SUM_C: &str = r#"
#include <stdio.h>
#include <stdlib.h>

int main(void) {
    char line[256];
    long long sum = 0;
    while (fgets(line, sizeof line, stdin)) {
        sum += atoll(line);
        printf("%lld\n", sum);
    }
    return 0;
}
"#;

/// A Python program that starts a second thread once it has answered: a fork would copy only
/// one of them, so its first recovery must be refused.
const THREADED_PY: &str = r#"
import sys, threading, time
total = 0
started = False
for line in sys.stdin:
    total += int(line)
    print(total)
    if not started:
        threading.Thread(target=lambda: time.sleep(3600), daemon=True).start()
        started = True
"#;

/// A threaded Python program whose state is the first number it read, and which answers
/// `True` only for the number 100 after it: a replica started afresh (whose first number is a
/// later one) matches the others' `False` until their hundred-and-first line, then differs
/// once. (It was 10: at 250 lines a second, a Python started afresh on a loaded machine came
/// in after the others' eleventh line, never matched, and the scenario was another one.)
const THREADED_FIRST_PY: &str = r#"
import sys, threading, time
first = None
started = False
for line in sys.stdin:
    n = int(line)
    if first is None:
        first = n
    print(n - first == 100)
    if not started:
        threading.Thread(target=lambda: time.sleep(3600), daemon=True).start()
        started = True
"#;

/// A Python program that echoes each line, with a second thread once it has answered: no
/// state, so a replica started afresh matches the others at once. A replica whose pid names a
/// file in the folder given as its argument answers `wrong` instead (a fault, on cue).
const THREADED_ECHO_PY: &str = r#"
import os, sys, threading, time
cue = sys.argv[1]
started = False
for line in sys.stdin:
    if os.path.exists(os.path.join(cue, str(os.getpid()))):
        print("wrong")
    else:
        print(line.strip())
    if not started:
        threading.Thread(target=lambda: time.sleep(3600), daemon=True).start()
        started = True
"#;

/// Starts the Python `script` (with `args`) as the TMR component `sum`, fed `lines` lines;
/// once it has answered 5 (and so runs two threads), SIGKILLs replica 1 and waits for its
/// restart, by exec with the state lost (no donor can fork). Returns the run, the killed pid
/// and the new one.
fn threaded_restarted_by_exec(
    sys: System,
    script: &str,
    args: &[String],
    lines: u64,
) -> (RunningSystem, i32, i32) {
    std::fs::write(sys.path("program.py"), script).unwrap();
    let mut argv = vec!["-u".into(), sys.path("program.py").display().to_string()];
    argv.extend_from_slice(args);
    let desc = pipeline(&sys, (python3(), argv), "tmr", lines);
    let mut run = sys.start_json(&desc);
    run.wait_for_replicas("sum", 3);
    wait_for_sums(&run, 5);
    let pid = run.replica_pids("sum")[&1];
    s3res_testkit::kill_pid(pid, libc::SIGKILL).unwrap();
    let rec = run.wait_for_recovery("sum", 1, pid);
    assert_eq!(rec.method, Some(RecoveryMethod::Exec), "{rec:?}");
    assert_eq!(rec.state_lost, Some(true), "{rec:?}");
    let fresh = rec.new_pid.expect("the recovery names the new replica");
    (run, pid, fresh)
}

/// How many lines `collect` has written to `sums.txt` so far.
fn answered(run: &RunningSystem) -> usize {
    std::fs::read_to_string(run.path("sums.txt")).map_or(0, |t| t.lines().count())
}

/// Waits until `collect` has written `n` sums (within 30 s). An unmodified program's replica
/// may donate only once it has answered (a wrapper that execs the program drops the preload
/// library's restart handler: `Replica::may_donate`), so a fault before any answer is repaired
/// by exec with the state lost, rightly; a test that expects a fork must first let the
/// replicas answer. (A SIGKILL 5 ms after start made the repair an exec: CI, stop 59.)
fn wait_for_sums(run: &RunningSystem, n: usize) {
    s3res_testkit::wait_until(
        &format!("{n} sums collected"),
        Duration::from_secs(30),
        || (answered(run) >= n).then_some(()),
    );
}

fn python3() -> PathBuf {
    // The interpreter itself, not a version manager's shell shim (which works, but slowly).
    let system = Path::new("/usr/bin/python3");
    if system.is_file() {
        return system.to_path_buf();
    }
    which("python3").expect("python3 (the build probe found one)")
}

fn which(name: &str) -> Option<PathBuf> {
    std::env::split_paths(&std::env::var_os("PATH")?)
        .map(|d| d.join(name))
        .find(|p| p.is_file())
}

/// `awk` and the arguments that make it answer line by line: mawk (Debian's default) reads
/// its input in blocks unless `-W interactive`.
fn awk_program() -> (PathBuf, Vec<String>) {
    let awk = which("awk").expect("awk (the build probe found one)");
    let version = Command::new(&awk)
        .args(["-W", "version"])
        .stdin(Stdio::null())
        .output()
        .map(|o| String::from_utf8_lossy(&o.stdout).into_owned())
        .unwrap_or_default();
    let mut args = Vec::new();
    if version.contains("mawk") {
        args.extend(["-W".to_owned(), "interactive".to_owned()]);
    }
    args.push("{ s += $1; print s }".to_owned());
    (awk, args)
}

/// The program under test: its executable and arguments, given the system's folder.
#[derive(Clone, Copy)]
enum Program {
    Awk,
    Python,
    C,
}

impl Program {
    fn command(self, sys: &System) -> (PathBuf, Vec<String>) {
        match self {
            Program::Awk => awk_program(),
            Program::Python => {
                std::fs::write(sys.path("count.py"), COUNT_PY).unwrap();
                (
                    python3(),
                    vec!["-u".into(), sys.path("count.py").display().to_string()],
                )
            }
            Program::C => (compile_c(sys, "sum", SUM_C, &[]), Vec::new()),
        }
    }
}

/// Compiles `source` with `cc` into the system's folder; returns the executable.
fn compile_c(sys: &System, name: &str, source: &str, flags: &[&str]) -> PathBuf {
    let src = sys.path(&format!("{name}.c"));
    let exe = sys.path(name);
    std::fs::write(&src, source).unwrap();
    let out = Command::new("cc")
        .args(flags)
        .arg("-O1")
        .arg("-o")
        .arg(&exe)
        .arg(&src)
        .stdin(Stdio::null())
        .output()
        .expect("running cc");
    assert!(
        out.status.success(),
        "cc failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    exe
}

/// feed → `sum` (the program, unmodified, under `redundancy`) → collect.
fn pipeline(sys: &System, program: (PathBuf, Vec<String>), redundancy: &str, n: u64) -> Value {
    pipeline_at(sys, program, redundancy, n, HZ)
}

/// [`pipeline`], fed at `hz`.
fn pipeline_at(
    sys: &System,
    program: (PathBuf, Vec<String>),
    redundancy: &str,
    n: u64,
    hz: u64,
) -> Value {
    std::fs::write(sys.path("feed.py"), FEED_PY).unwrap();
    std::fs::write(sys.path("collect.py"), COLLECT_PY).unwrap();
    let py = python3().display().to_string();
    json!({
        "name": "unmodified",
        "components": {
            "feed": {"exec": py, "args": [sys.path("feed.py"), n.to_string(), hz.to_string()]},
            "sum": {
                "exec": program.0,
                "args": program.1,
                "runtime": "preload",
                "framing": "lines",
                "redundancy": redundancy,
                "timeout_us": 300000
            },
            "collect": {"exec": py, "args": [sys.path("collect.py"), sys.path("sums.txt")]}
        },
        "channels": [
            {"from": "feed.out", "to": "sum.in"},
            {"from": "sum.out", "to": "collect.in"}
        ]
    })
}

/// Every running sum, once and in order: line k is 1 + 2 + ... + k.
fn assert_sums_continuous(run: &RunningSystem, n: u64) {
    let text = std::fs::read_to_string(run.path("sums.txt")).expect("collect wrote sums.txt");
    let got: Vec<&str> = text.lines().collect();
    for (k, line) in got.iter().enumerate() {
        let k = k as u64 + 1;
        assert_eq!(
            line.parse::<u64>().ok(),
            Some(k * (k + 1) / 2),
            "line {k} of {}: {line:?} (the running sum broke or a line was lost or repeated)",
            got.len()
        );
    }
    assert_eq!(got.len() as u64, n, "every number answered once");
}

/// SIGKILLs and SIGSTOPs, in a seeded order, each into a random replica once the previous one
/// is repaired, every repair by fork with the state kept.
fn kill_and_stop(run: &mut RunningSystem, rng: &mut Rng, replicas: usize) {
    let mut faults: Vec<i32> = [vec![libc::SIGKILL; KILLS], vec![libc::SIGSTOP; STOPS]].concat();
    for i in (1..faults.len()).rev() {
        faults.swap(i, rng.below(i as u64 + 1) as usize);
    }
    for sig in faults {
        let slot = rng.below(replicas as u64) as usize;
        let pid = run.replica_pids("sum")[&slot];
        s3res_testkit::kill_pid(pid, sig).expect("signal a replica");
        let rec = run.wait_for_recovery("sum", slot, pid);
        assert_eq!(rec.method, Some(RecoveryMethod::Fork), "{rec:?}");
        assert_eq!(rec.state_lost, Some(false), "{rec:?}");
        std::thread::sleep(Duration::from_millis(rng.range(20, 120)));
    }
}

/// One `s3res-inject inject` into replica `slot` of `sum`, with `fault` (its `--fault` and
/// options); it must succeed. The live view can still name a replica that has just died (a
/// register flip that crashed it a moment later, its replacement not yet in the view):
/// `s3res-inject` then refuses, rightly, and the injection is tried again, at most three
/// times, 200 ms apart.
fn inject(state: &Path, slot: usize, fault: &[&str]) {
    let mut tries = 0;
    loop {
        let out = Command::new(bin_path("s3res-inject"))
            .args(["inject", "--state"])
            .arg(state)
            .args(["--component", "sum", "--replica"])
            .arg(slot.to_string())
            .args(fault)
            .stdin(Stdio::null())
            .output()
            .expect("running s3res-inject");
        if out.status.success() {
            return;
        }
        tries += 1;
        let why = String::from_utf8_lossy(&out.stderr);
        assert!(tries < 3, "s3res-inject {fault:?}, {tries} tries: {why}");
        eprintln!("s3res-inject {fault:?} refused (try {tries}): {why}");
        std::thread::sleep(Duration::from_millis(200));
    }
}

/// Register flips through `s3res-inject --fault reg` (ptrace; works on any process). Whatever
/// each does — nothing, a crash, a hang, a wrong sum — TMR masks it.
fn flip_registers(run: &mut RunningSystem, rng: &mut Rng, state: &Path) {
    for _ in 0..REG_FLIPS {
        let slot = rng.below(3);
        let seed = rng.next_u64() % 1_000_000;
        inject(
            state,
            slot as usize,
            &["--fault", "reg", "--seed", &seed.to_string()],
        );
        // Give the flip time to show (or not) before the next one: one fault at a time.
        std::thread::sleep(Duration::from_millis(rng.range(300, 500)));
        run.wait_for_replicas("sum", 3);
    }
}

/// SDC injections (`--fault sdc`): the library flips a bit of the next line the program writes
/// through `write`; the voter outvotes the line and replaces the replica.
fn corrupt_lines(run: &mut RunningSystem, rng: &mut Rng, state: &Path, n: usize) {
    for _ in 0..n {
        let slot = rng.below(3) as usize;
        let pid = run.replica_pids("sum")[&slot];
        inject(state, slot, &["--fault", "sdc"]);
        let rec = run.wait_for_recovery("sum", slot, pid);
        assert_eq!(rec.method, Some(RecoveryMethod::Fork), "{rec:?}");
        let fault = run.events().into_iter().find(|e| {
            e.pid == Some(pid) && e.kind != EventKind::Start && e.kind != EventKind::Recovery
        });
        assert_eq!(
            fault.as_ref().map(|e| e.kind),
            Some(EventKind::Sdc),
            "{fault:?}"
        );
    }
}

fn under_fire(program: Program, redundancy: &str, replicas: usize) {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let mut rng = Rng::from_env();
    let sys = System::new();
    let state = sys.path("state.json");
    let desc = pipeline(&sys, program.command(&sys), redundancy, NUMBERS);
    let mut run = sys.arg("--state").arg(&state).start_json(&desc);
    run.wait_for_replicas("sum", replicas);
    wait_for_sums(&run, 5);
    kill_and_stop(&mut run, &mut rng, replicas);
    if replicas == 3 {
        flip_registers(&mut run, &mut rng, &state);
        if matches!(program, Program::Python) {
            corrupt_lines(&mut run, &mut rng, &state, 5);
        }
    }
    assert!(
        run.try_status().is_none(),
        "the feed ended before every fault was injected; feed more numbers"
    );
    let out = run.wait_success(LIMIT);
    for f in out.faults() {
        assert_ne!(f.kind, EventKind::RecoveryFailed, "{f:?}");
    }
    let recoveries = out
        .events
        .iter()
        .filter(|e| e.kind == EventKind::Recovery)
        .count();
    eprintln!(
        "{redundancy}: {} faults, {recoveries} recoveries",
        out.faults().len()
    );
    assert_sums_continuous(&run, NUMBERS);
}

/// SIGKILL of an unmodified program's voter, 20 times while lines flow (2000 a second, so
/// that most kills land in a round), each at a seeded random moment: a successor takes the
/// replicas over on the pipes the dead voter parked, every line reaches the end of the
/// pipeline once and in order, the running sum never breaks (no replica was given a line
/// twice or missed one, no answer was dropped or voted twice), every kill is a
/// `voter_restart` event, and the run ends cleanly with nothing left behind.
fn kill_voters_of(program: Program) {
    const LINES: u64 = 16_000;
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let sys = System::new();
    let desc = pipeline_at(&sys, program.command(&sys), "tmr", LINES, 2000);
    let mut run = kill_voters_in(sys, &desc);
    assert_sums_continuous(&run, LINES);
    run.assert_nothing_left();
}

/// Starts `desc` (its component `sum` under TMR), kills its voter 20 times (see
/// [`kill_voters_of`]), and checks that the run ended cleanly with a successor for every kill
/// that adopted all three replicas.
fn kill_voters_in(sys: System, desc: &Value) -> RunningSystem {
    const KILLS: usize = 20;
    let mut rng = Rng::from_env();
    let mut run = sys.start_json(desc);
    run.wait_for_replicas("sum", 3);
    run.kill_voter_repeatedly(&mut rng, KILLS);
    let out = run.wait(LIMIT);
    for e in out
        .events
        .iter()
        .filter(|e| !matches!(e.kind, EventKind::Start | EventKind::VoterRestart))
    {
        eprintln!("event during the kills: {e:?}");
    }
    assert!(
        out.status.success(),
        "bootstrap: {}\n{}",
        out.status,
        s3res_testkit::tail(&out.stderr, 40)
    );
    for e in out.voter_restarts(KILLS) {
        let detail = e.detail.as_deref().unwrap_or("");
        assert!(detail.contains("3 of 3 replicas adopted"), "{e:?}");
    }
    run
}

/// The same for an unmodified program that reads and writes s3res frames itself (`"framing":
/// "frames"`): `cat`, preloaded, under TMR, its voter killed 20 times. Every number comes
/// back once and in order.
#[test]
#[cfg_attr(not(s3res_python3), ignore = "needs python3")]
fn twenty_voter_kills_under_cat_reading_frames_lose_and_repeat_no_frame() {
    const FRAMES: u64 = 16_000;
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let sys = System::new();
    let cat = which("cat").expect("cat");
    let mut desc = pipeline_at(&sys, (cat, Vec::new()), "tmr", FRAMES, 2000);
    desc["components"]["sum"]["framing"] = json!("frames");
    let mut run = kill_voters_in(sys, &desc);
    assert_numbers_continuous(&run, FRAMES);
    run.assert_nothing_left();
}

/// `cat` reading s3res frames (`"framing": "frames"`) is recovered by fork like any program:
/// the library holds a restart while the last `write` ended inside a frame. (It used to wait
/// for the end of a line, which a frame seldom has: the fork waited out the recovery timeout
/// and fell back to exec.)
#[test]
#[cfg_attr(not(s3res_python3), ignore = "needs python3")]
fn cat_reading_frames_is_recovered_by_fork() {
    const FRAMES: u64 = 5000;
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let mut rng = Rng::from_env();
    let sys = System::new();
    let cat = which("cat").expect("cat");
    let mut desc = pipeline_at(&sys, (cat, Vec::new()), "tmr", FRAMES, 1000);
    desc["components"]["sum"]["framing"] = json!("frames");
    let mut run = sys.start_json(&desc);
    run.wait_for_replicas("sum", 3);
    wait_for_sums(&run, 5);
    for _ in 0..5 {
        let slot = rng.below(3) as usize;
        let pid = run.replica_pids("sum")[&slot];
        s3res_testkit::kill_pid(pid, libc::SIGKILL).expect("kill a replica");
        let rec = run.wait_for_recovery("sum", slot, pid);
        assert_eq!(rec.method, Some(RecoveryMethod::Fork), "{rec:?}");
        assert_eq!(rec.state_lost, Some(false), "{rec:?}");
        std::thread::sleep(Duration::from_millis(rng.range(50, 150)));
    }
    run.wait_success(LIMIT);
    assert_numbers_continuous(&run, FRAMES);
}

/// An unmodified program's replicas keep a spare line to their voter for their next fork child
/// (replica-rt's `restart`, "The spare line"), renewed after every fork by the preload
/// library's `write` once a line is whole. Three kills in turn, each replacement later a
/// donor or a victim itself: every child joins on its donor's line (before the renewal, the
/// second and third donors had forked already and had none: their children connected).
#[test]
#[cfg_attr(not(s3res_python3), ignore = "needs python3")]
fn every_fork_child_of_an_unmodified_program_joins_on_a_spare_line() {
    const LINES: u64 = 1500;
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let sys = System::new().env("RUST_LOG", "info,s3res_voter::recovery=debug");
    let desc = pipeline(&sys, Program::Python.command(&sys), "tmr", LINES);
    let mut run = sys.start_json(&desc);
    run.wait_for_replicas("sum", 3);
    // Answers out (every replica has made some): a donor must have answered to be asked.
    wait_for_sums(&run, 20);
    for slot in [2, 0, 2] {
        let pids = run.replica_pids("sum");
        let pid = pids[&slot];
        s3res_testkit::kill_pid(pid, libc::SIGKILL).expect("kill a replica");
        let rec = run.wait_for_recovery("sum", slot, pid);
        assert_eq!(rec.method, Some(RecoveryMethod::Fork), "{rec:?}");
        assert_eq!(rec.state_lost, Some(false), "{rec:?}");
        // Some lines (4 ms apart): donor and child write an answer, and make their lines.
        std::thread::sleep(Duration::from_millis(300));
        // The child locks its memory once it has answered (at the preload library's `write`),
        // as its donor did at start (where the donor could not, neither can the child).
        let donor = pids[&rec.donor.expect("a fork names its donor")];
        if s3res_testkit::procs::locked_kib(donor).unwrap_or(0) > 0 {
            let child = rec.new_pid.expect("new pid");
            s3res_testkit::wait_until(
                "the fork child locks its memory",
                Duration::from_secs(10),
                || (s3res_testkit::procs::locked_kib(child).unwrap_or(0) > 0).then_some(()),
            );
        }
    }
    let out = run.wait_success(LIMIT);
    s3res_testkit::assert_children_joined_on_spare_lines(&out.stderr, 3);
    assert_sums_continuous(&run, LINES);
}

/// Every number the feed sent, back once and in order (a program that echoes them).
fn assert_numbers_continuous(run: &RunningSystem, n: u64) {
    let text = std::fs::read_to_string(run.path("sums.txt")).expect("collect wrote sums.txt");
    let got: Vec<&str> = text.lines().collect();
    for (k, line) in got.iter().enumerate() {
        assert_eq!(
            line.parse::<usize>().ok(),
            Some(k + 1),
            "frame {} of {}: {line:?} (a frame was lost or repeated)",
            k + 1,
            got.len()
        );
    }
    assert_eq!(got.len() as u64, n, "every number once");
}

/// Faults in a replica and in its voter together, ten times: a replica killed, then the voter
/// 0–3 ms later (in the middle of the recovery, or before it began), so that a successor finds
/// a slot to refill while its predecessor's round is unfinished, a fork child its predecessor
/// never named, or one it named before its round was committed. Every sum once, in order,
/// continuous; every slot refilled by fork with the state kept; nothing left behind.
#[test]
#[cfg_attr(
    not(all(s3res_cc, s3res_python3)),
    ignore = "needs a C compiler and python3"
)]
fn a_replica_and_its_voter_killed_together_lose_no_line() {
    const LINES: u64 = 12_000;
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let mut rng = Rng::from_env();
    let sys = System::new();
    let desc = pipeline_at(&sys, Program::C.command(&sys), "tmr", LINES, 2000);
    let mut run = sys.start_json(&desc);
    run.wait_for_replicas("sum", 3);
    let mut voter = run.process_named("s3res-voter").expect("the voter");
    for kill in 0..10 {
        std::thread::sleep(Duration::from_millis(rng.range(150, 350)));
        let slot = rng.below(3) as usize;
        let pid = run.replica_pids("sum")[&slot];
        let gap = Duration::from_micros(rng.below(3000));
        s3res_testkit::kill_pid(pid, libc::SIGKILL).expect("kill a replica");
        std::thread::sleep(gap);
        s3res_testkit::kill_pid(voter, libc::SIGKILL).expect("kill the voter");
        voter = run.next_voter(voter, Duration::from_secs(10));
        eprintln!("kill {kill}: replica {slot} (pid {pid}), then the voter {gap:?} later");
        let deadline = std::time::Instant::now() + Duration::from_secs(10);
        while run.replica_pids("sum").get(&slot) == Some(&pid) {
            assert!(
                std::time::Instant::now() < deadline && run.try_status().is_none(),
                "replica {slot} was not refilled after kill {kill}:\n{}",
                s3res_testkit::tail(&run.stderr(), 30)
            );
            std::thread::sleep(Duration::from_millis(5));
        }
    }
    let out = run.wait_success(LIMIT);
    for e in out.events.iter().filter(|e| e.kind == EventKind::Recovery) {
        assert_eq!(e.method, Some(RecoveryMethod::Fork), "{e:?}");
        assert_eq!(e.state_lost, Some(false), "{e:?}");
    }
    out.voter_restarts(10);
    assert_sums_continuous(&run, LINES);
}

/// The voter killed in each window of the protocol that gives lines once and takes answers
/// once (docs/architecture.md, "An unmodified program's voter"), by a crash point
/// (`S3RES_VOTER_CRASH_AT`, `voter/src/crashpoint.rs`) on the 40th pass: line 14 of replica 0
/// written into its staging pipe and not journaled; journaled and not moved on; moved on and
/// that not journaled; round 14 committed and no answer taken; replica 0's take announced and
/// not read; read and not counted. Each time the successor finds what that window leaves —
/// its `voter_restart` event says what — and every sum comes once, in order, continuous.
#[test]
#[cfg_attr(
    not(all(s3res_cc, s3res_python3)),
    ignore = "needs a C compiler and python3"
)]
fn a_voter_killed_in_each_window_of_the_line_protocol_loses_nothing() {
    const LINES: u64 = 1500;
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let windows = [
        ("line-staged", "lines: 1 in staging pipes"),
        ("line-given", "lines: 1 in staging pipes"),
        ("line-moved", "lines: 0 in staging pipes, 1 given before"),
        ("round-committed", "3 answers of committed rounds to take"),
        ("answer-announced", "3 answers of committed rounds to take"),
        ("answer-read", "2 answers of committed rounds to take"),
    ];
    for (point, found) in windows {
        eprintln!("crash point {point}");
        let sys = System::new();
        let desc = pipeline_at(&sys, Program::C.command(&sys), "tmr", LINES, 2000);
        let mut run = sys
            .env("S3RES_VOTER_CRASH_AT", format!("{point}:40"))
            .start_json(&desc);
        let out = run.wait_success(LIMIT);
        let restarts = out.voter_restarts(1);
        let detail = restarts[0].detail.as_deref().unwrap_or("");
        assert!(detail.contains(found), "{point}: {detail}");
        assert!(out.faults().is_empty(), "{point}: {:?}", out.faults());
        assert_sums_continuous(&run, LINES);
    }
}

/// A voter of an unmodified program that stops (SIGSTOP) is killed once its heartbeat has
/// stood still past its deadline, and its successor takes the replicas over on their parked
/// pipes: the run completes with every sum once, in order, continuous.
#[test]
#[cfg_attr(
    not(all(s3res_cc, s3res_python3)),
    ignore = "needs a C compiler and python3"
)]
fn a_stopped_voter_of_an_unmodified_program_is_replaced() {
    const LINES: u64 = 8000;
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let sys = System::new();
    let desc = pipeline_at(&sys, Program::C.command(&sys), "tmr", LINES, 1000);
    let mut run = sys.start_json(&desc);
    run.wait_for_replicas("sum", 3);
    std::thread::sleep(Duration::from_millis(500));
    let voter = run.process_named("s3res-voter").expect("the voter");
    s3res_testkit::kill_pid(voter, libc::SIGSTOP).expect("stop the voter");
    let restart = run.wait_for_event(
        |e| e.kind == EventKind::VoterRestart,
        Duration::from_secs(60),
    );
    assert_ne!(restart.pid, Some(voter), "{restart:?}");
    let out = run.wait_success(LIMIT);
    let line = format!("the voter of component sum (pid {voter}) died: made no progress for");
    assert!(
        out.stderr.lines().any(|l| l.contains(&line)),
        "no line {line:?}:\n{}",
        s3res_testkit::tail(&out.stderr, 30)
    );
    assert_sums_continuous(&run, LINES);
}

#[test]
#[cfg_attr(
    not(all(s3res_cc, s3res_python3)),
    ignore = "needs a C compiler and python3"
)]
fn twenty_voter_kills_under_a_c_filter_lose_and_repeat_no_line() {
    kill_voters_of(Program::C);
}

#[test]
#[cfg_attr(not(all(s3res_awk, s3res_python3)), ignore = "needs awk and python3")]
fn twenty_voter_kills_under_awk_lose_and_repeat_no_line() {
    kill_voters_of(Program::Awk);
}

#[test]
#[cfg_attr(not(s3res_python3), ignore = "needs python3")]
fn twenty_voter_kills_under_a_python_script_lose_and_repeat_no_line() {
    kill_voters_of(Program::Python);
}

#[test]
#[cfg_attr(not(all(s3res_awk, s3res_python3)), ignore = "needs awk and python3")]
fn awk_keeps_its_running_sum_under_tmr() {
    under_fire(Program::Awk, "tmr", 3);
}

#[test]
#[cfg_attr(not(all(s3res_awk, s3res_python3)), ignore = "needs awk and python3")]
fn awk_keeps_its_running_sum_under_dmr() {
    under_fire(Program::Awk, "dmr", 2);
}

#[test]
#[cfg_attr(not(s3res_python3), ignore = "needs python3")]
fn a_python_script_keeps_its_count_under_tmr() {
    under_fire(Program::Python, "tmr", 3);
}

#[test]
#[cfg_attr(not(s3res_python3), ignore = "needs python3")]
fn a_python_script_keeps_its_count_under_dmr() {
    under_fire(Program::Python, "dmr", 2);
}

#[test]
#[cfg_attr(
    not(all(s3res_cc, s3res_python3)),
    ignore = "needs a C compiler and python3"
)]
fn a_c_filter_keeps_its_sum_under_tmr() {
    under_fire(Program::C, "tmr", 3);
}

#[test]
#[cfg_attr(
    not(all(s3res_cc, s3res_python3)),
    ignore = "needs a C compiler and python3"
)]
fn a_c_filter_keeps_its_sum_under_dmr() {
    under_fire(Program::C, "dmr", 2);
}

/// `s3res-bootstrap --check` of `desc`, written to the system's folder.
fn check(sys: &System, desc: &Value) -> std::process::Output {
    let path = sys.path("system.json");
    std::fs::write(&path, serde_json::to_string_pretty(desc).unwrap()).unwrap();
    Command::new(bin_path("s3res-bootstrap"))
        .arg("--check")
        .arg(&path)
        .stdin(Stdio::null())
        .output()
        .unwrap()
}

/// `--check` refuses a statically linked program with the reason, naming the field.
#[test]
#[cfg_attr(not(s3res_cc_static), ignore = "needs a C compiler with a static libc")]
fn a_statically_linked_program_is_refused_at_check() {
    let sys = System::new();
    let exe = compile_c(&sys, "static-sum", SUM_C, &["-static"]);
    let desc = pipeline(&sys, (exe, Vec::new()), "tmr", 10);
    let out = check(&sys, &desc);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{stderr}");
    assert!(stderr.contains("statically linked"), "{stderr}");
    assert!(stderr.contains("components.sum.exec"), "{stderr}");
}

/// `lock_memory` does nothing for an unmodified program (the preload library locks nothing):
/// `--check` says so, and accepts the description.
#[test]
#[cfg_attr(not(s3res_python3), ignore = "needs python3")]
fn lock_memory_of_an_unmodified_program_is_reported_as_ignored() {
    let sys = System::new();
    let mut desc = pipeline(&sys, (python3(), vec!["-u".into()]), "tmr", 10);
    desc["components"]["sum"]["lock_memory"] = json!("used");
    let out = check(&sys, &desc);
    let all = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(out.status.success(), "{all}");
    assert!(
        all.contains("component sum: `lock_memory` is ignored for an unmodified program"),
        "{all}"
    );
}

/// A program that starts a second thread is never forked: at its first recovery the voter
/// sees every candidate donor run two threads, passes them over (saying why) and starts the
/// replica afresh by exec at once — not after asking each donor to fork and waiting a whole
/// connect timeout for a child that a refusing donor never makes (2 s in all, before).
#[test]
#[cfg_attr(not(s3res_python3), ignore = "needs python3")]
fn a_program_that_starts_a_thread_is_not_forked() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let sys = System::new();
    let (mut run, ..) = threaded_restarted_by_exec(sys, THREADED_PY, &[], 3000);
    run.stop();
    let out = run.wait(LIMIT);
    assert!(
        out.stderr
            .contains("no recovery donor: replicas [0, 2] run more than one thread"),
        "{}",
        s3res_testkit::tail(&out.stderr, 30)
    );
    assert!(
        !out.stderr.contains("recovery by fork failed"),
        "a threaded donor was asked to fork: {}",
        s3res_testkit::tail(&out.stderr, 30)
    );
    run.assert_nothing_left();
}

/// The replica started afresh for a threaded stateful program lost the running sum, and no
/// fork can give it back (every donor runs two threads): it differs from the others in every
/// round. It is restarted once, not once per round — each exec would lose the sum again, be
/// outvoted again and be restarted again (93 execs in 11 s at 50 lines/s before, just under
/// the restart budget). It stays, outvoted, said once as `diverged`; the sums that go out
/// are the replicas' that kept the state, every one of them.
#[test]
#[cfg_attr(not(s3res_python3), ignore = "needs python3")]
fn a_lost_state_no_fork_can_give_back_is_not_restarted_every_round() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let sys = System::new();
    const LINES: u64 = 1000;
    let (mut run, pid, fresh) = threaded_restarted_by_exec(sys, THREADED_PY, &[], LINES);
    let out = run.wait_success(LIMIT);
    let events = &out.events;
    let restarts: Vec<&s3res_testkit::Event> = events
        .iter()
        .filter(|e| e.kind == EventKind::Recovery && e.component == "sum")
        .collect();
    assert_eq!(
        restarts.len(),
        1,
        "restarted into the same loss: {restarts:#?}\n{}",
        s3res_testkit::tail(&out.stderr, 30)
    );
    let diverged: Vec<&s3res_testkit::Event> = events
        .iter()
        .filter(|e| e.kind == EventKind::Diverged)
        .collect();
    assert_eq!(diverged.len(), 1, "{diverged:#?}");
    assert_eq!(
        (diverged[0].replica, diverged[0].pid),
        (Some(1), Some(fresh)),
        "{diverged:#?}"
    );
    let faults = out.faults();
    assert_eq!(faults.len(), 1, "only the kill is a fault: {faults:#?}");
    assert_eq!(faults[0].pid, Some(pid), "{faults:#?}");
    assert!(
        out.stderr.contains("diverged     sum replica 1 of 3"),
        "{}",
        s3res_testkit::tail(&out.stderr, 20)
    );
    assert_sums_continuous(&run, LINES);
    run.assert_nothing_left();
}

/// A replica killed before any line was given to any replica is restarted by exec (no replica
/// has answered, so none may donate) with nothing lost: a fresh process has the state every
/// replica has. It was said `state_lost: true` and treated as catching up, and the verdict
/// spoke of a lost state where none was. The feed waits for a file before its first line.
#[test]
fn a_replica_killed_before_any_line_loses_no_state() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    const LINES: u64 = 200;
    let sys = System::new();
    let mut desc = pipeline(&sys, awk_program(), "tmr", LINES);
    let go = sys.path("go");
    let feed = desc["components"]["feed"].clone();
    let mut args = vec![
        json!("-c"),
        json!(format!(
            "while [ ! -e '{}' ]; do sleep 0.02; done; exec \"$0\" \"$@\"",
            go.display()
        )),
        feed["exec"].clone(),
    ];
    args.extend(
        feed["args"]
            .as_array()
            .expect("the feed's args")
            .iter()
            .cloned(),
    );
    desc["components"]["feed"] = json!({"exec": "/bin/sh", "args": args});
    let mut run = sys.start_json(&desc);
    run.wait_for_replicas("sum", 3);
    let pid = run.replica_pids("sum")[&1];
    s3res_testkit::kill_pid(pid, libc::SIGKILL).unwrap();
    let rec = run.wait_for_recovery("sum", 1, pid);
    assert_eq!(rec.method, Some(RecoveryMethod::Exec), "{rec:?}");
    assert_eq!(
        rec.state_lost,
        Some(false),
        "no line was given yet: {rec:?}"
    );
    std::fs::write(&go, "").unwrap();
    let out = run.wait_success(LIMIT);
    assert!(
        !out.stderr.contains("state lost"),
        "{}",
        s3res_testkit::tail(&out.stderr, 20)
    );
    assert!(
        out.events.iter().all(|e| e.kind != EventKind::Diverged),
        "{:#?}",
        out.events
    );
    assert_sums_continuous(&run, LINES);
    run.assert_nothing_left();
}

/// The voter's successor does not know which replicas had matched (it is not journaled): it
/// takes a replica whose state is lost for one still catching up, so the diverged replica is
/// not faulted and restarted into the same loss once more after a voter's death (a review
/// found one more `sdc` and exec there).
#[test]
#[cfg_attr(not(s3res_python3), ignore = "needs python3")]
fn a_diverged_replica_stays_spared_across_a_voter_restart() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let sys = System::new();
    const LINES: u64 = 2000;
    let (mut run, pid, _) = threaded_restarted_by_exec(sys, THREADED_PY, &[], LINES);
    run.wait_for_event(|e| e.kind == EventKind::Diverged, Duration::from_secs(20));
    let voter = run.voter_of("sum").expect("the voter of sum");
    s3res_testkit::kill_pid(voter, libc::SIGKILL).expect("kill the voter");
    let out = run.wait_success(LIMIT);
    out.voter_restarts(1);
    let faults = out.faults();
    assert_eq!(faults.len(), 1, "only the kill is a fault: {faults:#?}");
    assert_eq!(faults[0].pid, Some(pid), "{faults:#?}");
    assert_sums_continuous(&run, LINES);
    run.assert_nothing_left();
}

/// A replica started afresh matches the others by chance (its lost state shows only at their
/// hundred-and-first line), is taken for caught up, and is faulted there and started afresh
/// once more. Its slot has relapsed: the next replica there is not taken for caught up by its
/// matches, and is kept, outvoted, as `diverged` at its own hundred-and-first. Before, every
/// replica started there was restarted at that line (a review found this).
#[test]
#[cfg_attr(not(s3res_python3), ignore = "needs python3")]
fn a_fresh_replica_that_matched_by_chance_is_restarted_once_more_not_every_time() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let sys = System::new();
    const LINES: u64 = 1000;
    let (mut run, _, _) = threaded_restarted_by_exec(sys, THREADED_FIRST_PY, &[], LINES);
    let out = run.wait_success(LIMIT);
    let restarts = out
        .events
        .iter()
        .filter(|e| e.kind == EventKind::Recovery)
        .count();
    assert_eq!(
        restarts,
        2,
        "the kill's and the relapse's: {:#?}\n{}",
        out.faults(),
        s3res_testkit::tail(&out.stderr, 30)
    );
    let diverged = out.events.iter().filter(|e| e.kind == EventKind::Diverged);
    assert_eq!(diverged.count(), 1, "{:#?}", out.events);
    let text = std::fs::read_to_string(run.path("sums.txt")).unwrap();
    let got: Vec<&str> = text.lines().collect();
    assert_eq!(got.len() as u64, LINES);
    for (k, line) in got.iter().enumerate() {
        let k = k as u64 + 1;
        let want = if k == 101 { "True" } else { "False" };
        assert_eq!(*line, want, "line {k}");
    }
    run.assert_nothing_left();
}

/// A replica started afresh that has matched the others once has caught up: a later dissent
/// of it is a fault like any other (restarted, though again by exec) — the spared divergence
/// is only the one its lost state explains.
#[test]
#[cfg_attr(not(s3res_python3), ignore = "needs python3")]
fn a_fresh_replica_that_matched_once_is_faulted_for_a_later_dissent() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let sys = System::new();
    let cue = sys.path("cue");
    std::fs::create_dir(&cue).unwrap();
    let args = [cue.display().to_string()];
    let (mut run, _, fresh) = threaded_restarted_by_exec(sys, THREADED_ECHO_PY, &args, 3000);
    // Lines answered after the fresh replica started: it matched them.
    let base = answered(&run);
    s3res_testkit::wait_until("answers after the restart", Duration::from_secs(20), || {
        (answered(&run) >= base + 20).then_some(())
    });
    std::fs::write(cue.join(fresh.to_string()), "").unwrap();
    let fault = run.wait_for_event(
        |e| e.kind == EventKind::Sdc && e.pid == Some(fresh),
        Duration::from_secs(20),
    );
    assert_eq!(
        fault.cause,
        Some(s3res_testkit::Cause::Minority),
        "{fault:?}"
    );
    run.wait_for_recovery("sum", 1, fresh);
    run.stop();
    let out = run.wait(LIMIT);
    assert!(
        !out.events.iter().any(|e| e.kind == EventKind::Diverged),
        "{:#?}",
        out.events
    );
    let text = std::fs::read_to_string(run.path("sums.txt")).unwrap();
    for (k, line) in text.lines().enumerate() {
        assert_eq!(line, (k + 1).to_string(), "line {} of the echo", k + 1);
    }
    run.assert_nothing_left();
}

/// The example of `docs/writing-a-component.md` ("Unmodified programs") runs as shown: awk,
/// unmodified, under TMR, fed by `s3res-frames send` and watched by `s3res-frames show`.
#[test]
#[cfg_attr(
    not(s3res_mawk),
    ignore = "the docs' example uses mawk's -W interactive"
)]
fn the_documented_example_runs_as_shown() {
    const DOC: &str = include_str!("../../docs/writing-a-component.md");
    let section = &DOC[DOC.find("## 8. Unmodified programs").expect("the section")..];
    let start = section.find("```json\n").expect("a json block") + "```json\n".len();
    let block = &section[start..start + section[start..].find("```").unwrap()];
    assert!(block.contains("\"runtime\": \"preload\""), "{block}");
    let sys = System::new();
    let numbers: Vec<String> = (1..=50).map(|k| k.to_string()).collect();
    std::fs::write(sys.path("numbers.txt"), numbers.join("\n") + "\n").unwrap();
    let mut run = sys.start(block);
    let out = run.wait_success(LIMIT);
    let sums: Vec<u64> = out.stdout.lines().map(|l| l.parse().unwrap()).collect();
    let expected: Vec<u64> = (1..=50u64).map(|k| k * (k + 1) / 2).collect();
    assert_eq!(sums, expected, "{}", s3res_testkit::tail(&out.stderr, 20));
}

/// The first mistake with an unmodified program: mawk without `-W interactive` reads its input
/// in blocks and never answers a single line. The component fails within its restart budget,
/// in one line that says what to check.
#[test]
#[cfg_attr(not(all(s3res_mawk, s3res_python3)), ignore = "needs mawk and python3")]
fn a_program_that_never_answers_a_line_is_told_to_flush() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let sys = System::new();
    let awk = which("awk").expect("awk");
    let desc = pipeline(&sys, (awk, vec!["{ print }".to_owned()]), "tmr", 3000);
    let mut run = sys.start_json(&desc);
    let out = run.wait(LIMIT);
    assert!(!out.status.success(), "{}", out.status);
    let line = out
        .stderr
        .lines()
        .find(|l| l.contains("failed beyond recovery: component sum"))
        .unwrap_or_else(|| panic!("{}", s3res_testkit::tail(&out.stderr, 20)));
    assert!(
        line.contains("write one line to stdout for each line it reads, and flush it"),
        "{line}"
    );
    run.assert_nothing_left();
}

/// A program that answers no line for some inputs (every fifth here) leaves every replica
/// asleep on an empty input at the deadline: the hang says so, and asks whether it sent
/// nothing for the round's input. Before, it said only "if the component needs more than
/// 300000 µs for a round, raise its timeout_us", which cannot help (12 of 12 such hangs of a
/// user's program).
const SKIPS_EVERY_FIFTH_PY: &str = r#"
import sys
for line in sys.stdin:
    if int(line) % 5 != 0:
        print(int(line))
"#;

#[test]
#[cfg_attr(not(s3res_python3), ignore = "needs python3")]
fn a_program_that_skips_an_answer_is_told_so_not_to_raise_its_timeout() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let sys = System::new();
    std::fs::write(sys.path("program.py"), SKIPS_EVERY_FIFTH_PY).unwrap();
    let program = (
        python3(),
        vec![
            "-u".to_owned(),
            sys.path("program.py").display().to_string(),
        ],
    );
    let desc = pipeline(&sys, program, "tmr", 40);
    let mut run = sys.start_json(&desc);
    let hang = run.wait_for_event(
        |e| e.kind == EventKind::Hang && e.round == Some(5),
        Duration::from_secs(30),
    );
    let detail = hang.detail.unwrap_or_default();
    assert!(
        detail.contains("waits for more input with none left to read")
            && detail.contains("one answer per input frame"),
        "{detail}"
    );
    run.stop();
    run.wait(LIMIT);
    run.assert_nothing_left();
}

/// Writes each line's answer in two `write`s with a pause between them: `head-`, then,
/// 1.5 s later, `tail` and the newline.
const SPLIT_LINE_PY: &str = r#"
import os, sys, time
for line in sys.stdin:
    os.write(1, b"head-")
    time.sleep(1.5)
    os.write(1, b"tail\n")
"#;

/// `python3 -c script` with the preload library, as replica 0 of `component` with stdin and
/// stdout for its ports and its voter's socket at `voter_socket`: the test plays the voter.
/// Returns the process and the test's ends of its stdin and stdout.
fn preloaded_python(
    script: &str,
    component: &str,
    voter_socket: &Path,
) -> (
    std::process::Child,
    std::os::fd::OwnedFd,
    std::os::fd::OwnedFd,
) {
    use replica_rt::contract::{self, Direction, PortMap, PortSpec};
    let port = |name: &str, dir, fd| PortSpec {
        name: name.into(),
        dir,
        fd,
        max_frame: 4096,
    };
    let map = PortMap {
        ports: vec![
            port("in", Direction::In, libc::STDIN_FILENO),
            port("out", Direction::Out, libc::STDOUT_FILENO),
        ],
    };
    let (stdin_r, stdin_w) = replica_rt::sys::pipe().unwrap();
    let (stdout_r, stdout_w) = replica_rt::sys::pipe().unwrap();
    let child = Command::new(python3())
        .args(["-c", script])
        .env("LD_PRELOAD", bin_path("libs3res_preload.so"))
        .env(contract::ENV_PORTS, map.to_env())
        .env(contract::ENV_VOTER_SOCKET, voter_socket)
        .env(contract::ENV_REPLICA, "0")
        .env(contract::ENV_COMPONENT, component)
        .stdin(Stdio::from(stdin_r))
        .stdout(Stdio::from(stdout_w))
        .spawn()
        .expect("starting python3");
    (child, stdin_w, stdout_r)
}

/// The preload library defers a restart while the program's stdout is mid-line: a RESTART that
/// arrives between `head-` and `tail\n` forks only once the line is whole, so the donor's pipe
/// carries the whole line and the child's new stdout starts at a line boundary. This test
/// plays the voter's part of the handshake itself (no bootstrap, no voter): a voter forks only
/// at a quiet point, where no line is open, so the end-to-end tests never reach this case.
#[test]
#[cfg_attr(not(s3res_python3), ignore = "needs python3")]
fn a_restart_mid_line_waits_for_the_end_of_the_line() {
    use replica_rt::contract::handshake::{
        FdTransfer, Hello, Ready, HELLO_MAGIC, READY_MAGIC, TRANSFER_MAGIC,
    };
    use replica_rt::contract::{self, MAX_HANDED_FDS};
    use replica_rt::sys;
    use std::io::{Read, Write};
    use std::os::fd::{AsFd, AsRawFd, OwnedFd};
    use std::os::unix::net::UnixListener;

    const NONCE: u32 = 0x1e1e;
    const STEP: Duration = Duration::from_secs(20);

    /// Kills the donor and its fork child, also when the test fails.
    struct Guard {
        donor: std::process::Child,
        child: Option<OwnedFd>,
    }
    impl Drop for Guard {
        fn drop(&mut self) {
            if let Some(pidfd) = &self.child {
                let _ = sys::pidfd_send_signal(pidfd.as_fd(), libc::SIGKILL);
            }
            let _ = self.donor.kill();
            let _ = self.donor.wait();
        }
    }

    /// Reads from `fd` until `want` bytes came (or `STEP` passed); returns them.
    fn read_exactly(fd: &OwnedFd, want: usize) -> Vec<u8> {
        let mut got = Vec::new();
        let deadline = std::time::Instant::now() + STEP;
        while got.len() < want {
            let left = deadline.saturating_duration_since(std::time::Instant::now());
            assert!(
                sys::wait_readable(fd.as_fd(), left).unwrap(),
                "only {:?} within {STEP:?}",
                String::from_utf8_lossy(&got)
            );
            let mut buf = [0u8; 256];
            let n = sys::read(fd.as_fd(), &mut buf[..want - got.len()]).unwrap();
            assert!(n > 0, "closed after {:?}", String::from_utf8_lossy(&got));
            got.extend_from_slice(&buf[..n]);
        }
        got
    }

    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let dir = tempfile::tempdir().unwrap();
    let sock_path = dir.path().join("voter.sock");
    let listener = UnixListener::bind(&sock_path).unwrap();
    listener.set_nonblocking(true).unwrap();
    let (donor, stdin_w, stdout_r) = preloaded_python(SPLIT_LINE_PY, "split", &sock_path);
    let donor_pid = donor.id() as libc::pid_t;
    let mut guard = Guard { donor, child: None };
    let mut to_donor = std::fs::File::from(stdin_w);

    // Mid-line: `head-` is out, `tail\n` 1.5 s away. The RESTART must wait for it.
    to_donor.write_all(b"1\n").unwrap();
    assert_eq!(read_exactly(&stdout_r, 5), b"head-");
    s3res_testkit::sigqueue(donor_pid, contract::signals::RESTART, NONCE as i32).unwrap();
    assert!(
        !sys::wait_readable(listener.as_fd(), Duration::from_millis(500)).unwrap(),
        "the donor forked in the middle of a line"
    );
    assert_eq!(read_exactly(&stdout_r, 5), b"tail\n");

    // Then the fork: the child connects with the nonce.
    assert!(
        sys::wait_readable(listener.as_fd(), STEP).unwrap(),
        "no fork once the line was whole"
    );
    let (mut conn, _) = listener.accept().unwrap();
    conn.set_nonblocking(false).unwrap();
    conn.set_read_timeout(Some(STEP)).unwrap();
    let child = sys::peer_pid(conn.as_fd()).unwrap();
    guard.child = Some(sys::pidfd_open(child).unwrap());
    assert_eq!(sys::parent_pid(child), Some(donor_pid));
    let mut hello = [0u8; Hello::SIZE];
    conn.read_exact(&mut hello).unwrap();
    let hello = Hello::from_bytes(hello);
    assert_eq!((hello.magic, hello.nonce), (HELLO_MAGIC, NONCE));
    let (child_in_r, child_in_w) = sys::pipe().unwrap();
    let (child_out_r, child_out_w) = sys::pipe().unwrap();
    let mut targets = [-1; MAX_HANDED_FDS];
    targets[0] = libc::STDIN_FILENO;
    targets[1] = libc::STDOUT_FILENO;
    let transfer = FdTransfer {
        magic: TRANSFER_MAGIC,
        count: 2,
        targets,
    };
    sys::send_with_fds(
        conn.as_fd(),
        transfer.as_bytes(),
        &[child_in_r.as_raw_fd(), child_out_w.as_raw_fd()],
    )
    .unwrap();
    drop((child_in_r, child_out_w));
    let mut ready = [0u8; Ready::SIZE];
    conn.read_exact(&mut ready).unwrap();
    let ready = Ready::from_bytes(ready);
    assert_eq!((ready.magic, ready.pid), (READY_MAGIC, child));
    drop(conn);

    // The child's stdout starts at a line boundary; the donor's goes on with whole lines.
    std::fs::File::from(child_in_w).write_all(b"2\n").unwrap();
    assert_eq!(read_exactly(&child_out_r, 10), b"head-tail\n");
    to_donor.write_all(b"3\n").unwrap();
    assert_eq!(read_exactly(&stdout_r, 10), b"head-tail\n");
    drop(guard);
}

/// Writes each running sum in two `write`s, its digits and then its newline, with a line of
/// stdin (the test's go-ahead) read between them: `python3 -u`'s `print` writes so too.
const SPLIT_SUM_PY: &str = r#"
import os, sys
total = 0
while True:
    line = sys.stdin.readline()
    if not line:
        break
    total += int(line)
    os.write(1, str(total).encode())
    sys.stdin.readline()
    os.write(1, b"\n")
"#;

/// An SDC injection that arrives between a line's digits and its newline flips a bit of the
/// next line that has one to flip: a write of the newline alone carries nothing to corrupt,
/// and must not use the injection up. (`a_python_script_keeps_its_count_under_tmr` waited in
/// vain for its fifth SDC when the injection met `print`'s lone newline.) Like the test above,
/// no voter: the test holds the program's pipes and signals it as `s3res-inject` does.
#[test]
#[cfg_attr(not(s3res_python3), ignore = "needs python3")]
fn an_sdc_injected_before_a_lone_newline_corrupts_the_next_line() {
    use replica_rt::contract;
    use replica_rt::sys;
    use std::io::Write;
    use std::os::fd::{AsFd, OwnedFd};

    const STEP: Duration = Duration::from_secs(20);

    /// Kills the program, also when the test fails.
    struct Guard(std::process::Child);
    impl Drop for Guard {
        fn drop(&mut self) {
            let _ = self.0.kill();
            let _ = self.0.wait();
        }
    }

    /// One byte from `fd`, within `STEP`.
    fn read_byte(fd: &OwnedFd) -> u8 {
        assert!(
            sys::wait_readable(fd.as_fd(), STEP).unwrap(),
            "no output within {STEP:?}"
        );
        let mut b = [0u8; 1];
        assert_eq!(sys::read(fd.as_fd(), &mut b).unwrap(), 1, "stdout closed");
        b[0]
    }

    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let dir = tempfile::tempdir().unwrap();
    let (program, stdin_w, stdout_r) =
        preloaded_python(SPLIT_SUM_PY, "sum", &dir.path().join("voter.sock"));
    let pid = program.id() as libc::pid_t;
    let guard = Guard(program);
    let mut stdin = std::fs::File::from(stdin_w);

    // Sum 1: its digit is out, its newline not yet. The injection lands now: the signal is
    // pending before the go-ahead is written, so the program takes it before it reads on.
    stdin.write_all(b"1\n").unwrap();
    assert_eq!(read_byte(&stdout_r), b'1');
    s3res_testkit::kill_pid(pid, contract::signals::INJECT_SDC).unwrap();
    stdin.write_all(b"go\n").unwrap();
    assert_eq!(
        read_byte(&stdout_r),
        b'\n',
        "the newline itself was changed"
    );

    // Sum 3: the injection is still pending, and this line's digit carries it.
    stdin.write_all(b"2\ngo\n").unwrap();
    let digit = read_byte(&stdout_r);
    assert_eq!(
        (digit ^ b'3').count_ones(),
        1,
        "sum 3 went out as {:?}: the injection was used up on the lone newline",
        digit as char
    );
    assert_eq!(read_byte(&stdout_r), b'\n');

    // Used once: sum 6 goes out clean.
    stdin.write_all(b"3\ngo\n").unwrap();
    assert_eq!([read_byte(&stdout_r), read_byte(&stdout_r)], *b"6\n");
    drop(guard);
}

/// A frame that holds a newline, on its way to a program that reads lines, ends the input
/// there and fails the component in one line naming the frame and the byte — the program is
/// not blamed. Before, `cat` took the frame for two lines and answered twice, every replica
/// was blamed for the extra answer and restarted with its state lost, a wrong frame went out,
/// and the run ended "clean", status 0.
#[test]
fn a_frame_with_a_newline_for_a_program_that_reads_lines_is_refused_not_blamed_on_it() {
    let (mut run, out) = run_lines_program("cat", &[], &[b"1", b"2\n3", b"4"]);
    assert!(!out.status.success(), "{}", out.status);
    assert!(
        out.stderr
            .contains("input frame 2 on `in` holds a newline (byte 1 of 3), and `/"),
        "{}",
        s3res_testkit::tail(&out.stderr, 20)
    );
    let faults = out
        .events
        .iter()
        .filter(|e| {
            e.replica.is_some() && e.kind != EventKind::Start && e.kind != EventKind::Recovery
        })
        .count();
    assert_eq!(faults, 0, "a replica was blamed: {:#?}", out.events);
    run.assert_nothing_left();
}

/// A program that writes two lines for one (`sed -u p`) is told what the rule is in the fault
/// its extra line raises: before, the detail said "extra frame in one round" and nothing
/// named the program's habit.
#[test]
fn a_program_that_writes_two_lines_for_one_is_told_the_rule() {
    let (mut run, out) = run_lines_program("sed", &["-u", "p"], &[b"1", b"2", b"3"]);
    let extra: Vec<&str> = out
        .events
        .iter()
        .filter(|e| e.cause == Some(s3res_protocol::event::Cause::ExtraFrame))
        .filter_map(|e| e.detail.as_deref())
        .collect();
    assert!(!extra.is_empty(), "{:#?}", out.events);
    for d in extra {
        assert!(
            d.contains("must write exactly one line for each line it reads"),
            "{d}"
        );
    }
    run.assert_nothing_left();
}

/// Runs `program ARGS` unmodified, under TMR, reading lines: bootstrap's stdin gives it
/// `payloads` (one frame each), its answers go to bootstrap's stdout; the run to its end.
fn run_lines_program(
    program: &str,
    args: &[&str],
    payloads: &[&[u8]],
) -> (RunningSystem, s3res_testkit::Outcome) {
    let mut frames = Vec::new();
    for payload in payloads {
        s3res_protocol::frame::encode_into(payload, &mut frames);
    }
    let sys = System::new().stdin(frames);
    let exec = which(program).unwrap_or_else(|| panic!("{program} on PATH"));
    let desc = json!({
        "name": "lines",
        "components": {
            "p": {"exec": exec, "args": args, "runtime": "preload", "framing": "lines",
                  "redundancy": "tmr", "timeout_us": 300000}
        },
        "channels": [
            {"from": "stdin", "to": "p.in"},
            {"from": "p.out", "to": "stdout"}
        ]
    });
    let mut run = sys.start_json(&desc);
    let out = run.wait(LIMIT);
    (run, out)
}

/// A Python program that echoes each number, and dies at 20 in every replica (a bad input).
const DIES_AT_20_PY: &str = r#"
import sys
for line in sys.stdin:
    if int(line) == 20:
        sys.exit(3)
    print(int(line))
"#;

/// A bad input kills every replica of a program started through a wrapper (a shell script that
/// `exec`s the interpreter after 0.2 s, as a pyenv shim does more slowly): the three are
/// started afresh, and none is forked from another while that one is still in its wrapper. A
/// wrapper loads the preload library, and its restart handler, before the `exec` drops the
/// handler again (`Replica::handler_before_answer`). Before, a user's shimmed Python lost
/// donors "killed by signal 10" (the restart signal) at every bad line until the restart budget
/// was spent, where the interpreter run directly went on to the end. (Whether a replica's
/// handler shows yet when the next one is restarted is a race: before, this test failed 3 runs
/// of 6; `a_preloaded_replica_that_has_not_answered_is_no_donor_whatever_it_catches` checks the
/// rule itself.)
#[test]
#[cfg_attr(not(s3res_python3), ignore = "needs python3")]
fn a_bad_line_under_a_wrapper_restarts_every_replica_afresh_and_goes_on() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let sys = System::new();
    std::fs::write(sys.path("program.py"), DIES_AT_20_PY).unwrap();
    let wrapper = sys.path("wrapper.sh");
    std::fs::write(
        &wrapper,
        format!(
            "#!/bin/sh\nsleep 0.2\nexec {} -u {}\n",
            python3().display(),
            sys.path("program.py").display()
        ),
    )
    .unwrap();
    std::fs::set_permissions(
        &wrapper,
        std::os::unix::fs::PermissionsExt::from_mode(0o755),
    )
    .unwrap();
    let desc = pipeline_at(&sys, (wrapper, Vec::new()), "tmr", 60, 50);
    let mut run = sys.start_json(&desc);
    let out = run.wait_success(LIMIT);
    let recoveries: Vec<_> = out
        .events
        .iter()
        .filter(|e| e.kind == EventKind::Recovery || e.signal == Some(libc::SIGUSR1))
        .collect();
    assert!(
        recoveries.len() == 3
            && recoveries
                .iter()
                .all(|e| e.method == Some(RecoveryMethod::Exec)),
        "three replicas started afresh, none forked from a wrapper: {recoveries:#?}"
    );
    let text = std::fs::read_to_string(run.path("sums.txt")).unwrap();
    let want: Vec<String> = (1..=60)
        .filter(|&k| k != 20)
        .map(|k| k.to_string())
        .collect();
    assert_eq!(text.lines().collect::<Vec<_>>(), want);
}
