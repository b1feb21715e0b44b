//! The restart handler, end to end, without the voter: this test plays the voter's part of the
//! handshake against a real replica process.
//!
//! `harness = false` (see Cargo.toml): the helper replica must be single-threaded, and libtest
//! would run it on a worker thread while its main thread waits, so the fork could land in the
//! wrong thread. The same binary is the test (no env var) and the helper replica (env var set).

use std::io::Read;
use std::os::fd::{AsFd, AsRawFd, BorrowedFd, OwnedFd};
use std::os::unix::net::{UnixListener, UnixStream};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{bail, ensure, Context, Result};
use replica_rt::contract::handshake::{
    FdTransfer, Hello, Ready, Rebind, HELLO_MAGIC, READY_MAGIC, REBIND_MAGIC, TRANSFER_MAGIC,
};

/// The nonce this test's "voter" sends with RESTART; the child must echo it.
const NONCE: u32 = 0x5eed;
/// The nonce of an attempt this test's "voter" abandons at once (superseded by [`NONCE`]).
const ABANDONED: u32 = 0xdead;
use replica_rt::contract::{self, signals, Direction, PortMap, PortSpec, MAX_HANDED_FDS};
use replica_rt::{frame, sys};

const HELPER_ENV: &str = "S3RES_RT_TEST_HELPER";
const IN_FD: i32 = 3;
const OUT_FD: i32 = 4;
const MAX_FRAME: usize = 300_000;
const STEP: Duration = Duration::from_secs(5);

/// One test of this harness.
type Test = fn() -> Result<()>;

fn main() {
    if std::env::var_os(HELPER_ENV).is_some() {
        if let Err(e) = helper() {
            eprintln!("helper: {e:#}");
            std::process::exit(1);
        }
        return;
    }
    let tests: [(&str, Test); 4] = [
        ("restart_by_fork", restart_by_fork),
        (
            "unread_input_stays_and_the_child_gets_a_copy",
            unread_input_stays_and_the_child_gets_a_copy,
        ),
        ("rebind_after_voter_death", rebind_after_voter_death),
        (
            "no_successor_ends_the_replica",
            no_successor_ends_the_replica,
        ),
    ];
    if std::env::args().any(|a| a == "--list") {
        for (name, _) in tests {
            println!("{name}: test");
        }
        return;
    }
    let mut failed = false;
    for (name, test) in tests {
        match test() {
            Ok(()) => println!("test {name} ... ok"),
            Err(e) => {
                eprintln!("test {name} ... FAILED: {e:#}");
                failed = true;
            }
        }
    }
    if failed {
        std::process::exit(1);
    }
}

/// A listening socket in a fresh temp dir (kept alive by the returned dir), non-blocking.
fn voter_socket() -> Result<(tempfile::TempDir, std::path::PathBuf, UnixListener)> {
    let dir = tempfile::tempdir()?;
    let path = dir.path().join("voter.sock");
    let listener = UnixListener::bind(&path)?;
    listener.set_nonblocking(true)?;
    Ok((dir, path, listener))
}

/// Starts the helper replica on `p`'s replica ends, its voter socket at `sock`.
fn spawn_helper(p: &Pipes, sock: &std::path::Path) -> Result<Child> {
    let port = |name: &str, dir, fd| PortSpec {
        name: name.into(),
        dir,
        fd,
        max_frame: MAX_FRAME,
    };
    let map = PortMap {
        ports: vec![
            port("in", Direction::In, IN_FD),
            port("out", Direction::Out, OUT_FD),
        ],
    };
    let mut cmd = Command::new(std::env::current_exe()?);
    cmd.env(HELPER_ENV, "1")
        .env(contract::ENV_PORTS, map.to_env())
        .env(contract::ENV_VOTER_SOCKET, sock)
        .env(contract::ENV_REPLICA, "0")
        .env(contract::ENV_COMPONENT, "helper")
        .stdin(Stdio::null());
    sys::map_fds_on_exec(
        &mut cmd,
        vec![
            (p.replica_in.as_raw_fd(), IN_FD),
            (p.replica_out.as_raw_fd(), OUT_FD),
        ],
    );
    cmd.spawn().context("starting the helper replica")
}

/// The voter dies in the middle of a round (its pipe ends close with a frame in flight); the
/// replica comes back to the successor through the rebind handshake, with its counts, takes
/// fresh pipes, and the replayed round is answered once more from its last frame, not run
/// again: the state moves once per input frame.
fn rebind_after_voter_death() -> Result<()> {
    sys::set_child_subreaper()?;
    let (_dir, sock_path, listener) = voter_socket()?;
    let first = pipes()?;
    let helper = spawn_helper(&first, &sock_path)?;
    let pid = helper.id() as libc::pid_t;
    let mut guard = Guard {
        donor: helper,
        forked: Vec::new(),
    };
    drop((first.replica_in, first.replica_out));
    ensure!(roundtrip(&first.to_replica, &first.from_replica, b"a")? == answer(0, b"a"));
    ensure!(roundtrip(&first.to_replica, &first.from_replica, b"b")? == answer(1, b"b"));
    // Frame 2 goes out, and the voter dies: both its ends close, whether or not the replica
    // has read the frame or answered it yet.
    write_frame(&first.to_replica, b"c")?;
    drop((first.to_replica, first.from_replica));

    let (mut stream, peer) = accept_peer(&listener)?;
    ensure!(peer == pid, "rebind from {peer}, the replica is {pid}");
    let mut hello = [0u8; Rebind::SIZE];
    stream.read_exact(&mut hello).context("reading Rebind")?;
    let hello = Rebind::from_bytes(hello);
    ensure!(
        hello.magic == REBIND_MAGIC,
        "Rebind magic {:#x}",
        hello.magic
    );
    ensure!(hello.pid == pid, "Rebind pid {}", hello.pid);
    ensure!(
        hello.frames_taken[0] == 3,
        "frames taken {:?}",
        &hello.frames_taken[..2]
    );
    let sent = hello.frames_sent[1];
    ensure!((2..=3).contains(&sent), "frames sent {sent}");
    let second = pipes()?;
    sys::send_with_fds(
        stream.as_fd(),
        transfer(TRANSFER_MAGIC).as_bytes(),
        &[
            second.replica_in.as_raw_fd(),
            second.replica_out.as_raw_fd(),
        ],
    )?;
    drop((second.replica_in, second.replica_out));
    let mut ready = [0u8; Ready::SIZE];
    stream.read_exact(&mut ready).context("reading Ready")?;
    ensure!(
        Ready::from_bytes(ready).pid == pid,
        "Ready from another pid"
    );

    // The successor replays round 2, then sends frame 3.
    write_raw(&second.to_replica, &frame::resume_frame(2))?;
    write_frame(&second.to_replica, b"c")?;
    write_frame(&second.to_replica, b"d")?;
    let mut dec = frame::FrameDecoder::resuming(MAX_FRAME);
    let c = read_frame_with(&mut dec, second.from_replica.as_fd())?;
    ensure!(c == answer(2, b"c"), "round 2 answered {c:?}");
    let d = read_frame_with(&mut dec, second.from_replica.as_fd())?;
    ensure!(
        d == answer(3, b"d"),
        "round 3 answered {d:?}: the replayed round ran twice"
    );
    // The end, on purpose: the replica exits at once.
    write_raw(&second.to_replica, &frame::end_frame())?;
    drop(second.to_replica);
    let status = wait_exit(&mut guard.donor)?;
    ensure!(status.success(), "replica ended with {status}");
    drop(guard);
    Ok(())
}

/// The voter dies and no successor comes (the socket is gone: the system is ending): the
/// replica ends as at the end of its input, at once and cleanly.
fn no_successor_ends_the_replica() -> Result<()> {
    let dir = tempfile::tempdir()?;
    let sock_path = dir.path().join("voter.sock");
    let listener = UnixListener::bind(&sock_path)?;
    let first = pipes()?;
    let helper = spawn_helper(&first, &sock_path)?;
    let mut guard = Guard {
        donor: helper,
        forked: Vec::new(),
    };
    drop((first.replica_in, first.replica_out));
    ensure!(roundtrip(&first.to_replica, &first.from_replica, b"a")? == answer(0, b"a"));
    drop(listener);
    drop((first.to_replica, first.from_replica));
    let status = wait_exit(&mut guard.donor)?;
    ensure!(status.success(), "replica ended with {status}");
    drop(guard);
    Ok(())
}

/// Waits (bounded) for `child` to exit.
fn wait_exit(child: &mut Child) -> Result<std::process::ExitStatus> {
    let deadline = Instant::now() + STEP;
    loop {
        if let Some(status) = child.try_wait()? {
            return Ok(status);
        }
        ensure!(
            Instant::now() < deadline,
            "replica did not exit within {STEP:?}"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
}

/// Accepts one connection (bounded); the peer's pid.
fn accept_peer(listener: &UnixListener) -> Result<(UnixStream, libc::pid_t)> {
    listener.set_nonblocking(true)?;
    ensure!(
        sys::wait_readable(listener.as_fd(), STEP)?,
        "no connection within {STEP:?}"
    );
    let (stream, _) = listener.accept()?;
    stream.set_nonblocking(false)?;
    stream.set_read_timeout(Some(STEP))?;
    let pid = sys::peer_pid(stream.as_fd())?;
    Ok((stream, pid))
}

fn write_raw(fd: &OwnedFd, bytes: &[u8]) -> Result<()> {
    let n = sys::write(fd.as_fd(), bytes)?;
    ensure!(n == bytes.len(), "short write to the replica");
    Ok(())
}

/// The replica: a stateful echo (each answer is prefixed with the number of answers before it,
/// so a replacement that lost its donor's state shows).
fn helper() -> Result<()> {
    replica_rt::init_logging("rt-helper");
    let mut rt = replica_rt::init()?;
    let mut input = rt.input("in")?;
    let mut output = rt.output("out")?;
    let mut answered: u64 = 0;
    let mut buf = Vec::new();
    while let Some(frame) = input.recv()? {
        buf.clear();
        buf.extend_from_slice(&answered.to_le_bytes());
        buf.extend_from_slice(frame);
        output.send(&buf)?;
        answered += 1;
    }
    Ok(())
}

/// Kills (and reaps, where we may) every process the test caused, also when it fails.
struct Guard {
    donor: Child,
    /// Forked replicas: children of the donor, not ours, so reached through pidfds.
    forked: Vec<OwnedFd>,
}

impl Drop for Guard {
    fn drop(&mut self) {
        for pidfd in &self.forked {
            let _ = sys::pidfd_send_signal(pidfd.as_fd(), libc::SIGKILL);
        }
        let _ = self.donor.kill();
        let _ = self.donor.wait();
        // Forks of the donor that were never accepted (a failure mid-test) are orphans now, and
        // ours, since the test is a child subreaper: kill and reap them too, within a bound.
        sys::sweep_children(STEP);
    }
}

struct Pipes {
    /// Test side: write frames here.
    to_replica: OwnedFd,
    /// Test side: read answers here.
    from_replica: OwnedFd,
    /// Replica side, to be handed over.
    replica_in: OwnedFd,
    replica_out: OwnedFd,
}

fn pipes() -> Result<Pipes> {
    let (replica_in, to_replica) = sys::pipe()?;
    let (from_replica, replica_out) = sys::pipe()?;
    Ok(Pipes {
        to_replica,
        from_replica,
        replica_in,
        replica_out,
    })
}

/// A running helper replica (the donor) that has answered once, and the test's side of it.
struct Donor {
    /// Holds the socket's directory.
    _dir: tempfile::TempDir,
    listener: UnixListener,
    /// The test's ends of the donor's pipes.
    first: TestEnds,
    donor_pid: libc::pid_t,
    guard: Guard,
}

fn start_donor() -> Result<Donor> {
    // Orphans of a failed test (the donor's children) then come to us, for the guard to reap.
    sys::set_child_subreaper()?;
    let (dir, sock_path, listener) = voter_socket()?;
    let p = pipes()?;
    let donor = spawn_helper(&p, &sock_path)?;
    let donor_pid = donor.id() as libc::pid_t;
    let guard = Guard {
        donor,
        forked: Vec::new(),
    };
    drop((p.replica_in, p.replica_out));
    let first = TestEnds {
        to_replica: p.to_replica,
        from_replica: p.from_replica,
    };
    // The first answer also proves init ran, so the handlers are in place before any signal.
    let a = roundtrip(&first.to_replica, &first.from_replica, b"hello")?;
    ensure!(a == answer(0, b"hello"), "first answer {a:?}");
    Ok(Donor {
        _dir: dir,
        listener,
        first,
        donor_pid,
        guard,
    })
}

fn restart_by_fork() -> Result<()> {
    let Donor {
        _dir,
        listener,
        first,
        donor_pid,
        mut guard,
    } = start_donor()?;

    // SDC injection with a chosen bit: bit 8 is the lowest bit of the answer's second byte.
    sys::sigqueue(donor_pid, signals::INJECT_SDC, 8)?;
    let a = roundtrip(&first.to_replica, &first.from_replica, b"flip")?;
    let mut want = answer(1, b"flip");
    want[1] ^= 1;
    ensure!(a == want, "SDC-injected answer {a:?}, expected {want:?}");

    // A handshake with a bad magic: the child must give up (exit), the donor carry on.
    sys::sigqueue(donor_pid, signals::RESTART, NONCE as i32)?;
    let (stream, child) = accept_child(&listener, donor_pid)?;
    guard.forked.push(sys::pidfd_open(child)?);
    let bad = pipes()?;
    let bad_transfer = transfer(0xdead_beef);
    sys::send_with_fds(
        stream.as_fd(),
        bad_transfer.as_bytes(),
        &[bad.replica_in.as_raw_fd(), bad.replica_out.as_raw_fd()],
    )?;
    let pidfd = guard.forked.last().context("pidfd")?;
    ensure!(
        sys::wait_readable(pidfd.as_fd(), STEP)?,
        "a child given a bad handshake did not exit"
    );
    drop(stream);

    // The real restart.
    let started = Instant::now();
    sys::sigqueue(donor_pid, signals::RESTART, NONCE as i32)?;
    let (second, child, ready) = join_child(&listener, donor_pid, &mut guard)?;
    println!("restart: signal to Ready in {:?}", started.elapsed());
    let _ = child;
    // The child reports the whole frames its process had sent per port: two, on `out`.
    let out_position = (OUT_FD - contract::FIRST_PORT_FD) as usize;
    ensure!(
        ready.frames_sent[out_position] == 2 && ready.frames_sent[0] == 0,
        "Ready counts {:?}",
        &ready.frames_sent[..2]
    );

    // Both carry on from the same state: two answers were given before the fork.
    let a = roundtrip(&second.to_replica, &second.from_replica, b"child")?;
    ensure!(a == answer(2, b"child"), "forked child answered {a:?}");
    let a = roundtrip(&first.to_replica, &first.from_replica, b"donor")?;
    ensure!(a == answer(2, b"donor"), "donor answered {a:?}");

    // The end of input, on purpose (an END frame, as a voter ends it), ends the child (the
    // donor reaps it: SIGCHLD is ignored there). Without END the child would take the closed
    // pipe for its voter's death and look for a successor (see `rebind_after_voter_death`).
    write_raw(&second.to_replica, &frame::end_frame())?;
    drop(second.to_replica);
    let pidfd = guard.forked.last().context("pidfd")?;
    ensure!(
        sys::wait_readable(pidfd.as_fd(), STEP)?,
        "forked child did not exit at EOF"
    );

    // RESTARTs while the donor is blocked in the middle of writing a frame larger than a pipe
    // holds are deferred until the frame is out and counted, so the child's new output starts
    // on a frame boundary and its count agrees with the donor's pipe. Two arrive: the later
    // one's nonce wins, and only one child is made. (A masked signal kept the first.)
    let big = vec![0x42u8; 200_000];
    write_frame(&first.to_replica, &big)?;
    std::thread::sleep(Duration::from_millis(50));
    sys::sigqueue(donor_pid, signals::RESTART, ABANDONED as i32)?;
    std::thread::sleep(Duration::from_millis(20));
    sys::sigqueue(donor_pid, signals::RESTART, NONCE as i32)?;
    ensure!(
        !sys::wait_readable(listener.as_fd(), Duration::from_millis(200))?,
        "the donor forked in the middle of writing a frame"
    );
    let a = read_frame(first.from_replica.as_fd())?;
    ensure!(
        a == answer(3, &big),
        "big answer differs ({} bytes)",
        a.len()
    );
    let (third, _, ready) = join_child(&listener, donor_pid, &mut guard)?;
    // "donor" and the big answer came after the first fork: four frames, the big one whole.
    ensure!(
        ready.frames_sent[out_position] == 4,
        "Ready counts {:?}",
        &ready.frames_sent[..2]
    );
    ensure!(
        !sys::wait_readable(listener.as_fd(), Duration::from_millis(200))?,
        "a second child connected: two RESTARTs in one frame made two forks"
    );
    // The donor goes on from the same state, on its old pipe, right after the big frame.
    let a = roundtrip(&first.to_replica, &first.from_replica, b"after")?;
    ensure!(a == answer(4, b"after"), "donor answered {a:?}");
    let a = roundtrip(&third.to_replica, &third.from_replica, b"third")?;
    ensure!(
        a == answer(4, b"third"),
        "second forked child answered {a:?}"
    );

    // Control-flow-error injection: the donor spins and answers nothing.
    sys::kill(donor_pid, signals::inject_cfe())?;
    write_frame(&first.to_replica, b"anyone?")?;
    ensure!(
        !sys::wait_readable(first.from_replica.as_fd(), Duration::from_millis(300))?,
        "the donor answered after a CFE injection"
    );
    drop(guard);
    Ok(())
}

/// A fork recovery leaves the donor's unread input in its pipe, and the child hands the voter
/// a copy behind `Ready`: a frame written while the donor is stopped, with a RESTART pending,
/// comes to the voter behind the child's `Ready` (its length at the input's position); the
/// donor still answers it from its own pipe, and the child answers it from its new one.
fn unread_input_stays_and_the_child_gets_a_copy() -> Result<()> {
    let Donor {
        _dir,
        listener,
        first,
        donor_pid,
        mut guard,
    } = start_donor()?;

    // Stopped, the donor reads nothing: the frame is unread when the RESTART is handled (a
    // continued process takes its pending signals before its read goes on).
    sys::kill(donor_pid, libc::SIGSTOP)?;
    let deadline = Instant::now() + STEP;
    while sys::process_state(donor_pid) != Some('T') {
        ensure!(Instant::now() < deadline, "the donor did not stop");
        std::thread::sleep(Duration::from_millis(1));
    }
    write_frame(&first.to_replica, b"unread")?;
    sys::sigqueue(donor_pid, signals::RESTART, NONCE as i32)?;
    sys::kill(donor_pid, libc::SIGCONT)?;
    let (child, _, ready, mut stream) = join_child_keeping(&listener, donor_pid, &mut guard)?;
    let mut framed = Vec::new();
    frame::encode_into(b"unread", &mut framed);
    let in_position = (IN_FD - contract::FIRST_PORT_FD) as usize;
    ensure!(
        ready.frames_sent[in_position] == framed.len() as u64,
        "Ready says {} bytes unread, the frame is {}",
        ready.frames_sent[in_position],
        framed.len()
    );
    let mut copy = vec![0u8; framed.len()];
    stream
        .read_exact(&mut copy)
        .context("reading the unread input")?;
    ensure!(copy == framed, "the copy is {copy:?}");
    // The donor read it from its own pipe, which still held it.
    let a = read_frame(first.from_replica.as_fd())?;
    ensure!(a == answer(1, b"unread"), "donor answered {a:?}");
    // The child gets it as the voter would give it: at the head of its new pipe.
    let n = sys::write(child.to_replica.as_fd(), &copy)?;
    ensure!(n == copy.len(), "short write to the child");
    let a = read_frame(child.from_replica.as_fd())?;
    ensure!(a == answer(1, b"unread"), "child answered {a:?}");
    drop(guard);
    Ok(())
}

/// Test side of a replacement's pipes.
struct TestEnds {
    to_replica: OwnedFd,
    from_replica: OwnedFd,
}

/// Plays the voter's part of the handshake with the donor's child, after RESTART was sent
/// (the donor had no unread input: the connection is dropped after `Ready`).
fn join_child(
    listener: &UnixListener,
    donor: libc::pid_t,
    guard: &mut Guard,
) -> Result<(TestEnds, libc::pid_t, Ready)> {
    join_child_keeping(listener, donor, guard).map(|(ends, child, ready, _)| (ends, child, ready))
}

/// [`join_child`], and the connection, on which the donor's unread input follows `Ready`.
fn join_child_keeping(
    listener: &UnixListener,
    donor: libc::pid_t,
    guard: &mut Guard,
) -> Result<(TestEnds, libc::pid_t, Ready, UnixStream)> {
    let (mut stream, child) = accept_child(listener, donor)?;
    guard.forked.push(sys::pidfd_open(child)?);
    let p = pipes()?;
    sys::send_with_fds(
        stream.as_fd(),
        transfer(TRANSFER_MAGIC).as_bytes(),
        &[p.replica_in.as_raw_fd(), p.replica_out.as_raw_fd()],
    )?;
    drop((p.replica_in, p.replica_out));
    stream.set_read_timeout(Some(STEP))?;
    let mut ready = [0u8; Ready::SIZE];
    stream.read_exact(&mut ready).context("reading Ready")?;
    let ready = Ready::from_bytes(ready);
    ensure!(ready.magic == READY_MAGIC, "Ready magic {:#x}", ready.magic);
    ensure!(
        ready.pid == child,
        "Ready pid {} but the peer is {child}",
        ready.pid
    );
    Ok((
        TestEnds {
            to_replica: p.to_replica,
            from_replica: p.from_replica,
        },
        child,
        ready,
        stream,
    ))
}

fn transfer(magic: u32) -> FdTransfer {
    let mut targets = [-1; MAX_HANDED_FDS];
    targets[0] = IN_FD;
    targets[1] = OUT_FD;
    FdTransfer {
        magic,
        count: 2,
        targets,
    }
}

/// Accepts the donor's child (bounded), checking through SO_PEERCRED that it is one.
fn accept_child(listener: &UnixListener, donor: libc::pid_t) -> Result<(UnixStream, libc::pid_t)> {
    let deadline = Instant::now() + STEP;
    loop {
        match listener.accept() {
            Ok((stream, _)) => {
                stream.set_nonblocking(false)?;
                let pid = sys::peer_pid(stream.as_fd())?;
                let parent = sys::parent_pid(pid);
                ensure!(
                    parent == Some(donor),
                    "peer {pid} has parent {parent:?}, not the donor {donor}"
                );
                stream.set_read_timeout(Some(STEP))?;
                let mut hello = [0u8; Hello::SIZE];
                (&stream).read_exact(&mut hello).context("reading Hello")?;
                let hello = Hello::from_bytes(hello);
                ensure!(hello.magic == HELLO_MAGIC, "Hello magic {:#x}", hello.magic);
                ensure!(
                    hello.nonce == NONCE,
                    "Hello nonce {:#x}, sent {NONCE:#x}",
                    hello.nonce
                );
                return Ok((stream, pid));
            }
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                let left = deadline.saturating_duration_since(Instant::now());
                if left.is_zero() {
                    bail!("no connection from a forked child within {STEP:?}");
                }
                sys::wait_readable(listener.as_fd(), left)?;
            }
            Err(e) => return Err(e.into()),
        }
    }
}

fn answer(count: u64, payload: &[u8]) -> Vec<u8> {
    let mut v = count.to_le_bytes().to_vec();
    v.extend_from_slice(payload);
    v
}

fn write_frame(fd: &OwnedFd, payload: &[u8]) -> Result<()> {
    let mut bytes = Vec::new();
    frame::encode_into(payload, &mut bytes);
    let n = sys::write(fd.as_fd(), &bytes)?;
    ensure!(n == bytes.len(), "short write to the replica");
    Ok(())
}

fn roundtrip(to: &OwnedFd, from: &OwnedFd, payload: &[u8]) -> Result<Vec<u8>> {
    write_frame(to, payload)?;
    read_frame(from.as_fd())
}

/// Reads exactly one frame, bounded by STEP.
fn read_frame(fd: BorrowedFd<'_>) -> Result<Vec<u8>> {
    read_frame_with(&mut frame::FrameDecoder::new(MAX_FRAME), fd)
}

/// The next frame `dec` decodes from `fd`, reading as needed, bounded by STEP.
fn read_frame_with(dec: &mut frame::FrameDecoder, fd: BorrowedFd<'_>) -> Result<Vec<u8>> {
    let deadline = Instant::now() + STEP;
    loop {
        if let Some(f) = dec.next_frame()? {
            return Ok(f.to_vec());
        }
        let left = deadline.saturating_duration_since(Instant::now());
        ensure!(
            !left.is_zero() && sys::wait_readable(fd, left)?,
            "no answer within {STEP:?}"
        );
        let mut buf = [0u8; 64 * 1024];
        let n = sys::read(fd, &mut buf)?;
        ensure!(n > 0, "replica closed its output");
        dec.push(&buf[..n]);
    }
}
