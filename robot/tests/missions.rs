//! End to end: the robot system of `examples/robot/` run by the real `s3res-bootstrap`, with
//! the real voters and component binaries, on a real (simulated) mission.
//!
//! Checks behaviour, never speed: every run is bounded by the mission's own time limit and a
//! generous wall-clock limit, and the harness tears everything down on failure.

use std::path::Path;
use std::time::{Duration, Instant};

use s3res_testkit::{procs, Cause, Event, EventKind, RecoveryMethod, Rng, RunningSystem, System};
use serde_json::{json, Value};

/// Wall-clock bound on one mission (the examples end by 120 simulated s = 48 s at 50 Hz, the
/// repository's `system.json` by 300 s = 120 s;
/// the rest is slack for a loaded machine).
const LIMIT: Duration = Duration::from_secs(180);

/// Missions fly one at a time: each is a real-time system of up to 20 processes meant to have
/// the machine to itself, and two at once on CI's two cores made the robot late often enough
/// to run out of mission time (seen once: 68 late periods, time limit at 42.9 m).
static ONE_ROBOT: std::sync::Mutex<()> = std::sync::Mutex::new(());

fn one_robot_at_a_time() -> std::sync::MutexGuard<'static, ()> {
    // A failed mission poisons the lock; the next one may fly all the same.
    ONE_ROBOT.lock().unwrap_or_else(|e| e.into_inner())
}

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
    for (c, timeout_us) in [
        ("filter", 200_000),
        ("navigator", 200_000),
        ("mapper", 200_000),
        ("planner", 300_000),
    ] {
        if desc["components"][c].get("timeout_us").is_some() {
            desc["components"][c]["timeout_us"] = json!(timeout_us);
        }
    }
    desc
}

/// Starts the TMR robot with the sim's `seed` and waits until `components` run three replicas
/// each; the test's seeded random source with it.
fn start_tmr_robot(seed: u64, components: &[&str]) -> (Rng, RunningSystem) {
    let rng = Rng::from_env();
    let sys = System::new();
    let desc = robot_system(&sys, "tmr", seed, &[]);
    let mut run = sys.start_json(&desc);
    for c in components {
        run.wait_for_replicas(c, 3);
    }
    (rng, run)
}

/// One injected fault: which component, which replica slot, which process, and what the
/// injection returned.
struct Injection<T> {
    component: &'static str,
    slot: usize,
    pid: i32,
    what: T,
}

/// Until the system finishes: every 0.3–0.7 s, picks a random replica of a random one of
/// `components` and calls `inject(rng, pid)` on it, then waits for that replica's recovery
/// before the next one (the paper's single-fault assumption). `inject` returns `None` when the
/// replica is already gone (the mission just ended).
fn inject_until_end<T>(
    run: &mut RunningSystem,
    rng: &mut Rng,
    components: &[&'static str],
    mut inject: impl FnMut(&mut Rng, i32) -> Option<T>,
) -> Vec<Injection<T>> {
    let mut done = Vec::new();
    let started = Instant::now();
    while run.try_status().is_none() && started.elapsed() < LIMIT {
        std::thread::sleep(Duration::from_millis(rng.range(300, 700)));
        let component = components[rng.below(components.len() as u64) as usize];
        let slot = rng.below(3) as usize;
        let Some(&pid) = run.replica_pids(component).get(&slot) else {
            continue;
        };
        let Some(what) = inject(rng, pid) else {
            break;
        };
        let deadline = Instant::now() + Duration::from_secs(10);
        loop {
            let recovered = run.events().iter().any(|e| {
                e.kind == EventKind::Recovery && e.component == component && e.pid == Some(pid)
            });
            if recovered || run.try_status().is_some() || Instant::now() > deadline {
                break;
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        done.push(Injection {
            component,
            slot,
            pid,
            what,
        });
    }
    done
}

/// Every kill in `killed` shows as a crash of that replica and a recovery by fork. The last one
/// may race the end of the mission (the replica had finished, or the voter was ending, when a
/// fault is recorded but not repaired) and is then excused: the injection loop waits for each
/// recovery before the next kill, so no earlier one can.
fn assert_kills_recovered_by_fork<T>(events: &[Event], killed: &[Injection<T>]) {
    for (i, k) in killed.iter().enumerate() {
        let of = |kind: EventKind| {
            events.iter().find(|e| {
                e.kind == kind
                    && e.component == k.component
                    && e.replica == Some(k.slot)
                    && e.pid == Some(k.pid)
            })
        };
        let (c, slot, pid) = (k.component, k.slot, k.pid);
        if i + 1 == killed.len() && of(EventKind::Recovery).is_none() {
            continue;
        }
        assert!(
            of(EventKind::Crash).is_some(),
            "kill of {c} {slot}/{pid} not seen as a crash"
        );
        let rec = of(EventKind::Recovery)
            .unwrap_or_else(|| panic!("kill of {c} {slot}/{pid} not recovered"));
        assert_eq!(rec.method, Some(RecoveryMethod::Fork), "{rec:?}");
    }
}

/// No replica disagreed with its siblings: every component's output depends on its inputs
/// only, not on timing.
fn assert_no_sdc(events: &[Event]) {
    let sdc: Vec<_> = events.iter().filter(|e| e.kind == EventKind::Sdc).collect();
    assert!(sdc.is_empty(), "replicas disagreed: {sdc:?}");
}

/// Faults that timing alone can cause on a loaded machine (a replica late past its deadline:
/// `hang`, or in stream mode `protocol` for a lone replica ahead of two late ones) are
/// allowed, but each must be recovered — unless it is its component's last event, found while
/// the voter was ending (then it is recorded, not repaired); nothing else may show. Returns
/// how many there were.
fn assert_only_timing_faults_recovered(events: &[Event]) -> usize {
    let faults: Vec<_> = events
        .iter()
        .filter(|e| !matches!(e.kind, EventKind::Start | EventKind::Recovery))
        .collect();
    for f in &faults {
        // A protocol fault timing explains: a producer of a frame the others did not make in
        // time (stream mode).
        let timing = f.kind == EventKind::Hang || f.cause == Some(Cause::ExtraFrame);
        assert!(timing, "a fault timing cannot explain: {f:?}");
        let recovered = events
            .iter()
            .any(|e| e.kind == EventKind::Recovery && e.component == f.component && e.pid == f.pid);
        let last = events
            .iter()
            .rev()
            .find(|e| e.component == f.component)
            .is_some_and(|e| std::ptr::eq(e, *f));
        assert!(recovered || last, "not recovered: {f:?}");
    }
    faults.len()
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
    let _robot = one_robot_at_a_time();
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
    let _robot = one_robot_at_a_time();
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
    let _robot = one_robot_at_a_time();
    let (mut rng, mut run) = start_tmr_robot(1, &["navigator", "filter"]);

    // Each replica's locked memory as it is killed (0.3–0.7 s after the recovery before).
    let killed = inject_until_end(&mut run, &mut rng, &["navigator"], |_, pid| {
        let locked_kib = procs::locked_kib(pid).unwrap_or(0);
        s3res_testkit::kill_pid(pid, libc::SIGKILL)
            .ok()
            .map(|()| locked_kib)
    });
    let out = run.wait_success(LIMIT);
    let m = mission(&run);
    eprintln!("tmr, seed 1, {} kills: {}", killed.len(), line(&m));
    assert!(
        killed.len() >= 5,
        "too few kills ({}) to mean anything",
        killed.len()
    );
    assert_kills_recovered_by_fork(&out.events, &killed);
    // A fork child locks its memory once it has answered, where the navigator waits for its
    // inputs (`wait_any`): every one killed had, where the replicas started by exec could.
    let forked: Vec<i32> = out
        .events
        .iter()
        .filter(|e| e.kind == EventKind::Recovery && e.component == "navigator")
        .filter_map(|e| e.new_pid)
        .collect();
    let (children, first): (Vec<_>, Vec<_>) = killed.iter().partition(|k| forked.contains(&k.pid));
    if first.iter().any(|k| k.what > 0) {
        for k in &children {
            assert!(
                k.what > 0,
                "fork child {} of navigator {} had no memory locked when it was killed",
                k.pid,
                k.slot
            );
        }
    }
    assert_eq!(m["success"], true, "{}", line(&m));
    assert_eq!(m["collisions"], 0);
    assert_no_sdc(&out.events);
}

/// Everything of the control loop under TMR, mapper and planner in stream mode; a mapper or
/// planner replica is SIGKILLed about twice a second (random component, slot and gap, seeded)
/// for the whole mission. Every kill shows as a crash and a recovery by fork, the replicas
/// never disagree, and the mission succeeds.
#[test]
fn tmr_mission_survives_mapper_and_planner_kills() {
    let _robot = one_robot_at_a_time();
    let (mut rng, mut run) = start_tmr_robot(5, &["mapper", "planner"]);

    let killed = inject_until_end(&mut run, &mut rng, &["mapper", "planner"], |_, pid| {
        s3res_testkit::kill_pid(pid, libc::SIGKILL).ok()
    });
    let out = run.wait_success(LIMIT);
    let m = mission(&run);
    let count = |c: &str| killed.iter().filter(|k| k.component == c).count();
    eprintln!(
        "tmr, seed 5, {} mapper and {} planner kills: {}",
        count("mapper"),
        count("planner"),
        line(&m)
    );
    assert!(
        count("mapper") >= 3 && count("planner") >= 3,
        "too few kills to mean anything"
    );
    assert_kills_recovered_by_fork(&out.events, &killed);
    assert_eq!(m["success"], true, "{}", line(&m));
    assert_eq!(m["collisions"], 0);
    assert_no_sdc(&out.events);
}

/// The voters of the stream components are killed instead of their replicas: every 0.3–0.7 s
/// (seeded) the mapper's or the planner's voter gets a SIGKILL, for the whole mission. Each is
/// replaced by a voter that adopts the replicas (a `voter_restart` event per kill), no replica
/// is restarted by exec (the state is kept), and the mission succeeds.
#[test]
fn tmr_mission_survives_its_stream_voters_killed() {
    let _robot = one_robot_at_a_time();
    let (mut rng, mut run) = start_tmr_robot(5, &["mapper", "planner"]);
    let mut killed = Vec::new();
    let started = Instant::now();
    while run.try_status().is_none() && started.elapsed() < LIMIT {
        std::thread::sleep(Duration::from_millis(rng.range(300, 700)));
        let component = ["mapper", "planner"][rng.below(2) as usize];
        let Some(voter) = run.voter_of(component) else {
            continue;
        };
        if s3res_testkit::kill_pid(voter, libc::SIGKILL).is_err() {
            continue;
        }
        killed.push(component);
        // The next kill only once the successor runs (one fault at a time).
        let deadline = Instant::now() + Duration::from_secs(10);
        while run.try_status().is_none()
            && Instant::now() < deadline
            && run.voter_of(component).is_none_or(|v| v == voter)
        {
            std::thread::sleep(Duration::from_millis(2));
        }
    }
    let out = run.wait_success(LIMIT);
    let m = mission(&run);
    let restarts = |c: &str| {
        out.events
            .iter()
            .filter(|e| e.kind == EventKind::VoterRestart && e.component == c)
            .count()
    };
    let count = |c: &str| killed.iter().filter(|&&k| k == c).count();
    eprintln!(
        "tmr, seed 5, {} mapper and {} planner voter kills, {} and {} restarts: {}",
        count("mapper"),
        count("planner"),
        restarts("mapper"),
        restarts("planner"),
        line(&m)
    );
    assert!(
        count("mapper") >= 3 && count("planner") >= 3,
        "too few kills to mean anything"
    );
    // The last kill may race the end of the mission (a voter ending on its own is not
    // replaced).
    for c in ["mapper", "planner"] {
        assert!(
            restarts(c) + 1 >= count(c) && restarts(c) <= count(c),
            "{c}: {} kills, {} voter restarts",
            count(c),
            restarts(c)
        );
    }
    for e in &out.events {
        assert!(
            !(e.kind == EventKind::Recovery && e.method == Some(RecoveryMethod::Exec)),
            "a replica was restarted by exec (state lost): {e:?}"
        );
    }
    assert_eq!(m["success"], true, "{}", line(&m));
    assert_eq!(m["collisions"], 0);
    assert_no_sdc(&out.events);
}

/// The golden TMR mission: nothing injected. The replicas agree on every frame; a fault can
/// only be one that timing explains on a loaded machine, and must be recovered. (How many there
/// were is printed, not asserted: tests do not depend on the machine's speed.)
#[test]
fn tmr_mission_without_injection_succeeds() {
    let _robot = one_robot_at_a_time();
    let sys = System::new();
    let desc = robot_system(&sys, "tmr", 2, &[]);
    let mut run = sys.start_json(&desc);
    let out = run.wait_success(LIMIT);
    let m = mission(&run);
    let faults = assert_only_timing_faults_recovered(&out.events);
    eprintln!("tmr, seed 2, no injection, {faults} fault(s): {}", line(&m));
    assert_eq!(m["success"], true, "{}", line(&m));
    assert_eq!(m["collisions"], 0);
}

/// The repository's `system.json`, as README runs it: one mission of the TMR robot under
/// fire (its injector mixes crashes, bit flips and spins at 2 Hz), the sim's verdict on stderr,
/// every fault recovered, the verdict block at the end, everything finished and reaped.
#[test]
fn the_repository_system_json_flies_a_mission() {
    let _robot = one_robot_at_a_time();
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../system.json");
    let description = std::fs::read_to_string(&path).expect("the repository's system.json");
    let mut run = System::new().start(&description);
    let out = run.wait_success(LIMIT);
    let verdict = out
        .stderr
        .lines()
        .find(|l| l.contains("s3res-sim: mission"))
        .unwrap_or_else(|| panic!("no verdict: {}", s3res_testkit::tail(&out.stderr, 20)));
    eprintln!("{verdict}");
    assert!(verdict.contains("mission succeeded"), "{verdict}");
    for needle in [
        "  outcome      succeeded",
        "  injected     ",
        "  false pos.   ",
    ] {
        assert!(
            out.stderr.contains(needle),
            "{needle:?} missing: {}",
            s3res_testkit::tail(&out.stderr, 20)
        );
    }
    let faults: Vec<&Event> = out.faults();
    for f in &faults {
        assert_ne!(f.kind, EventKind::RecoveryFailed, "{f:?}");
        let recovered = out
            .events
            .iter()
            .any(|e| e.kind == EventKind::Recovery && e.component == f.component && e.pid == f.pid);
        // A fault in the last round may end with the component, before its recovery.
        let last = out
            .events
            .iter()
            .rev()
            .find(|e| e.component == f.component)
            .is_some_and(|e| std::ptr::eq(e, *f));
        assert!(
            recovered || last || f.replica.is_none(),
            "not recovered: {f:?}"
        );
    }
    eprintln!("{} fault(s)", faults.len());
    for c in ["filter", "navigator", "mapper", "planner"] {
        let starts = out
            .events
            .iter()
            .filter(|e| e.component == c && e.kind == EventKind::Start)
            .count();
        assert!(starts >= 3, "{c}: {starts} replica(s) started");
    }
}

/// Sensor filter and navigator under TMR; one bit of the next frame of a navigator replica is
/// flipped (SIGUSR2 with the bit as value) about twice a second, seeded. Every corruption is
/// outvoted (an `sdc` event naming that replica), the replica is replaced by fork, and the
/// mission succeeds.
#[test]
fn tmr_mission_outvotes_corrupted_navigator_frames() {
    let _robot = one_robot_at_a_time();
    let mut rng = Rng::from_env();
    let sys = System::new();
    let desc = robot_system(&sys, "tmr", 4, &[]);
    let mut run = sys.start_json(&desc);
    run.wait_for_replicas("navigator", 3);

    // A bit of the command (25 bytes) or of the request (38), whichever is sent next.
    let flipped = inject_until_end(&mut run, &mut rng, &["navigator"], |rng, pid| {
        let bit = rng.below(25 * 8) as i32;
        s3res_testkit::sigqueue(pid, s3res_testkit::signals::INJECT_SDC, bit)
            .is_ok()
            .then_some(bit)
    });
    let out = run.wait_success(LIMIT);
    let m = mission(&run);
    eprintln!("tmr, seed 4, {} bit flips: {}", flipped.len(), line(&m));
    assert!(flipped.len() >= 5, "too few flips ({})", flipped.len());
    for (i, f) in flipped.iter().enumerate() {
        let (slot, pid, bit) = (f.slot, f.pid, f.what);
        let seen = |kind: EventKind| {
            out.events.iter().any(|e| {
                e.kind == kind
                    && e.component == "navigator"
                    && e.replica == Some(slot)
                    && e.pid == Some(pid)
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
    let _robot = one_robot_at_a_time();
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
    s3res_testkit::kill_pid(navigator, libc::SIGKILL).expect("kill the navigator");
    let out = run.wait(LIMIT);
    let m = mission(&run);
    eprintln!("none, navigator killed: {}", line(&m));
    assert_eq!(m["success"], false, "{}", line(&m));
    assert!(!out.status.success(), "bootstrap must report the failure");
    assert!(
        out.stderr.contains("component sim failed"),
        "the sim's verdict reaches bootstrap: {}",
        s3res_testkit::tail(&out.stderr, 20)
    );
    run.assert_nothing_left();
}

/// DMR, and both planner replicas are killed at once shortly after the start: no healthy
/// donor is left, so both are restarted by exec with their state lost (no map, no idea of the
/// path they sent, plan count back at 0). The mission must still succeed: plan ids come from
/// the period, so the navigator takes the fresh planner's plans, and the navigator asks again
/// for a plan that has grown old, so a path the fresh planner cannot check is not followed
/// into a wall for ever. (Before both, such a mission ran into its time limit.)
#[test]
fn dmr_mission_survives_the_planners_state_loss() {
    let _robot = one_robot_at_a_time();
    let sys = System::new();
    let desc = robot_system(&sys, "dmr", 1, &[]);
    let mut run = sys.start_json(&desc);
    run.wait_for_replicas("planner", 2);
    std::thread::sleep(Duration::from_millis(500));
    let pids = run.replica_pids("planner");
    // Both stopped first, so that neither can be the other's donor between the two kills.
    for sig in [libc::SIGSTOP, libc::SIGKILL] {
        for pid in pids.values() {
            s3res_testkit::kill_pid(*pid, sig).expect("signal a planner replica");
        }
    }
    for (&slot, &pid) in &pids {
        let rec = run.wait_for_recovery("planner", slot, pid);
        assert_eq!(rec.state_lost, Some(true), "{rec:?}");
    }
    run.wait_success(LIMIT);
    let m = mission(&run);
    eprintln!("dmr, seed 1, planners restarted: {}", line(&m));
    assert_eq!(m["success"], true, "{}", line(&m));
}
