//! Anomaly detectors in the voter, end to end: `source → signal (protected) → stdout`, where
//! `s3res-signal` emits smooth telemetry (seq, x, y, speed, odometer).
//!
//! A fault-free run is captured through the channel's `capture` and models are trained on it
//! with the real `s3res-train` (once per test process). Then, on other data (`--offset`):
//! a fault-free run raises no alarm (the detectors see data, not timing, and the input is
//! deterministic); under DMR an exponent-bit flip of x or y in one replica's frame is
//! attributed by the detector and repaired by fork, and the output is exactly the fault-free
//! output; under SMR the flagged frame is held back and the replica restarted by exec; under
//! TMR the alarm is logged and the vote decides.
//!
//! The same in stream mode (`stream_*`): `s3res-signal --every 8` answers in bursts of eight
//! frames every eighth input, and the voter scores every frame it takes into its ledger.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;
use std::time::Duration;

use s3res_components::{Signal, SIGNAL_FRAME};
use s3res_testkit::{
    bin_path, signals, sigqueue, Cause, Event, EventKind, RecoveryMethod, Rng, RunningSystem,
    System,
};

const LIMIT: Duration = Duration::from_secs(120);
const TRAIN_FRAMES: u32 = 4000;

/// The monitored fields of a signal frame.
const FIELDS: &str = r#"[
  {"name": "seq", "type": "u64", "offset": 0},
  {"name": "x", "type": "f64", "offset": 8},
  {"name": "y", "type": "f64", "offset": 16},
  {"name": "speed", "type": "f64", "offset": 24},
  {"name": "odometer", "type": "f64", "offset": 32}
]"#;

/// Byte offsets of x and y: their exponent flips are beyond the normal range by construction
/// (x in 30..70, y in 20..40, changing by < 0.5 per frame; see `s3res_components::Signal`).
const FLIPPABLE: [(&str, usize); 2] = [("x", 8), ("y", 16)];

struct Models {
    gaussian: PathBuf,
    autoencoder: PathBuf,
}

/// A system description: the source sends `count` frames at `hz` to `signal`, whose voted
/// output goes to bootstrap's stdout. `extra` is added to the signal → stdout channel.
fn description(signal: &str, count: u32, hz: u32, extra: &str) -> String {
    format!(
        r#"{{
  "name": "anomaly",
  "components": {{
    "source": {{ "exec": "s3res-source", "args": ["--count", "{count}", "--hz", "{hz}"] }},
    "signal": {signal}
  }},
  "channels": [
    {{ "from": "source.out", "to": "signal.in" }},
    {{ "from": "signal.out", "to": "stdout", "max_frame": 64{extra} }}
  ]
}}"#
    )
}

fn signal(redundancy: &str, offset: u64) -> String {
    format!(
        r#"{{ "exec": "s3res-signal", "args": ["--offset", "{offset}"], "redundancy": "{redundancy}", "timeout_us": 500000 }}"#
    )
}

/// `s3res-signal` in stream mode: bursts of eight frames, one every eighth input.
fn stream_signal(redundancy: &str, offset: u64) -> String {
    format!(
        r#"{{ "exec": "s3res-signal", "args": ["--offset", "{offset}", "--every", "8"], "redundancy": "{redundancy}", "mode": "stream", "timeout_us": 500000 }}"#
    )
}

/// The voter's mode for `signal`.
#[derive(Debug, Clone, Copy)]
enum Mode {
    Reactive,
    Stream,
}

impl Mode {
    fn signal(self, redundancy: &str, offset: u64) -> String {
        match self {
            Mode::Reactive => signal(redundancy, offset),
            Mode::Stream => stream_signal(redundancy, offset),
        }
    }
}

fn detector(model: &Path) -> String {
    format!(
        r#", "fields": {FIELDS}, "detector": {{ "model": "{}" }}"#,
        model.display()
    )
}

/// The payloads of a file of length-prefixed frames.
fn frames(path: &Path) -> Vec<Vec<u8>> {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let mut out = Vec::new();
    let mut at = 0;
    while at + 4 <= bytes.len() {
        let len = u32::from_le_bytes(bytes[at..at + 4].try_into().unwrap()) as usize;
        assert!(
            at + 4 + len <= bytes.len(),
            "truncated frame in {}",
            path.display()
        );
        out.push(bytes[at + 4..at + 4 + len].to_vec());
        at += 4 + len;
    }
    assert_eq!(at, bytes.len(), "trailing bytes in {}", path.display());
    out
}

/// What a fault-free `s3res-signal --offset OFFSET` answers to source frames 0..count.
fn expected(offset: u64, count: u32) -> Vec<Vec<u8>> {
    let mut s = Signal::new(offset);
    (0..count as u64)
        .map(|seq| s.answer(seq).to_vec())
        .collect()
}

fn train(kind: &str, layout: &Path, frames: &Path, out: &Path) {
    let status = Command::new(bin_path("s3res-train"))
        .args([kind, "--layout"])
        .arg(layout)
        .arg("--frames")
        .arg(frames)
        .arg("--out")
        .arg(out)
        .status()
        .expect("running s3res-train");
    assert!(status.success(), "s3res-train {kind} failed");
}

/// Captures a fault-free run (SMR, the channel's `capture`) and trains both models on it.
/// Once per test process; the files live in cargo's temp dir for integration tests.
/// Runs `signal` (a component entry) over `count` source frames at offset 0 with a `capture`
/// into `capture`, and checks that the capture is what went downstream and fault-free.
fn capture_fault_free(signal: &str, count: u32, capture: &Path) {
    let extra = format!(r#", "capture": "{}""#, capture.display());
    let mut run = System::new().start(&description(signal, count, 0, &extra));
    run.wait_success(LIMIT);
    let captured = frames(capture);
    assert_eq!(
        captured,
        frames(&run.path("stdout.txt")),
        "the capture is not what the voter forwarded"
    );
    assert_eq!(
        captured,
        expected(0, count),
        "the capture run was not fault-free"
    );
}

/// Runs `signal` (a component entry at `offset`) under `model` on `count` frames as fast as
/// they go, and checks: no alarm, no fault, the output exactly the fault-free output.
fn assert_no_alarm(signal: &str, offset: u64, count: u32, model: &Path) {
    let mut run = System::new().start(&description(signal, count, 0, &detector(model)));
    let outcome = run.wait_success(LIMIT);
    let alarms = of_kind(&outcome.events, EventKind::Anomaly);
    assert!(
        alarms.is_empty(),
        "{signal}: false alarms on fault-free data: {alarms:?}"
    );
    assert!(
        outcome.faults().is_empty(),
        "{signal}: {:?}",
        outcome.faults()
    );
    assert_eq!(frames(&run.path("stdout.txt")), expected(offset, count));
    eprintln!(
        "{signal} with {}: 0 alarms in {count} frames × replicas",
        model.display()
    );
}

fn models() -> &'static Models {
    static MODELS: OnceLock<Models> = OnceLock::new();
    MODELS.get_or_init(|| {
        let dir = Path::new(env!("CARGO_TARGET_TMPDIR"))
            .join(format!("anomaly-models-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let capture = dir.join("train.bin");
        capture_fault_free(&signal("smr", 0), TRAIN_FRAMES, &capture);

        let layout = dir.join("layout.json");
        std::fs::write(&layout, FIELDS).unwrap();
        let models = Models {
            gaussian: dir.join("gaussian.json"),
            autoencoder: dir.join("autoencoder.json"),
        };
        train("gaussian", &layout, &capture, &models.gaussian);
        train("autoencoder", &layout, &capture, &models.autoencoder);
        models
    })
}

/// The events of `kind` about the signal component.
fn of_kind(events: &[Event], kind: EventKind) -> Vec<&Event> {
    s3res_testkit::of_kind(events, "signal", kind)
}

/// The `anomaly` events of corrupted frames, leaving out the alarm on the frame after one
/// (stream mode: a replica running ahead has its next frame scored against the corrupted one
/// before the vote removes it; the voter's cause says so: `alarm_again`).
fn first_alarms(events: &[Event]) -> Vec<&Event> {
    of_kind(events, EventKind::Anomaly)
        .into_iter()
        .filter(|e| e.cause == Some(Cause::Alarm))
        .collect()
}

/// Every alarm was raised by one of `culprits` (pids): none on a healthy replica.
fn assert_alarms_only_on(events: &[Event], culprits: &[i32]) {
    for alarm in of_kind(events, EventKind::Anomaly) {
        assert!(
            alarm.pid.is_some_and(|p| culprits.contains(&p)),
            "alarm on a healthy replica: {alarm:?}"
        );
    }
}

/// Frame bit index of exponent bit `k` (0..11) of the f64 at byte `offset`.
fn exponent_bit(offset: usize, k: u64) -> i32 {
    (offset * 8 + 52 + k as usize) as i32
}

/// Starts `signal` (a component entry: [`Mode::signal`]) with `replicas` under `model`, at
/// 200 frames per second, and waits until its replicas take injections.
fn start_monitored(signal: &str, replicas: usize, count: u32, model: &Path) -> RunningSystem {
    let mut run = System::new().start(&description(signal, count, 200, &detector(model)));
    run.wait_for_replicas("signal", replicas);
    run
}

/// Flips a random exponent bit of x or y in replica `slot`'s next frame and waits until the
/// replica has been replaced. Returns the field, the bit, the replica's pid, and the recovery.
fn flip_and_wait_for_recovery(
    run: &mut RunningSystem,
    rng: &mut Rng,
    slot: usize,
) -> (&'static str, i32, i32, Event) {
    let (field, at) = *rng.pick(&FLIPPABLE);
    let bit = exponent_bit(at, rng.below(11));
    let pid = run.replica_pids("signal")[&slot];
    sigqueue(pid, signals::INJECT_SDC, bit).expect("sigqueue");
    let rec = run.wait_for_event(
        |e| e.kind == EventKind::Recovery && e.component == "signal" && e.pid == Some(pid),
        Duration::from_secs(20),
    );
    assert_eq!(rec.replica, Some(slot), "{rec:?}");
    (field, bit, pid, rec)
}

#[test]
fn a_fault_free_run_raises_no_alarm() {
    let models = models();
    for (redundancy, model) in [("dmr", &models.autoencoder), ("tmr", &models.gaussian)] {
        let offset = 50_000;
        assert_no_alarm(&signal(redundancy, offset), offset, 3000, model);
    }
}

#[test]
fn dmr_attributes_the_flagged_replica_and_repairs_it_by_fork() {
    dmr_attributes(Mode::Reactive);
}

#[test]
fn stream_dmr_attributes_the_flagged_replica_and_repairs_it_by_fork() {
    dmr_attributes(Mode::Stream);
}

fn dmr_attributes(mode: Mode) {
    let models = models();
    let mut rng = Rng::from_env();
    let (offset, count, injections) = (20_000, 2400, 8);
    let mut run = start_monitored(&mode.signal("dmr", offset), 2, count, &models.autoencoder);
    let mut attributed = 0;
    let mut culprits = Vec::new();
    for i in 0..injections {
        std::thread::sleep(Duration::from_millis(rng.range(100, 300)));
        let slot = rng.below(2) as usize;
        let (field, bit, pid, rec) = flip_and_wait_for_recovery(&mut run, &mut rng, slot);
        culprits.push(pid);
        assert_eq!(rec.method, Some(RecoveryMethod::Fork), "{rec:?}");
        assert_eq!(rec.donor, Some(1 - slot), "{rec:?}");
        assert_eq!(rec.state_lost, Some(false), "{rec:?}");
        let events = run.events();
        let sdc = of_kind(&events, EventKind::Sdc)
            .into_iter()
            .find(|e| e.pid == Some(pid))
            .unwrap_or_else(|| panic!("injection {i}: no sdc for pid {pid}"));
        assert_eq!(sdc.replica, Some(slot), "{sdc:?}");
        let alarm = of_kind(&events, EventKind::Anomaly)
            .into_iter()
            .find(|e| e.pid == Some(pid))
            .unwrap_or_else(|| panic!("injection {i}: no anomaly for pid {pid}"));
        assert_eq!(alarm.field.as_deref(), Some(field), "{alarm:?}");
        assert_eq!(alarm.output.as_deref(), Some("out"), "{alarm:?}");
        assert!(
            alarm.score.unwrap_or(f64::INFINITY) > alarm.threshold.unwrap(),
            "{alarm:?}"
        );
        attributed += 1;
        eprintln!("injection {i}: replica {slot}, {field} bit {bit}: anomaly score {:?}, attributed, forked from {}", alarm.score, 1 - slot);
    }
    let outcome = run.wait_success(LIMIT);
    let events = &outcome.events;
    // Exactly the injections: no alarm on the healthy replica, no unattributed sdc.
    assert_eq!(first_alarms(events).len(), injections);
    assert_alarms_only_on(events, &culprits);
    assert_eq!(of_kind(events, EventKind::Sdc).len(), injections);
    assert_eq!(outcome.faults().len(), injections, "{:?}", outcome.faults());
    // The output is the fault-free output, frame for frame: state survived every repair.
    assert_eq!(frames(&run.path("stdout.txt")), expected(offset, count));
    eprintln!(
        "{mode:?} DMR: {attributed} of {injections} exponent flips attributed and repaired by fork"
    );
}

/// SMR under the autoencoder: flips an exponent bit of x or y in the replica's next frame and
/// checks what both modes share: exactly one `anomaly` naming the field, one `sdc` naming the
/// replica with "held back", and a restart by exec with the state lost. Returns the ended run,
/// the alarm, the field and the bit.
fn smr_holds_back(
    mode: Mode,
    offset: u64,
    count: u32,
) -> (RunningSystem, Event, &'static str, i32) {
    let models = models();
    let mut rng = Rng::from_env();
    let mut run = start_monitored(&mode.signal("smr", offset), 1, count, &models.autoencoder);
    // The detector has a history (half a second at 200 Hz) before the flip.
    run.wait_for_stdout_frames(100, Duration::from_secs(20));
    let (field, bit, pid, rec) = flip_and_wait_for_recovery(&mut run, &mut rng, 0);
    assert_eq!(rec.method, Some(RecoveryMethod::Exec), "{rec:?}");
    assert_eq!(rec.state_lost, Some(true), "{rec:?}");
    run.wait_success(LIMIT);
    let events = run.events();
    let alarms = of_kind(&events, EventKind::Anomaly);
    assert_eq!(alarms.len(), 1, "{alarms:?}");
    let alarm = alarms[0].clone();
    assert_eq!(
        (
            alarm.replica,
            alarm.pid,
            alarm.field.as_deref(),
            alarm.output.as_deref()
        ),
        (Some(0), Some(pid), Some(field), Some("out")),
        "{alarm:?}"
    );
    let sdc = of_kind(&events, EventKind::Sdc);
    assert_eq!(sdc.len(), 1, "{sdc:?}");
    assert_eq!((sdc[0].replica, sdc[0].pid), (Some(0), Some(pid)));
    assert_eq!(sdc[0].cause, Some(Cause::AnomalyHeldBack), "{:?}", sdc[0]);
    (run, alarm, field, bit)
}

#[test]
fn smr_holds_the_flagged_frame_back_and_restarts_by_exec() {
    let (offset, count) = (30_000, 800);
    let (run, _, field, bit) = smr_holds_back(Mode::Reactive, offset, count);
    // One frame is missing; every frame that went out has its true position (the corrupted
    // one never did). The odometer restarted with the fresh replica: that is the state lost.
    let out = frames(&run.path("stdout.txt"));
    assert_eq!(out.len(), count as usize - 1);
    let want = expected(offset, count);
    let mut missing = None;
    let mut k = 0;
    for (seq, w) in want.iter().enumerate() {
        if k < out.len() && out[k][..8] == w[..8] {
            assert_eq!(out[k].len(), SIGNAL_FRAME);
            assert_eq!(out[k][..24], w[..24], "seq {seq}: x or y differs");
            k += 1;
        } else {
            assert!(
                missing.is_none(),
                "two frames missing: {missing:?} and {seq}"
            );
            missing = Some(seq);
        }
    }
    eprintln!("SMR: frame {missing:?} held back ({field} bit {bit}), replica restarted by exec");
}

#[test]
fn tmr_logs_the_alarm_and_the_vote_decides() {
    tmr_logs_the_alarm(Mode::Reactive);
}

#[test]
fn stream_tmr_logs_the_alarm_and_the_vote_decides() {
    tmr_logs_the_alarm(Mode::Stream);
}

fn tmr_logs_the_alarm(mode: Mode) {
    let models = models();
    let mut rng = Rng::from_env();
    let (offset, count) = (40_000, 800);
    let mut run = start_monitored(&mode.signal("tmr", offset), 3, count, &models.gaussian);
    // The detector has a history (half a second at 200 Hz) before the flip.
    run.wait_for_stdout_frames(100, Duration::from_secs(20));
    let slot = rng.below(3) as usize;
    let (field, _, pid, rec) = flip_and_wait_for_recovery(&mut run, &mut rng, slot);
    assert_eq!(rec.method, Some(RecoveryMethod::Fork), "{rec:?}");
    run.wait_success(LIMIT);
    let events = run.events();
    assert_alarms_only_on(&events, &[pid]);
    let alarms = first_alarms(&events);
    assert_eq!(alarms.len(), 1, "{alarms:?}");
    assert_eq!(alarms[0].replica, Some(slot));
    assert_eq!(alarms[0].field.as_deref(), Some(field));
    let sdc = of_kind(&events, EventKind::Sdc);
    assert_eq!(sdc.len(), 1, "{sdc:?}");
    assert_eq!(
        sdc[0].cause,
        Some(Cause::Minority),
        "the vote, not the detector, decides under TMR: {:?}",
        sdc[0]
    );
    assert_eq!(frames(&run.path("stdout.txt")), expected(offset, count));
}

/// Stream mode, capture to alarm: a fault-free stream SMR run is captured (the capture is what
/// went downstream), a Gaussian model is trained on it, and fault-free stream runs on other
/// data raise no alarm: DMR under that model, TMR under the autoencoder trained on the
/// reactive capture (the frames are the same whatever the mode).
#[test]
fn stream_capture_train_and_a_fault_free_run_raise_no_alarm() {
    let dir = tempfile::tempdir().unwrap();
    let capture = dir.path().join("stream.bin");
    capture_fault_free(&stream_signal("smr", 0), 2000, &capture);
    let layout = dir.path().join("layout.json");
    std::fs::write(&layout, FIELDS).unwrap();
    let gaussian = dir.path().join("gaussian.json");
    train("gaussian", &layout, &capture, &gaussian);

    let models = models();
    for (redundancy, model) in [("dmr", &gaussian), ("tmr", &models.autoencoder)] {
        let offset = 60_000;
        assert_no_alarm(&stream_signal(redundancy, offset), offset, 2000, model);
    }
}

/// Stream SMR: the flagged frame is held back and the replica restarted by exec. The frames
/// before it went out whole; the restarted replica lost the inputs it held (its burst), so a
/// few frames are missing after it, but every frame that went out is true (x, y) and the
/// stream goes on to its last frame.
#[test]
fn stream_smr_holds_the_flagged_frame_back_and_restarts_by_exec() {
    let (offset, count) = (30_000, 800);
    let (run, alarm, field, bit) = smr_holds_back(Mode::Stream, offset, count);
    // The alarm names the frame's number on the output: everything before it went out as
    // it should, the flagged frame did not.
    let held = alarm
        .frame
        .unwrap_or_else(|| panic!("no frame number in {alarm:?}")) as usize;
    let out = frames(&run.path("stdout.txt"));
    let want = expected(offset, count);
    assert_eq!(out[..held], want[..held], "frames before the held-back one");
    let seq = |f: &[u8]| u64::from_le_bytes(f[..8].try_into().unwrap());
    assert!(seq(&out[held]) > seq(&want[held]), "frame {held} went out");
    for pair in out.windows(2) {
        assert!(seq(&pair[0]) < seq(&pair[1]), "out of order");
    }
    for f in &out {
        let k = (seq(f) - offset) as usize;
        assert_eq!(f[..24], want[k][..24], "seq {}: x or y differs", seq(f));
    }
    assert_eq!(out.last().map(|f| seq(f)), Some(offset + count as u64 - 1));
    eprintln!(
        "stream SMR: frame {held} held back ({field} bit {bit}), {} frames lost with the replica's state, restarted by exec",
        count as usize - out.len()
    );
}
