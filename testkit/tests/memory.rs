//! End to end: the memory side of real-time fidelity.
//!
//! - After a recovery by fork, the donor and the new replica share no physical page of private
//!   writable memory (replica-rt's copy-on-write break). Checked by comparing page frame numbers
//!   from `/proc/PID/pagemap`, which shows them only to CAP_SYS_ADMIN: without it the test is
//!   listed as ignored, with the reason (see `build.rs`).
//! - A refused `mlockall` is reported once per replica process and once by the voter, and the
//!   system runs on.
//! - `lock_memory: used` locks on fault: a replica holds only what it touched, far less than
//!   under `all`, and a fork child locks too.
//! - A component that only polls (`try_recv`) has its fork children lock their memory and keep
//!   a spare line, as one that waits for input does.

use std::collections::HashSet;
use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::Path;
use std::time::{Duration, Instant};

use replica_rt::contract::signals;
use s3res_testkit::{
    assert_sink_whole, bin_path, echo_pipeline, Event, EventKind, RecoveryMethod, RunningSystem,
    System,
};

const LIMIT: Duration = Duration::from_secs(120);
/// Private heap each replica holds, filled.
const HEAP_MIB: usize = 32;

const PAGEMAP_PRESENT: u64 = 1 << 63;
const PAGEMAP_PFN: u64 = (1 << 55) - 1;

/// One line of `/proc/PID/maps`.
struct Mapping {
    start: u64,
    end: u64,
    perms: String,
    path: String,
}

impl Mapping {
    fn private_writable(&self) -> bool {
        let p = self.perms.as_bytes();
        p.len() == 4
            && p[1] == b'w'
            && p[3] == b'p'
            && !matches!(self.path.as_str(), "[vsyscall]" | "[vvar]" | "[vdso]")
    }
}

fn maps(pid: i32) -> Vec<Mapping> {
    let text = std::fs::read_to_string(format!("/proc/{pid}/maps"))
        .unwrap_or_else(|e| panic!("reading /proc/{pid}/maps: {e}"));
    text.lines()
        .map(|line| {
            let mut f = line.split_whitespace();
            let range = f.next().expect("range");
            let perms = f.next().expect("perms").to_owned();
            let path = f.nth(3).unwrap_or("").to_owned();
            let (a, b) = range.split_once('-').expect("start-end");
            Mapping {
                start: u64::from_str_radix(a, 16).expect("hex start"),
                end: u64::from_str_radix(b, 16).expect("hex end"),
                perms,
                path,
            }
        })
        .collect()
}

fn page_size() -> u64 {
    replica_rt::cow::page_size() as u64
}

/// PFNs of the present pages of the mappings of `pid` that `keep` selects.
fn present_pfns(pid: i32, keep: impl Fn(&Mapping) -> bool) -> Vec<u64> {
    present_pages(pid, keep)
        .into_iter()
        .map(|(_, pfn)| pfn)
        .collect()
}

/// `(address, page frame number)` of each present page of the mappings `keep` selects.
fn present_pages(pid: i32, keep: impl Fn(&Mapping) -> bool) -> Vec<(u64, u64)> {
    let pagemap = File::open(format!("/proc/{pid}/pagemap"))
        .unwrap_or_else(|e| panic!("opening /proc/{pid}/pagemap: {e}"));
    let ps = page_size();
    let mut pages = Vec::new();
    for m in maps(pid).iter().filter(|m| keep(m)) {
        let count = ((m.end - m.start) / ps) as usize;
        let mut buf = vec![0u8; count * 8];
        pagemap
            .read_exact_at(&mut buf, m.start / ps * 8)
            .unwrap_or_else(|e| panic!("reading pagemap of {pid} at {:#x}: {e}", m.start));
        for (i, entry) in buf.chunks_exact(8).enumerate() {
            let e = u64::from_le_bytes(entry.try_into().unwrap());
            if e & PAGEMAP_PRESENT != 0 {
                pages.push((m.start + i as u64 * ps, e & PAGEMAP_PFN));
            }
        }
    }
    pages
}

/// The user stack pointer of a stopped process (see [`Stopped`]): the second-to-last field of
/// `/proc/PID/syscall` ("nr args… sp pc", or "-1 sp pc" outside a system call).
fn stack_pointer(pid: i32) -> u64 {
    let text = std::fs::read_to_string(format!("/proc/{pid}/syscall"))
        .unwrap_or_else(|e| panic!("reading /proc/{pid}/syscall: {e}"));
    let fields: Vec<&str> = text.split_whitespace().collect();
    let sp = match fields.as_slice() {
        [_, .., sp, _pc] => sp.trim_start_matches("0x"),
        _ => panic!("/proc/{pid}/syscall of a stopped process: {text:?}"),
    };
    u64::from_str_radix(sp, 16).unwrap_or_else(|e| panic!("/proc/{pid}/syscall {text:?}: {e}"))
}

/// Whether this process may see page frame numbers (they read as 0 without CAP_SYS_ADMIN).
fn pfns_visible() -> bool {
    let probe = vec![1u8; 4 * page_size() as usize];
    let me = std::process::id() as i32;
    let addr = probe.as_ptr() as u64;
    let pfns = present_pfns(me, |m| m.start <= addr && addr < m.end);
    std::hint::black_box(&probe);
    pfns.iter().any(|&p| p != 0)
}

/// `VmLck` of `pid` in kB (0 if unreadable).
fn locked_kb(pid: i32) -> u64 {
    s3res_testkit::procs::locked_kib(pid).unwrap_or(0)
}

/// SIGKILLs replica `victim` and waits for its recovery by fork and for the fork child to
/// have locked its memory (`VmLck` turns non-zero: it locks at its first moment between rounds,
/// once it has answered; the voter reports the recovery at its `Ready`, after its
/// copy-on-write walk). Returns the recovery event.
fn kill_and_wait_for_locked_fork_child(run: &mut RunningSystem, victim: i32) -> Event {
    s3res_testkit::kill_pid(victim, libc::SIGKILL).unwrap();
    let rec = run.wait_for_event(
        |e| e.kind == EventKind::Recovery && e.pid == Some(victim),
        Duration::from_secs(20),
    );
    assert_eq!(rec.method, Some(RecoveryMethod::Fork), "{rec:?}");
    let child = rec.new_pid.expect("new pid");
    let deadline = Instant::now() + Duration::from_secs(10);
    while locked_kb(child) == 0 {
        assert!(
            Instant::now() < deadline,
            "the fork child {child} never locked its memory (VmLck stays 0)"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
    rec
}

/// Sends SIGCONT on drop, so a failed assertion never leaves the donor stopped.
struct Stopped(i32);

impl Stopped {
    fn new(pid: i32) -> Stopped {
        s3res_testkit::kill_pid(pid, libc::SIGSTOP)
            .unwrap_or_else(|e| panic!("SIGSTOP {pid}: {e}"));
        let stopped = Stopped(pid);
        // The signal is sent, not yet taken: what is read of the process must be of it
        // stopped (its stack pointer and its pages at one moment).
        s3res_testkit::wait_state(pid, "T", Duration::from_secs(10));
        stopped
    }
}

impl Drop for Stopped {
    fn drop(&mut self) {
        let _ = s3res_testkit::kill_pid(self.0, libc::SIGCONT);
    }
}

/// Kill a replica of a TMR echo that holds 32 MiB of filled heap; once its fork child has
/// finished the copy-on-write break (the recovery is reported at its `Ready`, after the walk;
/// and `VmLck` is non-zero), stop the donor and the child and compare the page frames: no present private
/// writable page of the child may be one of the donor's, but for its stack below its stack
/// pointer, which holds nothing live and is left shared on purpose (replica-rt's `cow`). The
/// executable's code pages, which both map from the page cache, must be seen shared — the
/// check that the comparison can see sharing at all.
#[test]
#[cfg_attr(
    not(s3res_pagemap_pfns),
    ignore = "needs CAP_SYS_ADMIN (root): /proc/PID/pagemap shows page frame numbers only to it"
)]
fn donor_and_fork_child_share_no_private_page() {
    s3res_testkit::require(
        pfns_visible(),
        "/proc/PID/pagemap shows page frame numbers only to CAP_SYS_ADMIN; here they read as 0",
    );
    let count = 2500;
    let sys = System::new();
    let echo = format!(
        r#"{{ "exec": "s3res-echo", "args": ["--stateful", "--heap-mib", "{HEAP_MIB}"],
             "redundancy": "tmr", "timeout_us": 1000000 }}"#
    );
    let desc = echo_pipeline(&sys.path("summary.json"), &echo, count, 500);
    let mut run = sys.start(&desc);
    run.wait_for_replicas("echo", 3);
    let first = run.replica_pids("echo");

    let rec = kill_and_wait_for_locked_fork_child(&mut run, first[&2]);
    let child = rec.new_pid.expect("new pid");
    let donor = first[&rec.donor.expect("donor")];

    let (donor_private, child_pages, child_sp, child_stack, donor_code, child_code) = {
        let _stopped = Stopped::new(donor);
        let _child_stopped = Stopped::new(child);
        let code = |m: &Mapping| m.perms.starts_with("r-x") && m.path.ends_with("/s3res-echo");
        let stack = maps(child)
            .into_iter()
            .find(|m| m.path == "[stack]")
            .map(|m| (m.start, m.end))
            .expect("the child's [stack] mapping");
        (
            present_pfns(donor, Mapping::private_writable),
            present_pages(child, Mapping::private_writable),
            stack_pointer(child),
            stack,
            present_pfns(donor, code),
            present_pfns(child, code),
        )
    };
    // Pages wholly below the child's stack pointer, in its stack.
    let dead =
        |addr: u64| addr >= child_stack.0 && addr < child_stack.1 && addr + page_size() <= child_sp;
    let child_private: Vec<u64> = child_pages
        .iter()
        .filter(|(addr, _)| !dead(*addr))
        .map(|&(_, pfn)| pfn)
        .collect();
    let below_sp = child_pages.len() - child_private.len();
    let donor_set: HashSet<u64> = donor_private.iter().copied().collect();
    let shared: Vec<u64> = child_private
        .iter()
        .copied()
        .filter(|p| donor_set.contains(p))
        .collect();
    let donor_code: HashSet<u64> = donor_code.into_iter().collect();
    let code_shared = child_code.iter().filter(|p| donor_code.contains(p)).count();
    eprintln!(
        "page frames: donor {donor} {} private writable present, child {child} {} checked \
         ({below_sp} below its stack pointer {child_sp:#x} not), shared {}; code pages shared \
         (control) {code_shared} of {}",
        donor_private.len(),
        child_private.len(),
        shared.len(),
        child_code.len()
    );
    let heap_pages = (HEAP_MIB as u64) << 20 >> page_size().trailing_zeros();
    assert!(
        child_private.len() as u64 >= heap_pages,
        "the child has {} private pages present, fewer than its {heap_pages}-page heap",
        child_private.len()
    );
    assert!(
        code_shared > 0,
        "control failed: donor and child share no code page, so the PFN comparison sees nothing"
    );
    assert!(
        shared.is_empty(),
        "{} private writable pages of the child {child} are still the donor's: {:x?}",
        shared.len(),
        &shared[..shared.len().min(16)]
    );

    run.wait_success(LIMIT);
    assert_sink_whole(&run.path("summary.json"), count);
}

/// The unix sockets `pid` holds (`socket:[…]` links in `/proc/PID/fd`).
fn sockets_held(pid: i32) -> usize {
    std::fs::read_dir(format!("/proc/{pid}/fd"))
        .map(|fds| {
            fds.filter_map(|fd| std::fs::read_link(fd.ok()?.path()).ok())
                .filter(|target| target.to_string_lossy().starts_with("socket:"))
                .count()
        })
        .unwrap_or(0)
}

/// Waits (10 s at most) until `who`, replica process `pid`, holds one socket: its spare line.
fn wait_for_one_socket(pid: i32, who: &str) {
    let deadline = Instant::now() + Duration::from_secs(10);
    while sockets_held(pid) != 1 {
        assert!(
            Instant::now() < deadline,
            "{who} ({pid}) of a polling component made no spare line in 10 s (it holds {} \
             sockets)",
            sockets_held(pid)
        );
        std::thread::sleep(Duration::from_millis(5));
    }
}

/// A component that never blocks for input, only looks for it with `try_recv` (`s3res-echo
/// --poll-us`), is looked after as one that waits: a fork child of it locks its memory, and
/// makes the spare line for its own next fork child (replica-rt's `restart::between_rounds`,
/// which `try_recv` did not call before stop 51). A replica holds exactly one socket, that
/// line: the child's first one (its donor's, on which it joined) is closed at its `Ready`.
#[test]
fn a_component_that_only_polls_locks_its_fork_children_and_keeps_spare_lines() {
    let count = 2000;
    let sys = System::new();
    let echo = r#"{ "exec": "s3res-echo", "args": ["--stateful", "--poll-us", "200"], "redundancy": "tmr", "timeout_us": 1000000 }"#;
    let desc = echo_pipeline(&sys.path("summary.json"), echo, count, 500);
    let mut run = sys.start(&desc);
    // (Not `wait_for_answers`: it looks for replicas blocked reading their input.)
    run.wait_for_replicas("echo", 3);
    let first = run.replica_pids("echo");
    // Its handlers are in place; its lock, then its spare line, come at the end of its init.
    wait_for_one_socket(first[&0], "a replica started by exec");
    s3res_testkit::require(
        locked_kb(first[&0]) > 0,
        "the replica's mlockall was refused (raise RLIMIT_MEMLOCK)",
    );
    let rec = kill_and_wait_for_locked_fork_child(&mut run, first[&2]);
    wait_for_one_socket(rec.new_pid.expect("new pid"), "the fork child");
    run.wait_success(LIMIT);
    assert_sink_whole(&run.path("summary.json"), count);
}

/// Runs bootstrap under `RLIMIT_MEMLOCK=0` (and, as root, without CAP_IPC_LOCK, which would
/// ignore the limit): every replica's `mlockall` is refused, and the voter's. Bootstrap says
/// so once for the system; the voter and the replicas, told so (`S3RES_MEMORY_LOCK_SAID`), do
/// not each say it again (before, each process did: 18 lines of one start under a 64 KiB
/// limit). A crash is still recovered by fork, and every frame gets through.
#[test]
#[cfg_attr(
    not(s3res_prlimit),
    ignore = "needs `prlimit` (and, as root, `setpriv`) from util-linux"
)]
fn refused_mlockall_is_reported_once_and_the_system_runs_on() {
    let root = s3res_testkit::is_root();
    let tools: &[&str] = if root {
        &["setpriv", "prlimit"]
    } else {
        &["prlimit"]
    };
    for tool in tools {
        s3res_testkit::require(
            which(tool).is_some(),
            &format!("`{tool}` (util-linux) is not installed"),
        );
    }
    let count = 1500;
    let sys = System::new();
    let wrapper = sys.path("limited-bootstrap.sh");
    let drop_cap = if root {
        "setpriv --bounding-set -ipc_lock --inh-caps -ipc_lock "
    } else {
        ""
    };
    std::fs::write(
        &wrapper,
        format!(
            "#!/bin/sh\nexec {drop_cap}prlimit --memlock=0:0 -- {} \"$@\"\n",
            bin_path("s3res-bootstrap").display()
        ),
    )
    .unwrap();
    make_executable(&wrapper);
    let echo = r#"{ "exec": "s3res-echo", "args": ["--stateful"], "redundancy": "tmr", "timeout_us": 1000000 }"#;
    let desc = echo_pipeline(&sys.path("summary.json"), echo, count, 500);
    let mut run = sys.start_with(&wrapper, &desc);
    run.wait_for_replicas("echo", 3);
    let first = run.replica_pids("echo");
    s3res_testkit::kill_pid(first[&1], libc::SIGKILL).unwrap();
    let rec = run.wait_for_event(
        |e| e.kind == EventKind::Recovery && e.pid == Some(first[&1]),
        Duration::from_secs(20),
    );
    assert_eq!(rec.method, Some(RecoveryMethod::Fork), "{rec:?}");
    let child = rec.new_pid.unwrap();
    assert_eq!(
        locked_kb(child),
        0,
        "the fork child locked memory after all"
    );

    let out = run.wait_success(LIMIT);
    let said = out
        .stderr
        .matches("memory locking is limited to 0 KiB")
        .count();
    let reports = out.stderr.matches("mlockall refused").count();
    let voter_reports = out
        .stderr
        .matches("the voter could not lock its memory")
        .count();
    eprintln!(
        "the limit said {said} times, refusals by replicas {reports}, by the voter {voter_reports}"
    );
    assert_eq!(
        (said, reports, voter_reports),
        (1, 0, 0),
        "bootstrap says the limit once, no replica or voter again; stderr:\n{}",
        s3res_testkit::tail(&out.stderr, 40)
    );
    assert_sink_whole(&run.path("summary.json"), count);
}

/// One mapping of `/proc/PID/smaps`: its range, name, resident size and `VmFlags`.
#[derive(Debug)]
struct Smap {
    start: u64,
    end: u64,
    name: String,
    rss_kb: u64,
    flags: Vec<String>,
}

fn smaps(pid: i32) -> Vec<Smap> {
    let text = std::fs::read_to_string(format!("/proc/{pid}/smaps"))
        .unwrap_or_else(|e| panic!("reading /proc/{pid}/smaps: {e}"));
    let mut out: Vec<Smap> = Vec::new();
    for line in text.lines() {
        let mut f = line.split_whitespace();
        let first = f.next().unwrap_or("");
        if let Some((a, b)) = first.split_once('-').filter(|_| !first.ends_with(':')) {
            out.push(Smap {
                start: u64::from_str_radix(a, 16).expect("hex start"),
                end: u64::from_str_radix(b, 16).expect("hex end"),
                name: f.nth(4).unwrap_or("").to_owned(),
                rss_kb: 0,
                flags: Vec::new(),
            });
        } else if let Some(last) = out.last_mut() {
            match first {
                "Rss:" => last.rss_kb = f.next().and_then(|v| v.parse().ok()).unwrap_or(0),
                "VmFlags:" => last.flags = f.map(str::to_owned).collect(),
                _ => {}
            }
        }
    }
    out
}

/// `pid`'s stack: the `[stack]` mapping and the one right under it, if that one was split
/// from it by a lock-on-fault flag (a fork child, which locks everything on fault, has them
/// merged again); and the heap.
fn stack_and_heap(pid: i32) -> (Vec<Smap>, Option<Smap>) {
    let maps = smaps(pid);
    let mut stack = Vec::new();
    let mut heap = None;
    if let Some(k) = maps.iter().position(|m| m.name == "[stack]") {
        if k > 0 && maps[k - 1].end == maps[k].start && maps[k - 1].name.is_empty() {
            stack.push(k - 1);
        }
        stack.push(k);
    }
    let mut stack_maps = Vec::new();
    for (k, m) in maps.into_iter().enumerate() {
        if stack.contains(&k) {
            stack_maps.push(m);
        } else if m.name == "[heap]" {
            heap = Some(m);
        }
    }
    (stack_maps, heap)
}

/// A replica locks its memory, but not what it never uses: the stack below the 32 KiB that
/// replica-rt keeps (`memory::STACK_LOCKED`) is locked on fault and not resident, and the heap
/// carries no 128 KiB malloc pad (every resident private page is copied at each fork recovery).
/// A fork child, which locks on fault, keeps it so.
#[test]
fn a_replica_keeps_neither_unused_stack_nor_malloc_slack_resident() {
    let count = 1500;
    let (mut run, first) = start_locked_echo("all", count);
    let pid = first[&0];
    let check = |pid: i32, who: &str| {
        let (stack, heap) = stack_and_heap(pid);
        let size_kb: u64 = stack.iter().map(|m| (m.end - m.start) / 1024).sum();
        let rss_kb: u64 = stack.iter().map(|m| m.rss_kb).sum();
        eprintln!(
            "{who} {pid}: stack {size_kb} KiB mapped, {rss_kb} KiB resident ({:?}); heap {:?} KiB resident",
            stack.iter().map(|m| (&m.name, m.rss_kb, m.flags.join(" "))).collect::<Vec<_>>(),
            heap.as_ref().map(|h| h.rss_kb)
        );
        assert!(
            stack
                .first()
                .is_some_and(|m| m.flags.iter().any(|f| f == "lf")),
            "{who} {pid}: the bottom of the stack is not locked on fault: {stack:#?}"
        );
        // What lies above the stack pointer at init (arguments, environment, the frames
        // under `init`) stays resident with the 32 KiB kept; the rest must not be.
        assert!(
            rss_kb + 32 <= size_kb,
            "{who} {pid}: {rss_kb} of its {size_kb} KiB of stack are resident"
        );
        if let Some(heap) = heap {
            assert!(
                heap.rss_kb < 128,
                "{who} {pid}: {} KiB of heap resident, the malloc pad is back",
                heap.rss_kb
            );
        }
    };
    check(pid, "replica");

    let rec = kill_and_wait_for_locked_fork_child(&mut run, first[&2]);
    let child = rec.new_pid.expect("new pid");
    check(child, "fork child");

    run.wait_success(LIMIT);
    assert_sink_whole(&run.path("summary.json"), count);
}

/// `VmRSS` of `pid` in kB (0 if unreadable).
fn resident_kb(pid: i32) -> u64 {
    status_kb(pid, "VmRSS:")
}

fn status_kb(pid: i32, key: &str) -> u64 {
    std::fs::read_to_string(format!("/proc/{pid}/status"))
        .ok()
        .and_then(|s| {
            s.lines()
                .find_map(|l| l.strip_prefix(key))
                .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        })
        .unwrap_or(0)
}

/// Starts a TMR stateful echo of `count` frames whose replicas lock `lock_memory` in a new
/// system's folder, and waits
/// until all three have answered; the pids by slot. Skips the test if locking is refused.
fn start_locked_echo(
    lock_memory: &str,
    count: u32,
) -> (RunningSystem, std::collections::BTreeMap<usize, i32>) {
    let sys = System::new();
    let echo = format!(
        r#"{{ "exec": "s3res-echo", "args": ["--stateful"], "redundancy": "tmr", "timeout_us": 1000000, "lock_memory": "{lock_memory}" }}"#
    );
    let desc = echo_pipeline(&sys.path("summary.json"), &echo, count, 500);
    let mut run = sys.start(&desc);
    run.wait_for_replicas("echo", 3);
    run.wait_for_answers("echo");
    let first = run.replica_pids("echo");
    s3res_testkit::require(
        locked_kb(first[&0]) > 0,
        "the replica's mlockall was refused (raise RLIMIT_MEMLOCK)",
    );
    (run, first)
}

/// A TMR echo whose replicas lock `lock_memory` (`all` or `used`): the resident and locked
/// sizes of one replica once all have answered, and of a fork child after a crash; every
/// frame gets through.
fn echo_memory(lock_memory: &str) -> [(u64, u64); 2] {
    let count = 1000;
    let (mut run, first) = start_locked_echo(lock_memory, count);
    let pid = first[&0];
    let replica = (resident_kb(pid), locked_kb(pid));
    let voter = run.voter_of("echo").expect("the echo's voter");
    assert!(
        locked_kb(voter) > 0,
        "lock_memory {lock_memory}: the voter {voter} locked nothing"
    );
    let rec = kill_and_wait_for_locked_fork_child(&mut run, first[&1]);
    let child = rec.new_pid.expect("new pid");
    let forked = (resident_kb(child), locked_kb(child));
    eprintln!(
        "lock_memory {lock_memory}: replica {pid} {} KiB resident of {} KiB locked; fork child \
         {child} {} of {}",
        replica.0, replica.1, forked.0, forked.1
    );
    run.wait_success(LIMIT);
    assert_sink_whole(&run.path("summary.json"), count);
    [replica, forked]
}

/// `lock_memory: all` (the default) makes every locked page resident at start; `used` locks
/// the same mappings on fault, so that a replica holds only what it touched: a good deal less
/// of the same binary. A fork child locks as its donor did, the voter locks too, and the
/// system loses nothing.
#[test]
fn lock_memory_used_keeps_only_touched_pages_resident() {
    let [all, _] = echo_memory("all");
    let [used, used_child] = echo_memory("used");
    // `all`: everything locked is resident but the stack below what replica-rt keeps
    // (locked on fault, 100-odd KiB) and the odd guard.
    assert!(
        all.0 + 512 >= all.1,
        "lock_memory all: only {} of {} KiB locked are resident",
        all.0,
        all.1
    );
    // `used`: the same binary, with the text and data it never touched left out.
    assert!(
        used.0 + 512 < all.0,
        "lock_memory used: {} KiB resident, against {} KiB with all",
        used.0,
        all.0
    );
    assert!(
        used.0 + 512 < used.1,
        "lock_memory used: {} of {} KiB locked are resident, as if populated",
        used.0,
        used.1
    );
    assert!(used_child.1 > 0, "the fork child did not lock its memory");
}

fn which(tool: &str) -> Option<std::path::PathBuf> {
    std::env::var_os("PATH").and_then(|paths| {
        std::env::split_paths(&paths)
            .map(|d| d.join(tool))
            .find(|p| p.is_file())
    })
}

fn make_executable(path: &Path) {
    use std::os::unix::fs::PermissionsExt;
    std::fs::set_permissions(path, std::fs::Permissions::from_mode(0o755)).unwrap();
}

/// The shared libraries that process `pid` maps (none for a statically linked executable).
fn shared_libraries(pid: i32) -> Vec<String> {
    let mut libs: Vec<String> = maps(pid)
        .into_iter()
        .map(|m| m.path)
        .filter(|p| p.contains(".so"))
        .collect();
    libs.dedup();
    libs
}

/// The `PT_GNU_RELRO` segment of the ELF executable `exe`, `(p_vaddr, p_memsz)`, and the
/// `p_vaddr` of its first loadable segment.
fn relro_segment(exe: &Path) -> Option<((u64, u64), u64)> {
    const PT_LOAD: u32 = 1;
    const PT_GNU_RELRO: u32 = 0x6474_e552;
    let elf = std::fs::read(exe).unwrap_or_else(|e| panic!("{}: {e}", exe.display()));
    assert_eq!(
        &elf[..5],
        b"\x7fELF\x02",
        "{} is not a 64-bit ELF file",
        exe.display()
    );
    let u16_at = |at: usize| u16::from_le_bytes(elf[at..at + 2].try_into().unwrap());
    let u32_at = |at: usize| u32::from_le_bytes(elf[at..at + 4].try_into().unwrap());
    let u64_at = |at: usize| u64::from_le_bytes(elf[at..at + 8].try_into().unwrap());
    let (phoff, phentsize, phnum) = (u64_at(0x20) as usize, u16_at(0x36), u16_at(0x38));
    let headers = (0..usize::from(phnum)).map(|i| phoff + i * usize::from(phentsize));
    let (mut relro, mut first_load) = (None, None);
    for h in headers {
        match u32_at(h) {
            PT_GNU_RELRO => relro = Some((u64_at(h + 16), u64_at(h + 40))),
            PT_LOAD if first_load.is_none() => first_load = Some(u64_at(h + 16)),
            _ => {}
        }
    }
    Some((relro?, first_load?))
}

/// The whole pages of `exe`'s relocated read-only data in process `pid` are mapped, and none
/// of them writable.
fn assert_relro_read_only(pid: i32, exe: &Path, segment: ((u64, u64), u64), who: &str) {
    let ((vaddr, memsz), first_load) = segment;
    let page = page_size();
    let path = exe.to_str().expect("a UTF-8 path");
    let mapped = maps(pid);
    let ours: Vec<&Mapping> = mapped.iter().filter(|m| m.path == path).collect();
    let lowest = ours
        .iter()
        .map(|m| m.start)
        .min()
        .expect("the executable is mapped");
    let base = lowest - (first_load & !(page - 1));
    let (start, end) = (
        (base + vaddr) & !(page - 1),
        (base + vaddr + memsz) & !(page - 1),
    );
    let mut covered = 0;
    for m in &ours {
        let (a, b) = (m.start.max(start), m.end.min(end));
        if a < b {
            assert!(
                !m.perms.contains('w'),
                "{who}: relocated read-only data {start:#x}-{end:#x} is writable: {:#x}-{:#x} {}",
                m.start,
                m.end,
                m.perms
            );
            covered += b - a;
        }
    }
    assert_eq!(
        covered,
        end - start,
        "{who}: {start:#x}-{end:#x} is not all mapped"
    );
}

/// A statically linked replica (docs/writing-a-component.md, "Statically linked"), built as
/// that section says: kill two replicas of a TMR stateful echo built so, one after the other.
/// Each is recovered by fork into a new process of the same executable, which maps no shared
/// library, as its donor did, and carries on counting: every frame gets through with the
/// echo's count unbroken.
#[test]
#[cfg_attr(
    not(s3res_cc_static),
    ignore = "needs a static C library (Debian's libc6-dev) to link a static executable"
)]
fn a_statically_linked_replica_is_recovered_by_fork_with_its_state() {
    let exe = s3res_testkit::bins::static_component_dir().join("s3res-echo");
    static_replicas_recovered_by_fork(&exe);
}

/// A small replica (docs/writing-a-component.md, "Small replicas"), built as that section
/// says: for musl, in the `replica` profile, where a panic aborts. Killed and recovered as the
/// statically linked one above, with its state.
#[test]
#[cfg_attr(
    not(all(s3res_musl_target, s3res_cc)),
    ignore = "needs the musl target's standard library (rustup target add x86_64-unknown-linux-musl) and a C compiler to link with"
)]
fn a_small_replica_built_for_musl_is_recovered_by_fork_with_its_state() {
    let exe = s3res_testkit::bins::musl_component_dir().join("s3res-echo");
    static_replicas_recovered_by_fork(&exe);
}

/// Runs `exe`, a statically linked `s3res-echo`, as a TMR stateful echo and kills two of its
/// replicas, one after the other: each comes back by fork, with its state, as a process of the
/// same executable that maps no shared library. Then the third is sent the control-flow-error
/// signal, by the number the contract fixes (a replica built on another C library than the
/// voter and this test hooks the same number): it spins, is caught as a hang and is replaced
/// by fork. Every frame gets through.
fn static_replicas_recovered_by_fork(exe: &Path) {
    let exe = std::fs::canonicalize(exe)
        .unwrap_or_else(|e| panic!("{} after its build: {e}", exe.display()));
    let count = 2000;
    let sys = System::new();
    let echo = format!(
        r#"{{ "exec": {}, "args": ["--stateful"], "redundancy": "tmr", "timeout_us": 1000000 }}"#,
        serde_json::to_string(&exe).expect("a path as a JSON string")
    );
    let desc = echo_pipeline(&sys.path("summary.json"), &echo, count, 500);
    let mut run = sys.start(&desc);
    run.wait_for_replicas("echo", 3);
    run.wait_for_answers("echo");
    let relro = relro_segment(&exe)
        .unwrap_or_else(|| panic!("{} has no PT_GNU_RELRO segment", exe.display()));
    let runs_static_echo = |pid: i32, who: &str| {
        let running = std::fs::read_link(format!("/proc/{pid}/exe"))
            .unwrap_or_else(|e| panic!("{who} {pid}: /proc/{pid}/exe: {e}"));
        assert_eq!(running, exe, "{who} {pid} runs another executable");
        let libs = shared_libraries(pid);
        assert!(
            libs.is_empty(),
            "{who} {pid} maps shared libraries: {libs:?}"
        );
        // The relocated read-only data is read-only: musl's static start-up leaves it
        // writable and replica-rt protects it (glibc's protects it itself); a fork child
        // inherits that (its copy-on-write walk leaves those pages shared).
        assert_relro_read_only(pid, &exe, relro, &format!("{who} {pid}"));
    };
    for (slot, pid) in run.replica_pids("echo") {
        runs_static_echo(pid, &format!("replica {slot}"));
    }
    // Two crashes, then a control-flow error (a spin, caught as a hang).
    for (slot, sig) in [
        (2, libc::SIGKILL),
        (0, libc::SIGKILL),
        (1, signals::inject_cfe()),
    ] {
        let victim = run.replica_pids("echo")[&slot];
        s3res_testkit::kill_pid(victim, sig).unwrap();
        if sig != libc::SIGKILL {
            run.wait_for_event(
                |e| e.kind == EventKind::Hang && e.pid == Some(victim),
                Duration::from_secs(20),
            );
        }
        let rec = run.wait_for_recovery("echo", slot, victim);
        assert_eq!(rec.method, Some(RecoveryMethod::Fork), "{rec:?}");
        assert_eq!(rec.state_lost, Some(false), "{rec:?}");
        let child = rec.new_pid.expect("new pid");
        assert_ne!(child, victim);
        runs_static_echo(child, &format!("the fork child in slot {slot}"));
        eprintln!(
            "slot {slot}: {victim} sent signal {sig}, {child} forked from slot {:?}",
            rec.donor
        );
    }
    run.wait_success(LIMIT);
    assert_sink_whole(&run.path("summary.json"), count);
}
