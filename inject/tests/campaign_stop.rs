//! A campaign killed from outside leaves nothing running, as a batch system's cancel or time
//! limit does it: SIGKILL to `s3res-inject` takes its run's whole system down with it (bootstrap
//! dies with its parent), and SIGTERM stops the run in progress, writes the completed runs, and
//! `--resume` with the same command then finishes the campaign with the same schedule, run for
//! run, as an uninterrupted one.

mod common;

use std::path::Path;
use std::sync::Mutex;
use std::time::{Duration, Instant};

use common::{echo_system, inject, read_json, read_jsonl, run_numbers, schedule, Spawned};
use s3res_testkit::Rng;

/// One campaign at a time: the machine has two cores, and the verdicts depend on deadlines.
static SERIAL: Mutex<()> = Mutex::new(());
const LIMIT: Duration = Duration::from_secs(300);
/// How long the run's processes may outlive a killed `s3res-inject`: the voters' stop
/// (SIGTERM from the kernel when bootstrap dies) kills their replicas at once.
const GONE: Duration = Duration::from_secs(2);
/// How long a SIGTERM'd `s3res-inject` may take to stop its run and write (bootstrap's orderly
/// stop, then the records and the tables).
const STOPS: Duration = Duration::from_secs(10);

fn campaign_args<'a>(
    system: &'a Path,
    out: &'a Path,
    runs: &'a str,
    seed: &'a str,
) -> Vec<&'a str> {
    vec![
        "-q",
        "campaign",
        "--system",
        system.to_str().unwrap(),
        "--fault",
        "sdc",
        "--rate",
        "2",
        "--arrival",
        "fixed",
        "--duration",
        "1",
        "--runs",
        runs,
        "--seed",
        seed,
        "--task-summary",
        "task.json",
        "--components",
        "echo",
        "--out",
        out.to_str().unwrap(),
    ]
}

/// Waits until `p` has a whole TMR system running (a voter and its three echo replicas) and at
/// least `runs_done` runs are in `out/runs.jsonl`.
fn wait_mid_run(p: &Spawned, out: &Path, runs_done: usize) {
    let deadline = Instant::now() + LIMIT;
    loop {
        let done = std::fs::read_to_string(out.join("runs.jsonl")).map_or(0, |t| t.lines().count());
        let live = p.live();
        let count = |name: &str| live.iter().filter(|q| q.comm == name).count();
        if done >= runs_done && count("s3res-voter") == 1 && count("s3res-echo") == 3 {
            return;
        }
        assert!(
            Instant::now() < deadline,
            "no run in progress after {runs_done} done: {live:?}"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// The names in folder `dir` that start with one of `prefixes`, sorted.
fn names_in(dir: &Path, prefixes: &[&str]) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| prefixes.iter().any(|p| n.starts_with(p)))
        .collect();
    names.sort();
    names
}

/// The folders s3res made (`s3res-…`) in the temporary directory `tmp`.
fn scratch_folders(tmp: &Path) -> Vec<String> {
    names_in(tmp, &["s3res-"])
}

/// The notes in the output folder `out` that name a run's scratch folder (`running-…`).
fn notes(out: &Path) -> Vec<String> {
    names_in(out, &["running-", ".running-"])
}

#[test]
fn sigkill_to_the_injector_mid_run_leaves_nothing_running_and_resume_clears_its_run_folder() {
    let _serial = SERIAL.lock().unwrap_or_else(|p| p.into_inner());
    let dir = tempfile::tempdir().unwrap();
    // 10 s of frames: a run left behind would still be running well past GONE.
    let system = echo_system(dir.path(), "tmr", 5000);
    let out = dir.path().join("out");
    // The runs' scratch folders go here, where the test can count them.
    let tmp = dir.path().join("tmp");
    std::fs::create_dir(&tmp).unwrap();
    let env = [("TMPDIR", tmp.to_str().unwrap())];
    let args = campaign_args(&system, &out, "3", "5");
    let mut resume = args[1..].to_vec();
    resume.push("--resume");
    let mut p = common::spawn_with(None, &env, &args);
    wait_mid_run(&p, &out, 0);
    // A second start on the folder in use is refused, and takes nothing of the first's.
    let f = common::spawn_with(None, &env, &resume).wait(LIMIT);
    let busy = format!("another s3res-inject (pid {}) is running", p.child.id());
    assert!(
        f.code == Some(1) && f.stderr.contains(&busy),
        "{}",
        f.stderr
    );
    let before = p.live();
    p.child.kill().unwrap(); // SIGKILL: no chance to stop anything itself
    p.child.wait().unwrap();
    let gone = p.gone_within(GONE);
    eprintln!("{} processes before SIGKILL: {gone:?}", before.len());
    assert!(
        gone.is_ok(),
        "the run outlived s3res-inject by {GONE:?}: {gone:?}\n(before: {before:?})"
    );
    let f = p.wait(LIMIT); // fails if anything is left
    assert_eq!(f.code, None, "{}", f.stderr);

    // The killed run's folder is left, named by a note in the output folder (beside it, the
    // killed bootstrap's runtime folder, which the next bootstrap removes)...
    let left: Vec<String> = scratch_folders(&tmp)
        .into_iter()
        .filter(|n| n.starts_with("s3res-inject-"))
        .collect();
    assert_eq!(left.len(), 1, "{left:?}");
    assert!(
        out.join(format!("running-{}", left[0])).is_file(),
        "no note names {left:?} in {}",
        out.display()
    );
    // ...and the campaign resumed there removes it, runs the rest, and leaves none.
    // Without `-q`: the removal is said at the default level.
    let f = common::spawn_with(None, &env, &resume).wait(LIMIT);
    assert!(f.success, "{}", f.stderr);
    assert!(
        f.stderr
            .contains("removed the scratch folder of a run whose campaign was killed"),
        "{}",
        f.stderr
    );
    assert_eq!(run_numbers(&out), [0, 1, 2]);
    assert_eq!(scratch_folders(&tmp), Vec::<String>::new());
    assert_eq!(notes(&out), Vec::<String>::new());
}

#[test]
fn sigterm_stops_the_run_keeps_the_finished_ones_and_resume_completes_the_campaign() {
    let _serial = SERIAL.lock().unwrap_or_else(|p| p.into_inner());
    let seed = Rng::from_env().next_u64().to_string();
    let dir = tempfile::tempdir().unwrap();
    let system = echo_system(dir.path(), "tmr", 1000);
    let out = dir.path().join("out");
    let args = campaign_args(&system, &out, "4", &seed);
    // The runs' scratch folders go here, where the test can see that none is left.
    let tmp = dir.path().join("tmp");
    std::fs::create_dir(&tmp).unwrap();
    let p = common::spawn_with(None, &[("TMPDIR", tmp.to_str().unwrap())], &args);
    wait_mid_run(&p, &out, 1);
    let sent = Instant::now();
    s3res_testkit::kill_pid(p.child.id() as i32, libc::SIGTERM).unwrap();
    let gone = p.gone_within(STOPS);
    eprintln!("after SIGTERM: {gone:?}");
    assert!(
        gone.is_ok(),
        "still running {STOPS:?} after SIGTERM: {gone:?}"
    );
    let f = p.wait(LIMIT);
    assert_eq!(f.code, Some(143), "{}", f.stderr);
    assert!(
        f.stderr.contains("--resume"),
        "the stop does not say how to go on:\n{}",
        f.stderr
    );
    eprintln!("stopped {:?} after SIGTERM", sent.elapsed());
    // A campaign that stops by itself leaves no folder, and no note naming one.
    assert_eq!(scratch_folders(&tmp), Vec::<String>::new());
    assert_eq!(notes(&out), Vec::<String>::new());

    // The finished runs are written, in order, with the tables of what was done.
    let kept = run_numbers(&out);
    assert!((1..4).contains(&kept.len()), "{kept:?}");
    assert_eq!(kept, (0..kept.len() as u64).collect::<Vec<_>>());
    for r in read_jsonl(&out.join("runs.jsonl")) {
        assert_eq!(r["ready"], true, "{r}");
    }
    let s = &read_json(&out.join("summary.json"))[0];
    assert_eq!(s["runs_done"], kept.len() as u64, "{s}");
    let last = kept.len() as u64 - 1;
    assert!(
        read_jsonl(&out.join("injections.jsonl"))
            .iter()
            .all(|i| i["run"].as_u64().unwrap() <= last),
        "injections of the discarded run were kept"
    );

    // Without --resume the folder is not overwritten; with other parameters it is not resumed.
    let f = inject(&args, LIMIT);
    assert!(
        f.code == Some(1) && f.stderr.contains("already holds a campaign"),
        "{}",
        f.stderr
    );
    let mut other = campaign_args(&system, &out, "4", "12345");
    other.push("--resume");
    let f = inject(&other, LIMIT);
    assert!(
        f.code == Some(1) && f.stderr.contains("seed: "),
        "{}",
        f.stderr
    );
    assert_eq!(
        run_numbers(&out),
        kept,
        "a refused resume changed the records"
    );

    // --resume runs only the missing runs and writes what an uninterrupted campaign writes.
    let mut resume = args[1..].to_vec();
    resume.push("--resume");
    let f = inject(&resume, LIMIT);
    assert!(f.success, "resume failed:\n{}", f.stderr);
    let expected = format!("resuming: {} run(s) already done", kept.len());
    assert!(f.stderr.contains(&expected), "{}", f.stderr);
    assert_eq!(run_numbers(&out), vec![0, 1, 2, 3]);
    let s_resumed = read_json(&out.join("summary.json"))[0].clone();
    assert!(f.stdout.contains("| tmr | sdc | 4 |"), "{}", f.stdout);

    let whole = dir.path().join("whole");
    let f = inject(&campaign_args(&system, &whole, "4", &seed), LIMIT);
    assert!(f.success, "{}", f.stderr);
    let s_whole = read_json(&whole.join("summary.json"))[0].clone();
    assert!(!schedule(&whole).is_empty());
    assert_eq!(schedule(&whole), schedule(&out));
    let per_run = |d: &Path| -> Vec<String> {
        read_jsonl(&d.join("runs.jsonl"))
            .iter()
            .map(|r| {
                format!(
                    "{} {} {} {}",
                    r["run"], r["run_seed"], r["planned"], r["ready"]
                )
            })
            .collect()
    };
    assert_eq!(per_run(&whole), per_run(&out));
    for k in ["runs", "runs_done", "planned", "seed", "config", "fault"] {
        assert_eq!(s_whole[k], s_resumed[k], "{k}");
    }
}
