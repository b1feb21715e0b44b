//! The voter allocates nothing per round in steady state.
//!
//! The voter library runs in-process on its own thread (started exactly as `s3res-voter`'s
//! `main` starts it: `ReactiveVoter::start(plan)` then `run`), with three real `s3res-echo` replicas.
//! A counting global allocator counts the allocations made *on the voter's thread* only, so
//! the test's own work does not disturb the count. After warm-up rounds at every frame size
//! (buffers grow to their working size once), further rounds must not allocate at all.
//! The same holds with an anomaly detector on the output and its voted frames captured to a
//! file.

use std::alloc::{GlobalAlloc, Layout, System as SystemAlloc};
use std::cell::Cell;
use std::io::{BufRead, BufReader};
use std::os::fd::{AsFd, IntoRawFd, OwnedFd};
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use s3res_protocol::event::{Event, EventKind};
use s3res_protocol::plan::{CapturePlan, ExternalPort, MonitorPlan, RoundTrigger, VoterPlan};
use s3res_voter::ReactiveVoter;

struct Counting;

thread_local! {
    static ON_VOTER_THREAD: Cell<bool> = const { Cell::new(false) };
}
static VOTER_ALLOCS: AtomicU64 = AtomicU64::new(0);

fn count() {
    // try_with: no panic while thread-locals are torn down.
    if ON_VOTER_THREAD.try_with(Cell::get).unwrap_or(false) {
        VOTER_ALLOCS.fetch_add(1, Ordering::Relaxed);
    }
}

// SAFETY: every call is forwarded unchanged to the system allocator; counting touches only an
// atomic and a const-initialised thread-local without destructor (neither allocates).
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        count();
        // SAFETY: forwarded with the caller's guarantees.
        unsafe { SystemAlloc.alloc(layout) }
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        count();
        // SAFETY: forwarded with the caller's guarantees.
        unsafe { SystemAlloc.alloc_zeroed(layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        count();
        // SAFETY: forwarded with the caller's guarantees.
        unsafe { SystemAlloc.realloc(ptr, layout, new_size) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: forwarded with the caller's guarantees.
        unsafe { SystemAlloc.dealloc(ptr, layout) }
    }
}

#[global_allocator]
static ALLOCATOR: Counting = Counting;

const LIMIT: Duration = Duration::from_secs(20);

/// Kills the replicas (pids from the start events) if the test ends early.
struct Replicas(Vec<i32>);

impl Drop for Replicas {
    fn drop(&mut self) {
        for &pid in &self.0 {
            let _ = replica_rt::sys::kill(pid, libc::SIGKILL);
            let _ = replica_rt::sys::reap(pid);
        }
    }
}

fn write_frame(fd: &OwnedFd, payload: &[u8]) {
    let mut buf = (payload.len() as u32).to_le_bytes().to_vec();
    buf.extend_from_slice(payload);
    let mut done = 0;
    while done < buf.len() {
        done += replica_rt::sys::write(fd.as_fd(), &buf[done..]).expect("writing a frame");
    }
}

fn read_exact(fd: &OwnedFd, buf: &mut [u8]) {
    let deadline = Instant::now() + LIMIT;
    let mut done = 0;
    while done < buf.len() {
        let left = deadline.saturating_duration_since(Instant::now());
        assert!(
            replica_rt::sys::wait_readable(fd.as_fd(), left).expect("poll"),
            "no answer within {LIMIT:?}"
        );
        let n = replica_rt::sys::read(fd.as_fd(), &mut buf[done..]).expect("reading");
        assert!(n > 0, "the voter closed its output");
        done += n;
    }
}

fn round_trip(input: &OwnedFd, output: &OwnedFd, payload: &[u8], answer: &mut Vec<u8>) {
    write_frame(input, payload);
    let mut len = [0u8; 4];
    read_exact(output, &mut len);
    answer.resize(u32::from_le_bytes(len) as usize, 0);
    read_exact(output, answer);
    assert_eq!(
        answer.as_slice(),
        payload,
        "the voted answer is not the frame"
    );
}

/// The counter is process-wide: one voter at a time.
static ONE_VOTER: std::sync::Mutex<()> = std::sync::Mutex::new(());

#[test]
fn steady_state_rounds_do_not_allocate() {
    steady_state(false);
}

#[test]
fn steady_state_rounds_with_a_detector_and_a_capture_do_not_allocate() {
    steady_state(true);
}

/// Monitored field of the echoed frames: an f64 at byte 0 that moves smoothly from round to
/// round (see [`stamp`]).
const FIELDS: &str = r#"[{"name": "x", "type": "f64", "offset": 0}]"#;

fn stamp(frame: &mut [u8], k: usize) {
    frame[..8].copy_from_slice(&(10.0 * (k as f64 * 0.01).sin()).to_le_bytes());
}

/// A Gaussian model of [`stamp`]'s values, saved in `dir`.
fn model(dir: &std::path::Path) -> std::path::PathBuf {
    let layout: s3res_anomaly::FieldLayout = serde_json::from_str(FIELDS).unwrap();
    let mut trainer = s3res_anomaly::Trainer::new(layout, Default::default());
    let mut frame = vec![0u8; 8];
    for k in 0..5000 {
        stamp(&mut frame, k);
        trainer.push(&frame).unwrap();
    }
    let path = dir.join("model.json");
    trainer.gaussian(6.0, 1e-6).unwrap().save(&path).unwrap();
    path
}

fn steady_state(monitored: bool) {
    let _one = ONE_VOTER.lock().unwrap_or_else(|e| e.into_inner());
    let echo = s3res_testkit::bin_path("s3res-echo");
    let dir = tempfile::tempdir().unwrap();
    let (in_r, in_w) = replica_rt::sys::pipe().unwrap();
    let (out_r, out_w) = replica_rt::sys::pipe().unwrap();
    let (ev_r, ev_w) = replica_rt::sys::pipe().unwrap();
    let max = replica_rt::frame::DEFAULT_MAX_FRAME;
    let plan = VoterPlan {
        system: "alloc-test".into(),
        component: "echo".into(),
        exec: echo,
        args: Vec::new(),
        replicas: 3,
        // Generous: this test is about allocations, not deadlines.
        timeout_us: 5_000_000,
        inputs: vec![ExternalPort {
            name: "in".into(),
            fd: in_r.into_raw_fd(),
            max_frame: max,
        }],
        outputs: vec![ExternalPort {
            name: "out".into(),
            fd: out_w.into_raw_fd(),
            max_frame: max,
        }],
        rounds: vec![RoundTrigger {
            input: "in".into(),
            outputs: vec!["out".into()],
        }],
        events_fd: Some(ev_w.into_raw_fd()),
        heartbeat_fd: None,
        socket_path: dir.path().join("v.sock"),
        socket_fd: None,
        // As s3res-bootstrap runs it: the journal's peek, take and commit are on every round.
        journal_fd: Some(replica_rt::shared::memfd(c"journal").unwrap().into_raw_fd()),
        park_fds: None,
        stamps_fd: None,
        adopt: None,
        restart_timeout_ms: 1000,
        priority: None,
        cpus: Vec::new(),
        start_timeout_ms: s3res_protocol::plan::default_start_timeout_ms(),
        max_restarts: s3res_protocol::plan::default_max_restarts(),
        restart_window_ms: s3res_protocol::plan::default_restart_window_ms(),
        voter_cpu: None,
        schedule: Default::default(),
        realtime: true,
        nice: None,
        mode: Default::default(),
        window: s3res_protocol::plan::default_stream_window(),
        monitors: Vec::new(),
        captures: Vec::new(),
        framing: Default::default(),
        lock_memory: Default::default(),
        cpu_idle: Default::default(),
        spin_us: s3res_protocol::plan::DEFAULT_SPIN_US,
        preload: None,
    };
    let mut plan = plan;
    let capture = dir.path().join("capture.bin");
    if monitored {
        plan.monitors.push(MonitorPlan {
            output: "out".into(),
            fields: serde_json::from_str(FIELDS).unwrap(),
            model: model(dir.path()),
            threshold: None,
        });
        plan.captures.push(CapturePlan {
            output: "out".into(),
            path: capture.clone(),
        });
    }
    let (done_tx, done_rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        ON_VOTER_THREAD.with(|c| c.set(true));
        let result = ReactiveVoter::start(plan).and_then(ReactiveVoter::run);
        ON_VOTER_THREAD.with(|c| c.set(false));
        let _ = done_tx.send(result.map_err(|e| e.to_string()));
    });

    let mut events = BufReader::new(std::fs::File::from(ev_r));
    let mut replicas = Replicas(Vec::new());
    while replicas.0.len() < 3 {
        let mut line = String::new();
        assert!(events.read_line(&mut line).unwrap() > 0, "events closed");
        let ev: Event = serde_json::from_str(&line).unwrap();
        assert_eq!(ev.kind, EventKind::Start, "unexpected event {line}");
        replicas.0.push(ev.pid.unwrap());
    }

    let sizes = [65536usize, 4096, 8];
    let mut frames: Vec<Vec<u8>> = sizes
        .iter()
        .map(|&n| (0..n).map(|i| (i * 7) as u8).collect())
        .collect();
    let mut answer = Vec::new();
    let mut k = 0;
    for f in frames.iter_mut() {
        for _ in 0..50 {
            stamp(f, k);
            k += 1;
            round_trip(&in_w, &out_r, f, &mut answer);
        }
    }
    let before = VOTER_ALLOCS.load(Ordering::Relaxed);
    let rounds = 2000;
    for r in 0..rounds {
        let f = &mut frames[1 + r % 2];
        stamp(f, k);
        k += 1;
        round_trip(&in_w, &out_r, f, &mut answer);
    }
    let after = VOTER_ALLOCS.load(Ordering::Relaxed);
    eprintln!(
        "voter thread (detector and capture: {monitored}): {} allocations in {rounds} steady-state rounds (8 B and 4 KiB frames)",
        after - before
    );

    // End of input: the voter lets the replicas finish and returns.
    drop(in_w);
    let result = done_rx
        .recv_timeout(LIMIT)
        .expect("the voter did not finish after its input closed");
    assert_eq!(result, Ok(()));
    if monitored {
        // Every frame was scored; an alarm would have allocated its event (so none came).
        // The capture holds every voted frame.
        let captured = std::fs::read(&capture).unwrap();
        let expected: usize = sizes.iter().map(|n| (4 + n) * 50).sum::<usize>()
            + (0..rounds).map(|r| 4 + sizes[1 + r % 2]).sum::<usize>();
        assert_eq!(captured.len(), expected, "capture size");
    }
    assert_eq!(
        after - before,
        0,
        "the voter allocated in steady-state rounds"
    );
}
