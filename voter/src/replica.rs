//! One replica process as the voter holds it: its pid and pidfd, and the voter's ends of its
//! pipes. Initial start (and recovery without a healthy donor) is by exec.

use std::io;
use std::os::fd::{AsFd, AsRawFd, BorrowedFd, OwnedFd, RawFd};
use std::process::{Command, Stdio};
use std::time::Duration;

use replica_rt::contract::{
    Direction, PortMap, PortSpec, ENV_COMPONENT, ENV_PORTS, ENV_REPLICA, ENV_STAMPS_FD,
    ENV_STARTED_FD, ENV_VOTER_SOCKET, FIRST_PORT_FD, STARTED,
};
use replica_rt::sys;

use crate::channel::{FrameReader, FrameWriter, Staging};
use crate::plan::{Framing, VoterPlan};
use crate::starvation::{Sample, SchedStat};
use replica_rt::stderr_relay::StderrRelay;

/// The voter's end of one replica input pipe. The voter keeps the read end too, so that it can
/// take back input the replica has not consumed when the replica becomes a recovery donor.
#[derive(Debug)]
pub struct ReplicaInput {
    pub writer: FrameWriter,
    pub read_end: OwnedFd,
}

/// A late replica's pipes at its deadline (see [`Replica::pipe_backlog`]); `None`: the kernel
/// did not say.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PipeBacklog {
    pub input_unread: Option<usize>,
    pub input_queued: usize,
    pub output_unread: Option<usize>,
}

impl std::fmt::Display for PipeBacklog {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let bytes = |n: Option<usize>| n.map_or_else(|| "?".to_owned(), |n| n.to_string());
        write!(
            f,
            "its input: {} B unread in the pipe, {} B queued in the voter; its output: {} B \
             unread in the pipe",
            bytes(self.input_unread),
            self.input_queued,
            bytes(self.output_unread)
        )
    }
}

#[derive(Debug)]
pub struct Replica {
    pub pid: libc::pid_t,
    pub pidfd: OwnedFd,
    /// Indexed like `plan.inputs`.
    pub inputs: Vec<ReplicaInput>,
    /// Indexed like `plan.outputs`.
    pub outputs: Vec<FrameReader>,
    /// Started by this voter (so `waitpid` reaps it); a fork child belongs to its donor until
    /// the donor dies and it is re-parented to us (the voter is a subreaper).
    pub our_child: bool,
    /// Has answered at least once, so replica-rt is initialised and the restart handler is in
    /// place: only such a replica may be a donor (before `init`, SIGUSR1 would kill it).
    pub proven: bool,
    /// Whether its restart handler, seen in the kernel's `SigCgt` before it has answered,
    /// means that it may donate (see [`Replica::may_donate`]). Not under the preload library:
    /// a wrapper that `exec`s the program (a pyenv shim, `env`, a shell script) loads the
    /// library and its handler first, and the `exec` drops the handler until the program's own
    /// load. A RESTART in between killed the donor: every bad line of a shimmed Python, whose
    /// three replicas were started afresh together, ended in donors "killed by signal 10" and
    /// the restart budget spent, where the interpreter itself ran on.
    pub handler_before_answer: bool,
    /// Its state is lost: started by exec after a fault, or forked from a replica whose state
    /// was. Such a replica never outvotes, and is never cloned over, one that kept the
    /// component's state (see `decision.rs`). The replicas started with the component kept it.
    /// Once no replica that kept it is left, the fresh ones vote among themselves as equals.
    pub state_lost: bool,
    /// Its state is lost and none of its frames has yet matched one that went out: what it
    /// sends differs because of the lost state, not (as far as anyone can tell) of a fault.
    /// While no fork could give its state back, a dissent of such a replica is not a fault
    /// (see `decision::spare_diverged`). Cleared by its first frame that matches.
    pub catching_up: bool,
    /// A `diverged` event has been written for it (once per replica).
    pub diverged: bool,
    /// Its stderr, relayed line by line with its slot and pid (`stderr.rs`).
    pub stderr: StderrRelay,
    /// When an output pipe of this live replica was seen closed: it is a `crash` if the process
    /// exits within a short grace, else a `protocol` fault.
    pub output_closed_at: Option<crate::clock::Instant>,
    /// When the verdict on that closed output is due: [`crate::core::EXIT_AFTER_EOF`] after
    /// it closed, moved on while the process still runs (on its way out, see
    /// `Core::closed_output_fault`).
    pub output_grace_ends: Option<crate::clock::Instant>,
    /// The start handshake: where a replica started by exec says that its runtime's `init` is
    /// done (see [`Replica::read_started`]); `None` once said, closed, or for a fork child.
    pub start_pipe: Option<OwnedFd>,
    /// The runtime started in this process: it said so, or it is a fork child of one that had.
    pub started: bool,
    /// Its times on and waiting for a CPU, to tell a late replica from one that could not run.
    pub schedstat: SchedStat,
    /// Its `/proc/PID/stat`, for its state letter (the donor pick reads it).
    pub proc_stat: ProcStat,
    /// An unmodified program's replica under a journaled voter: where it stands in lines
    /// given and answers taken (`None` until the voter journals it; see "Lines" in
    /// `journal.rs`).
    pub lines: Option<LineCounts>,
}

pub use crate::journal::LineCounts;

/// What a stream replica must keep of its outputs for a successor of this voter (see
/// `contract::ENV_OUTPUT_HISTORY`): the voter's window of frames undecided, as many decided and
/// still queued for downstream (reading stops while any are: `StreamVoter`), two more of each,
/// and
/// beyond them as many bytes as the pipe (its default size: the voter does not enlarge
/// replicas' outputs), the voter's read buffer (a read on readiness and one more look before a
/// deadline) and one cut frame may hold. `None`: no
/// successor can come (no journal), or the replica answers rounds (reactive mode).
fn output_history(plan: &VoterPlan) -> Option<String> {
    if plan.mode != crate::plan::Mode::Stream
        || plan.journal_fd.is_none()
        || plan.framing == Framing::Lines
    {
        return None;
    }
    let largest = plan.outputs.iter().map(|p| p.max_frame).max().unwrap_or(0);
    let bytes = DEFAULT_PIPE_SIZE
        + 2 * crate::channel::READ_CHUNK
        + largest
        + replica_rt::frame::HEADER_LEN;
    Some(format!("{},{bytes}", 2 * plan.window + 4))
}

/// A pipe's size unless someone changes it (Linux: 16 pages).
const DEFAULT_PIPE_SIZE: usize = 64 * 1024;

/// Fresh pipes for one replica: the replica's ends (in port order: inputs, then outputs, then
/// its stderr) and the voter's ends.
pub struct ReplicaPipes {
    pub replica_ends: Vec<OwnedFd>,
    pub inputs: Vec<ReplicaInput>,
    pub outputs: Vec<FrameReader>,
    pub stderr: StderrRelay,
    /// An unmodified program's pipes: its ports are stdin and stdout.
    preload: bool,
}

impl ReplicaPipes {
    pub fn new(plan: &VoterPlan) -> io::Result<Self> {
        let lines = plan.framing == Framing::Lines;
        let mut replica_ends = Vec::with_capacity(plan.inputs.len() + plan.outputs.len());
        let mut inputs = Vec::with_capacity(plan.inputs.len());
        // Its pipes outlive this voter (parked, `park.rs`): its stdin is written through a
        // staging pipe and its stdout peeked, so that a successor can tell what was given
        // and taken (see "Lines" in `journal.rs`).
        let staged = plan.preload.is_some() && plan.park_fds.is_some();
        for port in &plan.inputs {
            let (r, w) = sys::pipe()?;
            // The voter keeps a read end for taking input back. It must be a separate open file
            // description: O_NONBLOCK belongs to the description, and a dup shared with the
            // replica would make the replica's own reads fail with EAGAIN.
            let voter_r = reopen_nonblocking(&r)?;
            replica_ends.push(r);
            inputs.push(ReplicaInput {
                writer: if staged {
                    FrameWriter::staged(w, Staging::new(port.max_frame)?, lines)?
                } else if lines {
                    FrameWriter::lines(w)?
                } else {
                    FrameWriter::new(w)?
                },
                read_end: voter_r,
            });
        }
        let mut outputs = Vec::with_capacity(plan.outputs.len());
        for port in &plan.outputs {
            let (r, w) = sys::pipe()?;
            replica_ends.push(w);
            outputs.push(if staged {
                // Room for an answer the voter has not taken yet and the next one.
                let whole = port.max_frame + replica_rt::frame::HEADER_LEN;
                crate::channel::pipe_room(r.as_fd(), (2 * whole).max(64 << 10), whole)?;
                FrameReader::peeked_lines(r, port.max_frame, lines)?
            } else if lines {
                FrameReader::lines(r, port.max_frame)?
            } else {
                // A replica that took over fresh pipes from a voter's successor starts each
                // output with `RESUME n`, and answers a replayed round again behind one: the
                // repeats are dropped. Any other control word is still a bad frame.
                FrameReader::resuming(r, port.max_frame)?
            });
        }
        let (r, w) = sys::pipe()?;
        sys::set_nonblocking(r.as_fd(), true)?;
        replica_ends.push(w);
        Ok(ReplicaPipes {
            replica_ends,
            inputs,
            outputs,
            stderr: StderrRelay::new(r),
            preload: plan.preload.is_some(),
        })
    }

    /// Where each replica end must sit in the replica: its ports (see [`port_fd`]), then its
    /// stderr on fd 2.
    pub fn targets(&self) -> impl Iterator<Item = RawFd> + '_ {
        let ports = self.replica_ends.len() - 1;
        (0..ports)
            .map(|k| port_fd(self.preload, k))
            .chain(std::iter::once(libc::STDERR_FILENO))
    }
}

/// The fd number of port `k` (inputs first, then outputs) inside a replica: 3, 4, ... for a
/// component that links replica-rt; stdin and stdout for an unmodified program (bootstrap
/// gives it exactly one input, `in`, and one output, `out`).
fn port_fd(preload: bool, k: usize) -> RawFd {
    if preload {
        [libc::STDIN_FILENO, libc::STDOUT_FILENO][k.min(1)]
    } else {
        FIRST_PORT_FD + k as RawFd
    }
}

/// A new, non-blocking, close-on-exec open file description of the same pipe end (Linux:
/// opening `/proc/self/fd/N` of a pipe opens the pipe again rather than duplicating `N`).
fn reopen_nonblocking(fd: &OwnedFd) -> io::Result<OwnedFd> {
    use std::os::unix::fs::OpenOptionsExt;
    let file = std::fs::OpenOptions::new()
        .read(true)
        .custom_flags(libc::O_NONBLOCK | libc::O_CLOEXEC)
        .open(format!("/proc/self/fd/{}", fd.as_raw_fd()))?;
    Ok(OwnedFd::from(file))
}

/// The port map every replica of this component gets.
pub fn port_map(plan: &VoterPlan) -> PortMap {
    let ins = plan.inputs.iter().map(|p| (p, Direction::In));
    let outs = plan.outputs.iter().map(|p| (p, Direction::Out));
    PortMap {
        ports: ins
            .chain(outs)
            .enumerate()
            .map(|(k, (p, dir))| PortSpec {
                name: p.name.clone(),
                dir,
                fd: port_fd(plan.preload.is_some(), k),
                max_frame: p.max_frame,
            })
            .collect(),
    }
}

/// What a voter knows of a replica it did not start (see [`Replica::proven`] and
/// [`Replica::state_lost`]).
#[derive(Debug, Clone, Copy)]
struct Standing {
    proven: bool,
    state_lost: bool,
}

impl Replica {
    /// A replica a voter's successor took over (see `adopt.rs`): not its child, proven or not
    /// and with its state kept or lost as the predecessor's journal says, on fresh pipes.
    pub(crate) fn adopted(
        pid: libc::pid_t,
        pidfd: OwnedFd,
        pipes: ReplicaPipes,
        entry: crate::journal::SlotEntry,
    ) -> Replica {
        Replica::taken_over(pid, pidfd, pipes.inputs, pipes.outputs, pipes.stderr, entry)
    }

    /// A fork child of a donor that has joined (`recovery.rs`): proven, since it is a copy of a
    /// replica that has answered, so its handler is in place; its state kept (the voter sets
    /// `state_lost` from the donor's). Its `/proc/PID/stat` is opened after the `recovery` event.
    pub(crate) fn forked(pid: libc::pid_t, pidfd: OwnedFd, pipes: ReplicaPipes) -> Replica {
        Replica::not_our_child(
            pid,
            pidfd,
            pipes.inputs,
            pipes.outputs,
            pipes.stderr,
            Standing {
                proven: true,
                state_lost: false,
            },
        )
    }

    /// A replica another voter started, as its successor holds it: not its child, its runtime
    /// started, proven or not and with its state kept or lost as the journal says.
    fn taken_over(
        pid: libc::pid_t,
        pidfd: OwnedFd,
        inputs: Vec<ReplicaInput>,
        outputs: Vec<FrameReader>,
        stderr: StderrRelay,
        entry: crate::journal::SlotEntry,
    ) -> Replica {
        let replica = Replica::not_our_child(
            pid,
            pidfd,
            inputs,
            outputs,
            stderr,
            Standing {
                proven: entry.proven,
                state_lost: entry.state_lost,
            },
        );
        replica.proc_stat.open_now(replica.pidfd.as_fd());
        replica
    }

    /// A replica this voter did not start, whose runtime has: a fork child, or one taken over.
    fn not_our_child(
        pid: libc::pid_t,
        pidfd: OwnedFd,
        inputs: Vec<ReplicaInput>,
        outputs: Vec<FrameReader>,
        stderr: StderrRelay,
        Standing { proven, state_lost }: Standing,
    ) -> Replica {
        Replica {
            pid,
            pidfd,
            inputs,
            outputs,
            stderr,
            our_child: false,
            proven,
            // Set from the plan where it is known (`adopt.rs`); a fork child is proven.
            handler_before_answer: true,
            state_lost,
            // Whether it had matched since is not journaled: a successor takes a replica whose
            // state is lost for one still catching up (it may spare a dissent the predecessor
            // would have blamed, rather than restart a diverged replica into the same loss).
            catching_up: state_lost,
            diverged: false,
            output_closed_at: None,
            output_grace_ends: None,
            start_pipe: None,
            started: true,
            schedstat: SchedStat::new(pid),
            proc_stat: ProcStat::new(pid),
            lines: None,
        }
    }

    /// An unmodified program's replica a voter's successor took over on the pipes its
    /// predecessor parked (`adopt::parked_replicas`): `fds` are the voter's ends of its stdin,
    /// stdout and stderr, then the staging pipe's read and write ends. On failure the pidfd
    /// comes back, to kill the replica with.
    pub(crate) fn adopted_parked(
        plan: &VoterPlan,
        entry: crate::journal::SlotEntry,
        pidfd: OwnedFd,
        fds: Vec<OwnedFd>,
        counts: LineCounts,
    ) -> Result<Replica, (OwnedFd, io::Error)> {
        let built = (|| {
            let Ok([stdin, stdout, stderr, staging_r, staging_w]) = <[OwnedFd; 5]>::try_from(fds)
            else {
                return Err(io::Error::other(
                    "a parked set of other than five pipe ends",
                ));
            };
            let (Some(input), Some(output)) = (plan.inputs.first(), plan.outputs.first()) else {
                return Err(io::Error::other(
                    "an unmodified program has one input and one output",
                ));
            };
            let staging = Staging::adopt(staging_r, staging_w, input.max_frame)?;
            let read_end = reopen_nonblocking(&stdin)?;
            let lines = plan.framing == Framing::Lines;
            let writer = FrameWriter::staged(stdin, staging, lines)?;
            let reader = FrameReader::peeked_lines(stdout, output.max_frame, lines)?;
            sys::set_nonblocking(stderr.as_fd(), true)?;
            Ok((writer, read_end, reader, StderrRelay::new(stderr)))
        })();
        let (writer, read_end, reader, stderr) = match built {
            Ok(parts) => parts,
            Err(e) => return Err((pidfd, e)),
        };
        let inputs = vec![ReplicaInput { writer, read_end }];
        let mut replica =
            Replica::taken_over(entry.pid, pidfd, inputs, vec![reader], stderr, entry);
        replica.lines = Some(counts);
        replica.handler_before_answer = false;
        Ok(replica)
    }

    /// Starts replica `slot` afresh by exec (`stamps`: the answer-stamp page to map into it).
    pub fn spawn(
        plan: &VoterPlan,
        slot: usize,
        stamps: Option<BorrowedFd<'_>>,
    ) -> io::Result<Replica> {
        let pipes = ReplicaPipes::new(plan)?;
        let mut cmd = Command::new(&plan.exec);
        // Not the voter's mask (SIGCHLD blocked for its signalfd): a replica's own.
        sys::start_with_signals_blocked(&mut cmd, sys::REPLICA_SIGNALS);
        cmd.args(&plan.args)
            .env(ENV_PORTS, port_map(plan).to_env())
            .env(ENV_VOTER_SOCKET, &plan.socket_path)
            .env(replica_rt::contract::ENV_SPARE_LINE, "1")
            .env(ENV_REPLICA, slot.to_string())
            .env(ENV_COMPONENT, &plan.component)
            .env(
                replica_rt::contract::ENV_LOCK_MEMORY,
                plan.lock_memory.as_str(),
            )
            .stdin(Stdio::null());
        if let Some(history) = output_history(plan) {
            cmd.env(replica_rt::contract::ENV_OUTPUT_HISTORY, history);
        }
        if let Some(library) = &plan.preload {
            // The library reads the contract above at load time, before the program's `main`.
            cmd.env("LD_PRELOAD", library);
            if plan.framing == Framing::Frames {
                // It follows the program's stdout frame by frame, not line by line.
                cmd.env("S3RES_PRELOAD_FRAMES", "1");
            }
        }
        // The start handshake's pipe goes on the first number after the ports.
        let (start_r, start_w) = sys::pipe()?;
        sys::set_nonblocking(start_r.as_fd(), true)?;
        let start_target = FIRST_PORT_FD
            + if plan.preload.is_some() {
                0
            } else {
                (plan.inputs.len() + plan.outputs.len()) as RawFd
            };
        cmd.env(ENV_STARTED_FD, start_target.to_string());
        let mut map: Vec<(RawFd, RawFd)> = pipes
            .replica_ends
            .iter()
            .zip(pipes.targets())
            .map(|(fd, target)| (fd.as_raw_fd(), target))
            .collect();
        map.push((start_w.as_raw_fd(), start_target));
        if let Some(stamps) = stamps {
            // The answer stamps go on the number after the start handshake's.
            cmd.env(ENV_STAMPS_FD, (start_target + 1).to_string());
            map.push((stamps.as_raw_fd(), start_target + 1));
        }
        sys::map_fds_on_exec(&mut cmd, map);
        let child = cmd.spawn()?;
        // Only the replica holds the write end now: its end of the pipe is its exit.
        drop(start_w);
        let pid = child.id() as libc::pid_t;
        // `child` is dropped without waiting: the voter reaps with waitpid itself.
        drop(child);
        let pidfd = sys::pidfd_open(pid)?;
        let replica = Replica {
            pid,
            pidfd,
            inputs: pipes.inputs,
            outputs: pipes.outputs,
            stderr: pipes.stderr,
            our_child: true,
            proven: false,
            handler_before_answer: plan.preload.is_none(),
            state_lost: false,
            catching_up: false,
            diverged: false,
            output_closed_at: None,
            output_grace_ends: None,
            start_pipe: Some(start_r),
            started: false,
            schedstat: SchedStat::new(pid),
            proc_stat: ProcStat::new(pid),
            lines: None,
        };
        replica.proc_stat.open_now(replica.pidfd.as_fd());
        Ok(replica)
    }

    /// Reads the start handshake's pipe: `true` if the replica said that its runtime started
    /// (the pipe is closed either way once it has said so or closed its end).
    pub fn read_started(&mut self) -> bool {
        let Some(fd) = self.start_pipe.as_ref() else {
            return self.started;
        };
        let mut byte = [0u8; 1];
        match sys::read(fd.as_fd(), &mut byte) {
            Ok(1) if byte[0] == STARTED => {
                self.started = true;
                self.start_pipe = None;
            }
            Ok(_) => self.start_pipe = None,
            Err(e) if e.kind() == io::ErrorKind::WouldBlock => {}
            Err(_) => self.start_pipe = None,
        }
        self.started
    }

    /// An output pipe of this replica was seen closed: `true` if the process is already gone
    /// (a crash); else the time is noted, and `core::Core::closed_output_fault` decides once
    /// the grace is over (the kernel closes a dying process's fds just before it reports the
    /// exit).
    pub fn note_output_closed(&mut self) -> bool {
        if self.exited_within(std::time::Duration::ZERO) {
            return true;
        }
        let now = crate::clock::Instant::now();
        if self.output_closed_at.is_none() {
            self.output_closed_at = Some(now);
            self.output_grace_ends = Some(now + crate::core::EXIT_AFTER_EOF);
        }
        false
    }

    /// An unmodified program's replica under a journaled voter: the answers it gave that this
    /// voter has counted, taken or decoded (`None` otherwise). Its next answer is to line
    /// `answers_decoded + 1`.
    pub fn answers_decoded(&self) -> Option<u64> {
        let (at, out) = (self.lines.as_ref()?, self.outputs.first()?);
        Some(at.taken + out.untaken_lines() as u64)
    }

    /// Writes what is queued for input `i`, as far as the pipe takes it now.
    pub fn flush_input(&mut self, i: usize) -> io::Result<()> {
        self.inputs[i].writer.flush()
    }

    /// SIGKILL, through the pidfd (no pid-reuse race).
    pub fn kill(&self) {
        if let Err(e) = sys::pidfd_send_signal(self.pidfd.as_fd(), libc::SIGKILL) {
            if e.raw_os_error() != Some(libc::ESRCH) {
                tracing::warn!(pid = self.pid, error = %e, "could not kill replica");
            }
        }
    }

    /// Its time on a CPU and waiting for one so far, and how long the read of its clock
    /// took; `None` if `/proc` does not say.
    pub fn sched_times(&self) -> Option<Sample> {
        self.schedstat.read()
    }

    /// Whether the run in [`Replica::sched_times`] is its task clock's (see `starvation.rs`).
    pub fn times_on_clock(&self) -> bool {
        self.schedstat.on_clock()
    }

    /// Where its frames stand in its pipes, for a late replica's `hang` detail: input the
    /// replica has not read (in its pipes, and still queued in the voter for lack of room), and
    /// output the voter has not read off its pipes. A replica asleep on its input with its
    /// input unread, or with its answer unread in its output pipe, tells a late delivery or a
    /// missed read apart from a replica that took its input and did not answer.
    pub fn pipe_backlog(&self) -> PipeBacklog {
        PipeBacklog {
            input_unread: self
                .inputs
                .iter()
                .map(|i| sys::bytes_in_pipe(i.read_end.as_fd()).ok())
                .sum(),
            input_queued: self.inputs.iter().map(|i| i.writer.unwritten_len()).sum(),
            output_unread: self.outputs.iter().map(FrameReader::unread).sum(),
        }
    }

    /// Whether the process has exited (its pidfd is readable), waiting up to `timeout`.
    pub fn exited_within(&self, timeout: std::time::Duration) -> bool {
        sys::wait_readable(self.pidfd.as_fd(), timeout).unwrap_or(true)
    }

    /// How the process ended, waiting up to `within` for it to finish dying; `None` if it has
    /// not, or its status cannot be known. Our own child is reaped here. A fork child belongs
    /// to its donor, which lets the kernel reap it at once (SIGCHLD ignored); its status then
    /// stays beside its pidfd (Linux 6.15+; older kernels do not tell a non-parent).
    pub fn exit_status(&self, within: std::time::Duration) -> Option<sys::ExitStatus> {
        let deadline = crate::clock::Instant::now() + within;
        if !self.exited_within(within) {
            return None;
        }
        loop {
            if self.our_child {
                if let Some(status) = crate::ports::exit_of(self.pid) {
                    return Some(status);
                }
            }
            match sys::pidfd_exit_status(self.pidfd.as_fd()) {
                Ok(Some(status)) => return Some(status),
                Ok(None) => {}
                // This kernel does not say; our child's status comes from waitpid alone.
                Err(_) if !self.our_child => return sys::zombie_exit_status(self.pid),
                Err(_) => {}
            }
            // Not reaped yet (the pidfd records the status only then): a fork child whose
            // donor died belongs to a subreaper that may reap it late, and waiting for that
            // held the crash event, and the recovery, for the whole bound (100 ms).
            if !self.our_child {
                if let Some(status) = sys::zombie_exit_status(self.pid) {
                    return Some(status);
                }
            }
            if crate::clock::Instant::now() >= deadline {
                return None;
            }
            // Between the exit (pidfd readable) and the reaping that records the status.
            std::thread::sleep(std::time::Duration::from_micros(200));
        }
    }
}

impl Replica {
    /// Relays what it wrote to stderr (see `stderr.rs`), each line behind
    /// `[component#slot pid N]`.
    pub fn relay_stderr(&mut self, component: &str, slot: usize) {
        let prefix = format!("[{component}#{slot} pid {}] ", self.pid);
        self.stderr.relay(&prefix);
    }

    /// Whether this replica can be a recovery donor: its restart handler is installed (before
    /// replica-rt's `init` the restart signal would simply kill it). Known once it has sent a
    /// frame; before that (a replica killed right after start, a stream replica that has not
    /// produced yet) the kernel's `SigCgt` says whether it catches the signal.
    pub fn may_donate(&self) -> bool {
        self.proven || (self.handler_before_answer && catches_restart_signal(self.pid))
    }

    /// How good a recovery donor this replica is, and how its `/proc/PID/stat` looked for the
    /// rank (`None` if it is gone); `None`: it cannot donate. See [`DonorRank`].
    pub fn donor_rank(&self) -> Option<(DonorRank, Option<StatLook>)> {
        if !self.may_donate() {
            return None;
        }
        let look = self.proc_stat.look(self.pidfd.as_fd());
        let rank = DonorRank {
            stopped: matches!(look.map(|l| l.state), Some('T' | 't')),
            ..self.donor_rank_unlooked()
        };
        Some((rank, look))
    }

    /// Its [`DonorRank`] as far as it is known without a look at the process (taken as not
    /// stopped), whether or not it may donate.
    fn donor_rank_unlooked(&self) -> DonorRank {
        DonorRank {
            state_lost: self.state_lost,
            unproven: !self.proven,
            stopped: false,
        }
    }

    /// Whether the process sleeps in the kernel (`S`: waiting for input, or for its output
    /// pipe to drain) rather than running, runnable, stopped or dead.
    pub fn is_asleep(&self) -> bool {
        self.proc_stat.state(self.pidfd.as_fd()) == Some('S')
    }

    /// How its `/proc/PID/stat` looks now; `None` if it is gone.
    pub fn look(&self) -> Option<StatLook> {
        self.proc_stat.look(self.pidfd.as_fd())
    }
}

/// A replica's `/proc/PID/stat`, kept open after the first look: a look at its state is then
/// one `pread`. The donor pick reads it for every candidate, on the restart's critical path,
/// where opening the file by its path (a `/proc` lookup each time) took as long as the rest of
/// the pick. The open file stays with the process it was opened for (a read fails once that
/// one is reaped), so a pid reused after the replica died is never read in its place once the
/// file is open; and it is kept only if the replica was alive after the open, as its pidfd
/// says (a number names a process only until it is reaped, and a fork child is reaped by
/// nobody's wait: its donor ignores SIGCHLD). A failed open is not kept: the next look tries
/// again.
#[derive(Debug)]
pub struct ProcStat {
    pid: libc::pid_t,
    file: std::cell::OnceCell<std::fs::File>,
}

impl ProcStat {
    pub fn new(pid: libc::pid_t) -> ProcStat {
        ProcStat {
            pid,
            file: std::cell::OnceCell::new(),
        }
    }

    /// Opens the file now, if that has not happened yet: off the path that reads it.
    /// `pidfd` is the replica's.
    pub fn open_now(&self, pidfd: BorrowedFd<'_>) {
        let _ = self.file(pidfd);
    }

    fn file(&self, pidfd: BorrowedFd<'_>) -> Option<&std::fs::File> {
        if let Some(file) = self.file.get() {
            return Some(file);
        }
        let file = std::fs::File::open(format!("/proc/{}/stat", self.pid)).ok()?;
        // Alive now, so alive at the open: the file is this replica's.
        sys::pidfd_send_signal(pidfd, 0).ok()?;
        Some(self.file.get_or_init(|| file))
    }

    /// The state letter (`S`, `R`, `T`, `Z`, …); `None` if the process is gone (or `/proc`
    /// does not say). `pidfd` is the replica's.
    pub fn state(&self, pidfd: BorrowedFd<'_>) -> Option<char> {
        self.look(pidfd).map(|l| l.state)
    }

    /// Its state and thread count, from one read; `None` if the process is gone (or `/proc`
    /// does not say). `pidfd` is the replica's.
    pub fn look(&self, pidfd: BorrowedFd<'_>) -> Option<StatLook> {
        use std::os::unix::fs::FileExt;
        // The line is ~300 bytes; comm is at most 16.
        let mut buf = [0u8; 1024];
        let n = self.file(pidfd)?.read_at(&mut buf, 0).ok()?;
        let text = std::str::from_utf8(&buf[..n]).ok()?;
        Some(StatLook {
            state: sys::state_in_stat(text)?,
            threads: sys::threads_in_stat(text),
        })
    }
}

/// One look at a replica's `/proc/PID/stat`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StatLook {
    /// The state letter (`S`, `R`, `T`, …).
    pub state: char,
    /// Threads (`None`: the field did not parse).
    pub threads: Option<u64>,
}

impl StatLook {
    /// More than one thread: a fork would copy only the one that makes it.
    pub fn threaded(self) -> bool {
        self.threads.is_some_and(|n| n > 1)
    }
}

/// How good a recovery donor a replica is; the derived order is the preference (fields in
/// order of weight, `false` first).
///
/// * A replica that kept the component's state beats one whose state is lost: cloning a
///   fresh replica over a kept slot would spread the loss.
/// * A replica that has answered (and so was voted with) beats one that has not: a replica
///   just restarted by exec has lost its state, and cloning it over a healthy slot would
///   spread the loss.
/// * A stopped replica (SIGSTOP, a debugger, an injector's ptrace stop) would only make the
///   attempt time out.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub struct DonorRank {
    pub state_lost: bool,
    pub unproven: bool,
    pub stopped: bool,
}

impl DonorRank {
    /// Kept its state, answered, not stopped.
    pub const BEST: DonorRank = DonorRank {
        state_lost: false,
        unproven: false,
        stopped: false,
    };
}

/// What [`best_donor`] found.
#[derive(Debug, Default, PartialEq, Eq)]
pub struct DonorPick {
    pub donor: Option<usize>,
    /// Answered replicas that ran for the whole patience without once waiting for anything:
    /// hung (a control-flow error nobody had caught yet). The caller blames them.
    pub hung: Vec<usize>,
    /// Candidates passed over because they run more than one thread.
    pub threaded: Vec<usize>,
}

/// How often [`best_donor`] looks again while every candidate is running.
const RESAMPLE: Duration = Duration::from_micros(200);

/// The best donor among `slots`: lowest [`DonorRank`], then most `progress` (stream mode: the
/// frames a slot has produced), then lowest slot — **among those at a clean point**.
///
/// A replica that is running may be computing, or may be spinning in a control-flow error
/// that nobody has caught yet; its fork child would spin too (the restart handler returns
/// into the spin), and two spinners outvote the healthy replica (a robot campaign found both).
/// So a candidate is taken only once it is seen asleep in the kernel (`S`), or has blocked
/// (its voluntary context switches grew) since the first look: a healthy burst of work is
/// short. The voter looks every 200 µs for at most `patience` (the component's `timeout_us`,
/// the time any answer may take); a proven candidate that never waits in that time is
/// returned in [`DonorPick::hung`]. A stopped candidate is the last resort, as before; a
/// running one that has not answered yet is taken only at a clean point as well (passed over,
/// not blamed, if it never waits).
/// Replicas that kept their state are looked at first; only when none of them can donate
/// are the fresh ones. Slots in `exclude` are passed over (a donor that already failed).
/// A candidate running more than one thread is passed over: a fork copies only the thread
/// that makes it, so its child would lack the others (a replica-rt component's worker thread:
/// the child hung in every round, was rebuilt from the same donor, and hung again), and an
/// unmodified program's restart handler refuses (the voter would wait a whole connect timeout
/// to learn it). The thread count comes from the same read as the state letter.
pub fn best_donor(
    slots: &[Option<Replica>],
    progress: impl Fn(usize) -> u64,
    patience: Duration,
    exclude: crate::vote::ReplicaSet,
    before_waiting: &dyn Fn(),
) -> DonorPick {
    if let Some(d) = first_choice_asleep(slots, &progress, exclude) {
        return DonorPick {
            donor: Some(d),
            ..DonorPick::default()
        };
    }
    let mut threaded = Vec::new();
    // (rank, progress, slot, pid, state letter when ranked); slots are unique, so the state
    // never decides the order.
    let mut ranked: Vec<Candidate> = slots
        .iter()
        .enumerate()
        .filter(|&(d, _)| !exclude.contains(d))
        .filter_map(|(d, rep)| {
            let rep = rep.as_ref()?;
            let (rank, look) = rep.donor_rank()?;
            if look.is_some_and(StatLook::threaded) {
                threaded.push(d);
                return None;
            }
            let state = look.map(|l| l.state);
            Some((rank, std::cmp::Reverse(progress(d)), d, rep.pid, state))
        })
        .collect();
    ranked.sort();
    let mut hung = Vec::new();
    let mut looked = Vec::new();
    // The state read for the rank serves as a first look only until a group has been waited
    // on (up to `patience`): after that it is stale, and the look is taken afresh.
    let mut fresh = true;
    let first_look = |state: Option<char>, fresh: bool| if fresh { state } else { None };
    for state_lost in [false, true] {
        // (slot, pid, state when ranked) of the proven, running candidates.
        let clean: Vec<(usize, libc::pid_t, Option<char>)> = ranked
            .iter()
            .filter(|c| {
                c.0 == DonorRank {
                    state_lost,
                    unproven: false,
                    stopped: false,
                }
            })
            .map(|&(.., d, pid, state)| (d, pid, first_look(state, fresh)))
            .collect();
        looked.extend(clean.iter().map(|c| c.0));
        if let Some(d) = first_to_wait(&clean, patience, before_waiting) {
            return DonorPick {
                donor: Some(d),
                hung,
                threaded,
            };
        }
        fresh &= clean.is_empty();
        // None of them waited for anything in all that time: hung.
        hung.extend(
            clean
                .iter()
                .filter(|&&(_, pid, _)| {
                    sys::process_state(pid).is_some_and(|s| s != 'Z' && s != 'X')
                })
                .map(|&(d, ..)| d),
        );
        if ranked
            .iter()
            .any(|c| !c.0.state_lost && !hung.contains(&c.2))
        {
            // A kept candidate that is stopped or not yet proven still beats every fresh one.
            break;
        }
    }
    // The next best (stopped, or not yet proven, kept first) is the donor, if any. A stopped
    // one runs nothing and is taken as it is; one that runs but has not answered yet is taken
    // only at a clean point too: it may already spin (a control-flow error injected before its
    // first frame), and its child would spin as well. One that never waits is passed over,
    // not blamed: it may still be starting; the deadlines and the liveness look judge it.
    let rest: Vec<_> = ranked.iter().filter(|c| !looked.contains(&c.2)).collect();
    let mut ranks: Vec<DonorRank> = rest.iter().map(|c| c.0).collect();
    ranks.dedup();
    for rank in ranks {
        let group: Vec<(usize, libc::pid_t, Option<char>)> = rest
            .iter()
            .filter(|c| c.0 == rank)
            .map(|&&(.., d, pid, state)| (d, pid, first_look(state, fresh)))
            .collect();
        let donor = if rank.stopped {
            group.first().map(|c| c.0)
        } else {
            let donor = first_to_wait(&group, patience, before_waiting);
            fresh &= group.is_empty();
            donor
        };
        if donor.is_some() {
            return DonorPick {
                donor,
                hung,
                threaded,
            };
        }
    }
    DonorPick {
        donor: None,
        hung,
        threaded,
    }
}

/// A donor candidate as [`best_donor`] ranks it: rank, progress, slot, pid, and its state
/// letter when ranked.
type Candidate = (
    DonorRank,
    std::cmp::Reverse<u64>,
    usize,
    libc::pid_t,
    Option<char>,
);

/// The usual pick, found with one look: the candidate that ranks first before any look at
/// the processes (most `progress`, then lowest slot), if that rank is [`DonorRank::BEST`] and
/// it is asleep (`S`). That is the donor [`best_donor`]'s ranking picks, since a sleeping
/// replica is not stopped (and an answered one may donate); ranking first read every
/// candidate's `/proc/PID/stat` (a `pread` each, on the restart's critical path, stop 43)
/// where this one read answers. `None`: rank them all (also when it runs more than one
/// thread).
fn first_choice_asleep(
    slots: &[Option<Replica>],
    progress: &impl Fn(usize) -> u64,
    exclude: crate::vote::ReplicaSet,
) -> Option<usize> {
    let (rank, _, d) = slots
        .iter()
        .enumerate()
        .filter(|&(d, _)| !exclude.contains(d))
        .filter_map(|(d, rep)| {
            let rank = rep.as_ref()?.donor_rank_unlooked();
            Some((rank, std::cmp::Reverse(progress(d)), d))
        })
        .min()?;
    let look = slots[d].as_ref()?.look()?;
    (rank == DonorRank::BEST && look.state == 'S' && !look.threaded()).then_some(d)
}

/// The first of `candidates` seen asleep or having blocked since the first look, within
/// `patience` (looking every [`RESAMPLE`]).
///
/// The first look is the state each candidate was ranked with (`candidates` carries it, or
/// `None` once it is stale), then, for one not seen asleep there, one read of
/// `/proc/PID/status` for both its state and its voluntary switches; it stops at the first one
/// asleep. In the common case (the first
/// candidate waits for input) that is no further read of `/proc`: the voluntary switches of
/// every candidate, then the state again, were read before (about a tenth of a restart).
fn first_to_wait(
    candidates: &[(usize, libc::pid_t, Option<char>)],
    patience: Duration,
    before_waiting: &dyn Fn(),
) -> Option<usize> {
    let started = std::time::Instant::now();
    let mut first_blocks = Vec::with_capacity(candidates.len());
    for &(d, pid, ranked_state) in candidates {
        if ranked_state == Some('S') {
            return Some(d);
        }
        let look = status_look(pid);
        if look.state == Some('S') {
            return Some(d);
        }
        first_blocks.push(look.voluntary_switches);
    }
    if !candidates.is_empty() && started.elapsed() < patience {
        before_waiting();
    }
    while !candidates.is_empty() && started.elapsed() < patience {
        std::thread::sleep(RESAMPLE);
        for (&(d, pid, _), first) in candidates.iter().zip(&first_blocks) {
            if is_asleep(pid) || voluntary_switches(pid) != *first {
                return Some(d);
            }
        }
    }
    None
}

/// A process's state and voluntary context switches, from one read of `/proc/PID/status`.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
struct StatusLook {
    /// The state letter (`S`, `R`, `T`, …); `None` if the process is gone.
    state: Option<char>,
    voluntary_switches: Option<u64>,
}

fn status_look(pid: libc::pid_t) -> StatusLook {
    sys::with_proc_status(pid, |status| Some(parse_status(status))).unwrap_or_default()
}

fn parse_status(status: &str) -> StatusLook {
    let mut look = StatusLook::default();
    for line in status.lines() {
        if let Some(v) = line.strip_prefix("State:") {
            look.state = v.trim_start().chars().next();
        } else if let Some(v) = line.strip_prefix("voluntary_ctxt_switches:") {
            look.voluntary_switches = v.trim().parse().ok();
        }
    }
    look
}

/// Whether `pid` sleeps in the kernel (`S`): waiting for input, or for its output pipe.
pub fn is_asleep(pid: libc::pid_t) -> bool {
    sys::process_state(pid) == Some('S')
}

/// Voluntary context switches of `pid`, from `/proc/PID/status`.
pub fn voluntary_switches(pid: libc::pid_t) -> Option<u64> {
    status_look(pid).voluntary_switches
}

/// Time `pid` has spent on a CPU, ns: the first field of `/proc/PID/schedstat`.
pub fn cpu_time_ns(pid: libc::pid_t) -> Option<u64> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/schedstat")).ok()?;
    stat.split_whitespace().next()?.parse().ok()
}

/// Whether `pid` has a handler for the restart signal installed (`SigCgt` in
/// `/proc/PID/status`): replica-rt's `init` has run (it installs this handler last, after the
/// injection handlers), so a RESTART would fork it rather than kill it.
pub fn catches_restart_signal(pid: libc::pid_t) -> bool {
    caught_signals(pid)
        .is_some_and(|mask| mask & signal_bit(replica_rt::contract::signals::RESTART) != 0)
}

pub use replica_rt::sys::{caught_signals, signal_bit};

#[cfg(test)]
mod tests {
    use super::*;

    /// The held `/proc/PID/stat` says the state of the process it was opened for, and nothing
    /// once that process is reaped (its number may belong to another by then).
    #[test]
    fn a_held_stat_file_follows_its_process_and_not_its_number() {
        let mut child = crate::test_support::Sleeper::start();
        let pid = child.pid();
        let pidfd = sys::pidfd_open(pid).unwrap();
        let stat = ProcStat::new(pid);
        let deadline = std::time::Instant::now() + Duration::from_secs(10);
        while stat.state(pidfd.as_fd()) != Some('S') {
            assert!(std::time::Instant::now() < deadline, "sleep never slept");
            std::thread::sleep(Duration::from_millis(5));
        }
        child.0.kill().unwrap();
        child.0.wait().unwrap();
        assert_eq!(stat.state(pidfd.as_fd()), None, "reaped, yet read");
        // Never opened while it lived: not opened now (its pidfd says it is gone).
        let late = ProcStat::new(pid);
        assert_eq!(late.state(pidfd.as_fd()), None);
        assert!(late.file.get().is_none());
    }

    #[test]
    fn status_gives_state_and_voluntary_switches() {
        let text = "Name:\tx\nState:\tS (sleeping)\nTgid:\t7\nvoluntary_ctxt_switches:\t42\n\
                    nonvoluntary_ctxt_switches:\t3\n";
        assert_eq!(
            parse_status(text),
            StatusLook {
                state: Some('S'),
                voluntary_switches: Some(42)
            }
        );
        assert_eq!(parse_status(""), StatusLook::default());
        // This thread runs (the process's main thread may be waiting for it).
        // SAFETY: gettid takes no argument and cannot fail.
        let me = status_look(unsafe { libc::gettid() });
        assert_eq!(me.state, Some('R'), "the test itself runs");
        assert!(me.voluntary_switches.is_some());
        assert_eq!(
            status_look(0),
            StatusLook::default(),
            "no process 0 in /proc"
        );
    }

    /// A replica that catches the restart signal before it has answered may donate, unless
    /// it runs under the preload library: a wrapper that `exec`s the program loads it (and its
    /// handler) first, and the `exec` drops the handler. Here a shell that traps SIGUSR1 stands
    /// for such a wrapper.
    #[test]
    fn a_preloaded_replica_that_has_not_answered_is_no_donor_whatever_it_catches() {
        /// Kills and reaps the replica however the test ends.
        struct Reaped(Replica);
        impl Drop for Reaped {
            fn drop(&mut self) {
                self.0.kill();
                let _ = nix::sys::wait::waitpid(nix::unistd::Pid::from_raw(self.0.pid), None);
            }
        }
        let mut plan = crate::journal::tests::plan();
        plan.exec = "/bin/sh".into();
        plan.args = vec!["-c".into(), "trap : USR1; while :; do sleep 1; done".into()];
        for preload in [
            None,
            Some(std::path::PathBuf::from("/nonexistent/libs3res_preload.so")),
        ] {
            plan.preload = preload.clone();
            let rep = Reaped(Replica::spawn(&plan, 0, None).expect("spawning the shell"));
            let deadline = std::time::Instant::now() + Duration::from_secs(10);
            while !catches_restart_signal(rep.0.pid) {
                assert!(std::time::Instant::now() < deadline, "the trap never came");
                std::thread::sleep(Duration::from_millis(5));
            }
            assert!(!rep.0.proven);
            assert_eq!(rep.0.may_donate(), preload.is_none(), "preload {preload:?}");
        }
    }

    #[test]
    fn restart_handler_is_seen_in_proc() {
        // The test process does not catch SIGUSR1; pid 0 does not exist in /proc.
        assert!(!catches_restart_signal(std::process::id() as libc::pid_t));
        assert!(!catches_restart_signal(0));
    }
}
