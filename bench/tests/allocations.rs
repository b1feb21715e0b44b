//! The voter allocates nothing per round in steady state.
//!
//! The voter library runs in-process on its own thread (started exactly as `s3res-voter`'s
//! `main` starts it: `Voter::start(plan)` then `run`), with three real `s3res-echo` replicas.
//! A counting global allocator counts the allocations made *on the voter's thread* only, so
//! the test's own work does not disturb the count. After warm-up rounds at every frame size
//! (buffers grow to their working size once), further rounds must not allocate at all.

use std::alloc::{GlobalAlloc, Layout, System as SystemAlloc};
use std::cell::Cell;
use std::io::{BufRead, BufReader};
use std::os::fd::{AsFd, IntoRawFd, OwnedFd};
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use s3res_voter::event::{Event, EventKind};
use s3res_voter::plan::{ExternalPort, RoundTrigger, VoterPlan};
use s3res_voter::voter::Voter;

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

#[test]
fn steady_state_rounds_do_not_allocate() {
    let echo = s3res_tests::bin_path("s3res-echo");
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
        socket_path: dir.path().join("v.sock"),
        restart_timeout_ms: 1000,
        priority: None,
        cpus: Vec::new(),
        start_timeout_ms: s3res_voter::plan::default_start_timeout_ms(),
        voter_cpu: None,
        schedule: Default::default(),
        realtime: true,
        nice: None,
        mode: Default::default(),
        window: s3res_voter::plan::default_stream_window(),
        monitors: Vec::new(),
        captures: Vec::new(),
    };
    let (done_tx, done_rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        ON_VOTER_THREAD.with(|c| c.set(true));
        let result = Voter::start(plan).and_then(Voter::run);
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
    let frames: Vec<Vec<u8>> = sizes
        .iter()
        .map(|&n| (0..n).map(|i| (i * 7) as u8).collect())
        .collect();
    let mut answer = Vec::new();
    for f in &frames {
        for _ in 0..50 {
            round_trip(&in_w, &out_r, f, &mut answer);
        }
    }
    let before = VOTER_ALLOCS.load(Ordering::Relaxed);
    let rounds = 2000;
    for k in 0..rounds {
        round_trip(&in_w, &out_r, &frames[1 + k % 2], &mut answer);
    }
    let after = VOTER_ALLOCS.load(Ordering::Relaxed);
    eprintln!(
        "voter thread: {} allocations in {rounds} steady-state rounds (8 B and 4 KiB frames)",
        after - before
    );

    // End of input: the voter lets the replicas finish and returns.
    drop(in_w);
    let result = done_rx
        .recv_timeout(LIMIT)
        .expect("the voter did not finish after its input closed");
    assert_eq!(result, Ok(()));
    assert_eq!(
        after - before,
        0,
        "the voter allocated in steady-state rounds"
    );
}
