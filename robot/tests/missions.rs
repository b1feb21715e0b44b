//! End to end: the robot system of `examples/robot/` run by the real `s3res-bootstrap`, with
//! the real voters and component binaries, on a real (simulated) mission.
//!
//! Checks behaviour, never speed: every run is bounded by the mission's own time limit and a
//! generous wall-clock limit, and the harness tears everything down on failure.

use std::path::Path;
use std::time::{Duration, Instant};

use s3res_tests::{procs, EventKind, RecoveryMethod, Rng, RunningSystem, System};
use serde_json::{json, Value};

/// Wall-clock bound on one mission (the mission itself ends by 120 simulated s = 48 s at 50 Hz;
/// the rest is slack for a loaded machine).
const LIMIT: Duration = Duration::from_secs(180);

/// The robot system at `level` from `examples/robot/`, with the sim's seed and summary, and the
/// logger's CSV, placed in the system's temp dir. `timeout_us` overrides the protected
/// components' round deadline (generous: three replicas share two cores in CI).
fn robot_system(sys: &System, level: &str, seed: u64, sim_extra: &[&str]) -> Value {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../examples/robot")
        .join(format!("{level}.json"));
    let text = std::fs::read_to_string(&path).expect("example description");
    let mut desc: Value = serde_json::from_str(&text).expect("example is JSON");
    let mut args = vec![
        "--seed".to_owned(),
        seed.to_string(),
        "--summary".to_owned(),
        sys.path("mission.json").display().to_string(),
    ];
    args.extend(sim_extra.iter().map(|s| s.to_string()));
    desc["components"]["sim"]["args"] = json!(args);
    desc["components"]["logger"]["args"] =
        json!(["--out", sys.path("poses.csv").display().to_string()]);
    for c in ["filter", "navigator"] {
        if desc["components"][c].get("timeout_us").is_some() {
            desc["components"][c]["timeout_us"] = json!(200_000);
        }
    }
    desc
}

/// Until the system finishes: every 0.3–0.7 s, picks a random navigator replica and calls
/// `inject(rng, pid)` on it, then waits for that replica's recovery before the next one (the
/// paper's single-fault assumption). `inject` returns `None` when the replica is already gone
/// (the mission just ended). Returns `(slot, pid, what inject returned)` per injection.
fn inject_until_end<T>(
    run: &mut RunningSystem,
    rng: &mut Rng,
    mut inject: impl FnMut(&mut Rng, i32) -> Option<T>,
) -> Vec<(usize, i32, T)> {
    let mut done = Vec::new();
    let started = Instant::now();
    while run.try_status().is_none() && started.elapsed() < LIMIT {
        std::thread::sleep(Duration::from_millis(rng.range(300, 700)));
        let slot = rng.below(3) as usize;
        let Some(&pid) = run.replica_pids("navigator").get(&slot) else {
            continue;
        };
        let Some(what) = inject(rng, pid) else {
            break;
        };
        let deadline = Instant::now() + Duration::from_secs(10);
        loop {
            let recovered = run.events().iter().any(|e| {
                e.kind == EventKind::Recovery && e.component == "navigator" && e.pid == Some(pid)
            });
            if recovered || run.try_status().is_some() || Instant::now() > deadline {
                break;
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        done.push((slot, pid, what));
    }
    done
}

fn mission(run: &RunningSystem) -> Value {
    let path = run.path("mission.json");
    let text = std::fs::read_to_string(&path)
        .unwrap_or_else(|e| panic!("reading {}: {e}", path.display()));
    serde_json::from_str(&text).expect("mission summary is JSON")
}

fn line(m: &Value) -> String {
    format!(
        "success={} outcome={} time={}s path={}m late={} replans={} wall={}s",
        m["success"],
        m["outcome"],
        m["mission_time_s"],
        m["path_length_m"],
        m["late_periods"],
        m["replans"],
        m["wall_time_s"]
    )
}

#[test]
fn unprotected_mission_reaches_the_goal() {
    let sys = System::new();
    let desc = robot_system(&sys, "none", 2, &[]);
    let mut run = sys.start_json(&desc);
    run.wait_success(LIMIT);
    let m = mission(&run);
    eprintln!("none, seed 2: {}", line(&m));
    assert_eq!(m["success"], true, "{}", line(&m));
    assert_eq!(m["collisions"], 0);
    // The logger recorded a pose per period.
    let poses = std::fs::read_to_string(run.path("poses.csv")).expect("logger's CSV");
    assert_eq!(
        poses.lines().count() as u64 - 1,
        m["periods"].as_u64().unwrap()
    );
}

#[test]
fn dmr_mission_reaches_the_goal() {
    let sys = System::new();
    let desc = robot_system(&sys, "dmr", 3, &[]);
    let mut run = sys.start_json(&desc);
    let out = run.wait_success(LIMIT);
    let m = mission(&run);
    eprintln!("dmr, seed 3: {}", line(&m));
    assert_eq!(m["success"], true, "{}", line(&m));
    // The two replicas agreed on every frame: their outputs depend on their inputs only. (A
    // `hang` is possible on a starved machine and is not the components' doing.)
    let sdc: Vec<_> = out
        .events
        .iter()
        .filter(|e| e.kind == EventKind::Sdc)
        .collect();
    assert!(sdc.is_empty(), "replicas disagreed: {sdc:?}");
}

/// Sensor filter and navigator under TMR; a navigator replica is SIGKILLed about twice a
/// second (random slot, random gap, seeded) for the whole mission. Every kill must show as a
/// crash and a recovery by fork, and the mission must still succeed.
#[test]
fn tmr_mission_survives_navigator_kills() {
    let mut rng = Rng::from_env();
    let sys = System::new();
    let desc = robot_system(&sys, "tmr", 1, &[]);
    let mut run = sys.start_json(&desc);
    run.wait_for_replicas("navigator", 3);
    run.wait_for_replicas("filter", 3);

    let killed = inject_until_end(&mut run, &mut rng, |_, pid| {
        s3res_tests::kill_pid(pid, libc::SIGKILL).ok()
    });
    let out = run.wait_success(LIMIT);
    let m = mission(&run);
    eprintln!("tmr, seed 1, {} kills: {}", killed.len(), line(&m));
    assert!(
        killed.len() >= 5,
        "too few kills ({}) to mean anything",
        killed.len()
    );
    for (slot, pid, ()) in &killed {
        let of = |kind: EventKind| {
            out.events.iter().any(|e| {
                e.kind == kind
                    && e.component == "navigator"
                    && e.replica == Some(*slot)
                    && e.pid == Some(*pid)
            })
        };
        // A kill in the last moments may race the end of the mission; every other must show.
        let last = Some(&(*slot, *pid, ())) == killed.last();
        if last && !of(EventKind::Crash) {
            continue;
        }
        assert!(
            of(EventKind::Crash),
            "kill of {slot}/{pid} not seen as a crash"
        );
        assert!(
            of(EventKind::Recovery),
            "kill of {slot}/{pid} not recovered"
        );
        let rec = out
            .events
            .iter()
            .find(|e| e.kind == EventKind::Recovery && e.pid == Some(*pid))
            .unwrap();
        assert_eq!(rec.method, Some(RecoveryMethod::Fork), "{rec:?}");
    }
    assert_eq!(m["success"], true, "{}", line(&m));
    assert_eq!(m["collisions"], 0);
    // The replicas agreed on every frame they sent: the navigator's and the filter's outputs
    // depend on their inputs only, not on timing.
    let sdc: Vec<_> = out
        .events
        .iter()
        .filter(|e| e.kind == EventKind::Sdc)
        .collect();
    assert!(sdc.is_empty(), "replicas disagreed: {sdc:?}");
}

/// Sensor filter and navigator under TMR; one bit of the next frame of a navigator replica is
/// flipped (SIGUSR2 with the bit as value) about twice a second, seeded. Every corruption is
/// outvoted (an `sdc` event naming that replica), the replica is replaced by fork, and the
/// mission succeeds.
#[test]
fn tmr_mission_outvotes_corrupted_navigator_frames() {
    let mut rng = Rng::from_env();
    let sys = System::new();
    let desc = robot_system(&sys, "tmr", 4, &[]);
    let mut run = sys.start_json(&desc);
    run.wait_for_replicas("navigator", 3);

    // A bit of the command (25 bytes) or of the request (38), whichever is sent next.
    let flipped = inject_until_end(&mut run, &mut rng, |rng, pid| {
        let bit = rng.below(25 * 8) as i32;
        s3res_tests::sigqueue(pid, s3res_tests::signals::INJECT_SDC, bit)
            .is_ok()
            .then_some(bit)
    });
    let out = run.wait_success(LIMIT);
    let m = mission(&run);
    eprintln!("tmr, seed 4, {} bit flips: {}", flipped.len(), line(&m));
    assert!(flipped.len() >= 5, "too few flips ({})", flipped.len());
    for (i, (slot, pid, bit)) in flipped.iter().enumerate() {
        let seen = |kind: EventKind| {
            out.events.iter().any(|e| {
                e.kind == kind
                    && e.component == "navigator"
                    && e.replica == Some(*slot)
                    && e.pid == Some(*pid)
            })
        };
        if i + 1 == flipped.len() && !seen(EventKind::Sdc) {
            continue; // sent as the mission ended
        }
        assert!(
            seen(EventKind::Sdc),
            "flip of bit {bit} in {slot}/{pid} not outvoted"
        );
        assert!(seen(EventKind::Recovery), "{slot}/{pid} not replaced");
    }
    assert_eq!(m["success"], true, "{}", line(&m));
}

/// The same fault without protection: the navigator is SIGKILLed once, early. The robot keeps
/// its last command (a real drive would too), and the mission fails — by collision, or at the
/// (shortened) time limit if that command was to turn on the spot. The sim says so in its
/// summary and exit status, and bootstrap reports the failed components.
#[test]
fn unprotected_mission_fails_when_the_navigator_is_killed() {
    let sys = System::new();
    let desc = robot_system(&sys, "none", 1, &["--time-limit", "40"]);
    let mut run = sys.start_json(&desc);
    let deadline = Instant::now() + Duration::from_secs(30);
    let navigator = loop {
        let found = procs::in_group(run.pgid())
            .into_iter()
            .find(|p| p.comm == "s3res-navigator" && !p.is_zombie());
        if let Some(p) = found {
            break p.pid;
        }
        assert!(Instant::now() < deadline, "the navigator did not start");
        std::thread::sleep(Duration::from_millis(10));
    };
    // Let the robot get going (it waits for its first plan), then kill the navigator.
    std::thread::sleep(Duration::from_millis(1500));
    s3res_tests::kill_pid(navigator, libc::SIGKILL).expect("kill the navigator");
    let out = run.wait(LIMIT);
    let m = mission(&run);
    eprintln!("none, navigator killed: {}", line(&m));
    assert_eq!(m["success"], false, "{}", line(&m));
    assert!(!out.status.success(), "bootstrap must report the failure");
    assert!(
        out.stderr.contains("component sim failed"),
        "the sim's verdict reaches bootstrap: {}",
        s3res_tests::tail(&out.stderr, 20)
    );
    run.assert_nothing_left();
}
