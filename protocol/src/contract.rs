//! The contract between a component process and whoever starts it (bootstrap for an unprotected
//! component, the voter for a replica): environment variables, the port map, the restart
//! handshake on the voter's socket, and the signals.
//!
//! This crate *receives* these, so it defines them (see DESIGN.md, "Dependencies").

use std::os::fd::RawFd;

use serde::{Deserialize, Serialize};

/// JSON [`PortMap`]: which inherited fd is which named port.
pub const ENV_PORTS: &str = "S3RES_PORTS";
/// Path of the voter's Unix socket; present only when the process runs as a replica.
pub const ENV_VOTER_SOCKET: &str = "S3RES_VOTER_SOCKET";
/// Replica index (0-based) given at start; informational (a forked replica keeps its donor's).
pub const ENV_REPLICA: &str = "S3RES_REPLICA";
/// Name of the component in the system description.
pub const ENV_COMPONENT: &str = "S3RES_COMPONENT";
/// Set (to `1`) when the process's stderr is a pipe bootstrap reads and relays behind
/// `[component pid N]` (an unprotected component): the process writes no prefix of its own.
pub const ENV_STDERR_RELAYED: &str = "S3RES_STDERR_RELAYED";
/// The start handshake: the number of an inherited fd, the write end of a pipe the voter
/// reads. A replica's runtime writes [`STARTED`] to it once its `init` is done (handlers in
/// place: the replica can answer, be a donor, be injected), then closes it. A replica whose pipe
/// closes, or whose start deadline passes, without that byte never started the runtime: the
/// program does not speak the s3res protocol.
pub const ENV_STARTED_FD: &str = "S3RES_STARTED_FD";
/// The byte of the start handshake.
pub const STARTED: u8 = b'S';
/// The answer stamps: the number of an inherited fd, a memfd page in which the replica's
/// runtime records when it last answered (see `replica_rt::stamps`). Absent: no stamps, and
/// the voter looks for unwatched answers on its timer instead.
pub const ENV_STAMPS_FD: &str = "S3RES_STAMPS_FD";
/// Output history for a stream replica whose voter may be replaced: `"FRAMES,BYTES"`. The
/// replica keeps, per output, every frame its voter may not have decided yet — the newest
/// `BYTES` worth (what can sit in the pipe and the voter's read buffer) and `FRAMES` frames
/// older than those (what the voter may hold undecided: its window) — and sends them again to
/// a voter's successor after a rebind, behind `RESUME` (see `contract::handshake::Rebind`).
/// Absent: no history (a reactive replica answers a replayed round from its last frame).
pub const ENV_OUTPUT_HISTORY: &str = "S3RES_OUTPUT_HISTORY";
/// How much of its memory the replica locks: `all` or `used` (see [`crate::plan::LockMemory`]).
/// Absent: `all`.
pub const ENV_LOCK_MEMORY: &str = "S3RES_LOCK_MEMORY";

/// bootstrap's pid, given to each voter it starts. The voter asks again for the parent-death
/// signal bootstrap set up for it, which an exec that raises privileges clears (a voter given
/// file capabilities, as docs/real-time.md shows for users without root), and stops at once if
/// that process is no longer its parent. Absent (a voter started by hand): its parent then.
pub const ENV_SUPERVISOR_PID: &str = "S3RES_SUPERVISOR_PID";

/// Present (any value): bootstrap has said, once for the whole system, that a lock limit binds
/// the processes it starts (`RLIMIT_MEMLOCK` without `CAP_IPC_LOCK`). A voter or replica whose
/// memory lock is then refused says so at debug, not each on its own (18 lines of one start
/// said the same thing under a 64 KiB limit). Absent: a refusal is a warning.
pub const ENV_MEMORY_LOCK_SAID: &str = "S3RES_MEMORY_LOCK_SAID";

/// Present (any value): the voter takes spare lines (see [`handshake::Spare`]), so the
/// replica keeps one connected for its next fork child. Absent: it keeps none, and a fork child
/// connects when it needs to (as to a voter, or a test harness, that does not know them).
pub const ENV_SPARE_LINE: &str = "S3RES_SPARE_LINE";

/// Largest number of ports one component may have (inputs plus outputs). The restart handler
/// uses fixed-size arrays of this length, because it may not allocate.
pub const MAX_PORTS: usize = 32;

/// Largest number of fds a fork child is handed at a restart: one per port, and its own stderr
/// pipe (so that the voter can tell its lines from its donor's).
pub const MAX_HANDED_FDS: usize = MAX_PORTS + 1;

/// Direction of a port, seen from the component.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Direction {
    In,
    Out,
}

/// One named port and the fd it lives on.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct PortSpec {
    pub name: String,
    pub dir: Direction,
    pub fd: RawFd,
    /// Largest payload accepted on this port.
    pub max_frame: usize,
}

/// All ports of a component, in the order their fds were assigned.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct PortMap {
    pub ports: Vec<PortSpec>,
}

impl PortMap {
    pub fn to_env(&self) -> String {
        serde_json::to_string(self).expect("a port map always serializes")
    }

    pub fn from_env(s: &str) -> Result<Self, serde_json::Error> {
        serde_json::from_str(s)
    }

    pub fn get(&self, name: &str, dir: Direction) -> Option<&PortSpec> {
        self.ports.iter().find(|p| p.name == name && p.dir == dir)
    }
}

/// First fd number given to ports; 0–2 stay stdin/stdout/stderr.
pub const FIRST_PORT_FD: RawFd = 3;

/// The restart handshake, on the voter's `SOCK_STREAM` Unix socket:
///
/// 0. the voter sends the donor [`signals::RESTART`] with `sigqueue`, whose value is a nonce
///    that names this recovery attempt;
/// 1. the donor's handler forks; the child sends [`Hello`] with that nonce and its pid (a
///    child forked for an earlier, abandoned attempt carries an old nonce and is refused and
///    killed), on the donor's *spare line* where it has one ([`Spare`]: a connection the donor
///    made ahead, which the child inherits), else on a connection of its own;
/// 2. the voter checks who it is — on a connection of its own, `SO_PEERCRED`'s pid; on a
///    spare line, the pid in `Hello` — (its parent must be the donor), then sends one
///    message: [`FdTransfer`] as the payload and the new pipe fds as `SCM_RIGHTS`, in the same
///    order as `targets`, and only then reads `Hello` and checks the nonce (a child with an old
///    one is killed, and the pipes it got are dropped by the voter); so the child may receive
///    its fds before, or while, its `Hello` is read;
/// 3. the replica `dup2`s each fd onto its target number, closes the received copy, and answers
///    with [`Ready`];
/// 4. both close the connection.
///
/// The child's socket has send and receive timeouts, so a child the voter gave up on exits
/// instead of waiting forever.
///
/// [`Hello`]: handshake::Hello
/// [`Spare`]: handshake::Spare
/// [`FdTransfer`]: handshake::FdTransfer
/// [`Ready`]: handshake::Ready
pub mod handshake {
    use super::{MAX_HANDED_FDS, MAX_PORTS};

    /// Voter → replica payload: how many fds follow and which fd number each must end up on.
    /// Fixed-size and plain-old-data so the signal handler can receive it without allocating.
    #[repr(C)]
    #[derive(Debug, Clone, Copy, PartialEq, Eq)]
    pub struct FdTransfer {
        pub magic: u32,
        pub count: u32,
        pub targets: [i32; MAX_HANDED_FDS],
    }

    /// Replica → voter, first: which recovery attempt this child belongs to.
    #[repr(C)]
    #[derive(Debug, Clone, Copy, PartialEq, Eq)]
    pub struct Hello {
        pub magic: u32,
        /// The value the RESTART signal carried (0 if it came without one, e.g. from `kill`).
        pub nonce: u32,
        /// The child's pid: on a spare line, `SO_PEERCRED` names the replica that connected it
        /// (the donor), not the child.
        pub pid: i32,
    }

    /// Replica → voter, first and only, on a *spare line*: a connection a replica makes ahead
    /// (at start, and after each fork) for its next fork child, which inherits it and sends
    /// its [`Hello`] on it instead of making a connection of its own — `socket`, the socket's
    /// timeouts and `connect` cost a fresh fork child about 30 µs on the project's VM, on a
    /// restart's critical path. The voter keeps a spare line of each of its replicas (checked
    /// by `SO_PEERCRED` against the replica's pid and this message), and waits for a child's
    /// `Hello` on its donor's. Every spare line is used once: the donor closes its copy at the
    /// fork, the child after `Ready`, and each makes another later, in normal context (a
    /// signal handler may not, and its work would delay the child). A line that no longer
    /// leads to the voter (a voter replaced since, a spare refused) fails the child's first
    /// send, and the child connects as without one.
    #[repr(C)]
    #[derive(Debug, Clone, Copy, PartialEq, Eq)]
    pub struct Spare {
        pub magic: u32,
        /// The replica that made the line.
        pub pid: i32,
    }

    /// Replica → voter's successor, first, when its voter died (an input ended without an
    /// [`END`](crate::frame::END) frame, or an output's reader went away): "I am replica
    /// `pid`; give me new channels". The rebind handshake:
    ///
    /// 1. the replica connects to the socket (`S3RES_VOTER_SOCKET`, bound by bootstrap, which
    ///    keeps it open across voters, so the connection waits in its backlog while the next
    ///    voter starts) and sends `Rebind`;
    /// 2. the voter checks `SO_PEERCRED`'s pid against `pid` and against the replicas its
    ///    predecessor recorded, then sends [`FdTransfer`] with fresh pipes for every port and
    ///    stderr, as in the restart handshake;
    /// 3. the replica `dup2`s them onto its port numbers, drops whatever part of a frame the
    ///    old pipes left in its input buffers, answers [`Ready`], and goes on: its next frame on
    ///    each output is preceded by `RESUME n` with that frame's number, and the voter replays
    ///    the unfinished round (`RESUME k` and input frame `k`), which the replica answers
    ///    again from its last frames if it had taken it already.
    ///
    /// A voter that closes the connection instead (or no voter at all: the socket's last holder
    /// gone, the connection refused or reset) means the system is ending: the replica takes it
    /// as the end of its input.
    #[repr(C)]
    #[derive(Debug, Clone, Copy, PartialEq, Eq)]
    pub struct Rebind {
        pub magic: u32,
        pub pid: i32,
        /// Whole data frames taken so far on each port, by port position (fd − 3); 0 for
        /// outputs.
        pub frames_taken: [u64; MAX_PORTS],
        /// Whole frames sent so far on each port, by port position; 0 for inputs.
        pub frames_sent: [u64; MAX_PORTS],
    }

    pub const REBIND_MAGIC: u32 = u32::from_le_bytes(*b"S3rb");

    /// How long a replica whose voter died waits for the next one to take it back.
    pub const REBIND_TIMEOUT_MS: u64 = 10_000;

    impl Rebind {
        pub const SIZE: usize = std::mem::size_of::<Rebind>();

        pub fn to_bytes(self) -> [u8; Self::SIZE] {
            let mut out = [0u8; Self::SIZE];
            out[..4].copy_from_slice(&self.magic.to_ne_bytes());
            out[4..8].copy_from_slice(&self.pid.to_ne_bytes());
            let words = self.frames_taken.iter().chain(self.frames_sent.iter());
            for (k, n) in words.enumerate() {
                out[8 + 8 * k..16 + 8 * k].copy_from_slice(&n.to_ne_bytes());
            }
            out
        }

        pub fn from_bytes(b: [u8; Self::SIZE]) -> Self {
            let word = |k: usize| {
                let mut w = [0u8; 8];
                w.copy_from_slice(&b[8 + 8 * k..16 + 8 * k]);
                u64::from_ne_bytes(w)
            };
            Rebind {
                magic: u32::from_ne_bytes([b[0], b[1], b[2], b[3]]),
                pid: i32::from_ne_bytes([b[4], b[5], b[6], b[7]]),
                frames_taken: std::array::from_fn(word),
                frames_sent: std::array::from_fn(|k| word(MAX_PORTS + k)),
            }
        }
    }

    /// Replica → voter: the fds are in place.
    #[repr(C)]
    #[derive(Debug, Clone, Copy, PartialEq, Eq)]
    pub struct Ready {
        pub magic: u32,
        pub pid: i32,
        /// At an output's position (fd − 3): whole frames this process (and the donor before the
        /// fork, since its exec) had sent on it at the moment of the fork. A stream-mode voter
        /// uses it to line the child's output up with the donor's: the child's next frame on a
        /// port is number `frames_sent[port]` of that port.
        ///
        /// At an input's position, in a fork child's `Ready`: the bytes the donor had not read
        /// yet from that input's pipe at the fork. They follow `Ready` on the connection, input
        /// after input in port order, and the voter puts them at the head of the child's new
        /// pipe (replica-rt's `restart`, "Unread input"). 0 in a rebound replica's `Ready`.
        pub frames_sent: [u64; MAX_PORTS],
    }

    pub const TRANSFER_MAGIC: u32 = u32::from_le_bytes(*b"S3fd");
    pub const READY_MAGIC: u32 = u32::from_le_bytes(*b"S3ok");
    pub const HELLO_MAGIC: u32 = u32::from_le_bytes(*b"S3hi");
    pub const SPARE_MAGIC: u32 = u32::from_le_bytes(*b"S3sp");

    /// How long a fork child waits on the voter during the handshake before giving up.
    pub const CHILD_SOCKET_TIMEOUT_MS: u64 = 2000;

    impl Hello {
        pub const SIZE: usize = std::mem::size_of::<Hello>();

        pub fn to_bytes(self) -> [u8; Self::SIZE] {
            let mut out = [0u8; Self::SIZE];
            out[..4].copy_from_slice(&self.magic.to_ne_bytes());
            out[4..8].copy_from_slice(&self.nonce.to_ne_bytes());
            out[8..].copy_from_slice(&self.pid.to_ne_bytes());
            out
        }

        pub fn from_bytes(b: [u8; Self::SIZE]) -> Self {
            Hello {
                magic: u32::from_ne_bytes([b[0], b[1], b[2], b[3]]),
                nonce: u32::from_ne_bytes([b[4], b[5], b[6], b[7]]),
                pid: i32::from_ne_bytes([b[8], b[9], b[10], b[11]]),
            }
        }
    }

    impl Spare {
        pub const SIZE: usize = std::mem::size_of::<Spare>();

        pub fn to_bytes(self) -> [u8; Self::SIZE] {
            let mut out = [0u8; Self::SIZE];
            out[..4].copy_from_slice(&self.magic.to_ne_bytes());
            out[4..].copy_from_slice(&self.pid.to_ne_bytes());
            out
        }

        pub fn from_bytes(b: [u8; Self::SIZE]) -> Self {
            Spare {
                magic: u32::from_ne_bytes([b[0], b[1], b[2], b[3]]),
                pid: i32::from_ne_bytes([b[4], b[5], b[6], b[7]]),
            }
        }
    }

    impl FdTransfer {
        /// The message as the bytes it is sent as (the crate's one `unsafe`: a view of the
        /// struct's own memory, which a byte copy would not give without an allocation in
        /// the signal handler's path).
        #[allow(unsafe_code)]
        pub fn as_bytes(&self) -> &[u8] {
            // SAFETY: repr(C) struct of integers only, no padding (4-byte fields), so every
            // byte is initialised and the slice covers exactly the struct.
            unsafe {
                std::slice::from_raw_parts(
                    (self as *const Self).cast::<u8>(),
                    std::mem::size_of::<Self>(),
                )
            }
        }
    }

    impl Ready {
        pub const SIZE: usize = std::mem::size_of::<Ready>();

        pub fn to_bytes(self) -> [u8; Self::SIZE] {
            let mut out = [0u8; Self::SIZE];
            out[..4].copy_from_slice(&self.magic.to_ne_bytes());
            out[4..8].copy_from_slice(&self.pid.to_ne_bytes());
            for (k, n) in self.frames_sent.iter().enumerate() {
                out[8 + 8 * k..16 + 8 * k].copy_from_slice(&n.to_ne_bytes());
            }
            out
        }

        pub fn from_bytes(b: [u8; Self::SIZE]) -> Self {
            let mut frames_sent = [0u64; MAX_PORTS];
            for (k, n) in frames_sent.iter_mut().enumerate() {
                let mut word = [0u8; 8];
                word.copy_from_slice(&b[8 + 8 * k..16 + 8 * k]);
                *n = u64::from_ne_bytes(word);
            }
            Ready {
                magic: u32::from_ne_bytes([b[0], b[1], b[2], b[3]]),
                pid: i32::from_ne_bytes([b[4], b[5], b[6], b[7]]),
                frames_sent,
            }
        }
    }
}

/// Signals a replica understands. The voter and the injectors send them; replica-rt handles them.
pub mod signals {
    /// Fork yourself; the child reconnects to the voter (see [`super::handshake`]). Sent with
    /// `sigqueue`; the value is the attempt's nonce, which the child echoes in its `Hello`.
    pub const RESTART: libc::c_int = libc::SIGUSR1;
    /// Injection: corrupt the next outgoing frame. Sent with `sigqueue`, the value is the bit to
    /// flip (bit 0 is the lowest bit of the first payload byte); sent with `kill` (or a negative
    /// value), the bit is chosen at random and logged.
    pub const INJECT_SDC: libc::c_int = libc::SIGUSR2;

    /// The real-time signals of this contract are kernel numbers, not `SIGRTMIN() + k`: the
    /// C libraries keep a different number of real-time signals for themselves (glibc 32 and
    /// 33, so its `SIGRTMIN()` is 34; musl 32 to 34, so 35). A voter built on one and a replica
    /// built on the other would otherwise name different signals by the same words: a replica
    /// built for musl handled 37 where the voter sent 36. 36 and 37 are glibc's `SIGRTMIN() + 2`
    /// and `+ 3`, as before, and free for programs under either library.
    const CFE: libc::c_int = 36;
    const VAR: libc::c_int = 37;

    /// Injection: enter an endless loop (a control-flow error that never answers). Signal 36
    /// (glibc's `SIGRTMIN + 2`).
    pub fn inject_cfe() -> libc::c_int {
        CFE
    }

    /// Injection at the variable level: XOR a byte mask into chosen bytes of the next outgoing
    /// frame. Signal 37 (glibc's `SIGRTMIN + 3`). Sent with `sigqueue` only (a real-time
    /// signal, so that several queue instead of merging); the value is a [`VarRequest`] as [`VarRequest::to_value`] encodes it. One signal
    /// names one byte; a flip that spans bytes (the exponent of an f64) is several signals, the
    /// last one with `last` set, and only that one arms the flip. So the bytes of one request
    /// always land in the same frame.
    pub fn inject_var() -> libc::c_int {
        VAR
    }

    /// One byte of a variable-level injection, as carried in the `sigqueue` value (an `i32`
    /// that is never negative):
    ///
    /// | bits   | field                                                  |
    /// |--------|--------------------------------------------------------|
    /// | 0..8   | `mask`: the bits of the byte to flip (bit 0 = lowest)  |
    /// | 8..30  | `offset`: byte offset in the payload (< 4 MiB)         |
    /// | 30     | `last`: this is the request's last byte; arm it        |
    /// | 31     | always 0                                               |
    #[derive(Debug, Clone, Copy, PartialEq, Eq)]
    pub struct VarRequest {
        pub offset: u32,
        pub mask: u8,
        pub last: bool,
    }

    impl VarRequest {
        /// Largest byte offset a request can name.
        pub const MAX_OFFSET: u32 = (1 << 22) - 1;
        const LAST: i32 = 1 << 30;

        /// The `sigqueue` value; `None` if the offset is too large or the mask is empty.
        pub fn to_value(self) -> Option<i32> {
            if self.offset > Self::MAX_OFFSET || self.mask == 0 {
                return None;
            }
            let last = if self.last { Self::LAST } else { 0 };
            Some(last | (self.offset as i32) << 8 | i32::from(self.mask))
        }

        /// Decodes a `sigqueue` value; `None` for a negative value or an empty mask.
        pub fn from_value(value: i32) -> Option<Self> {
            if value < 0 || value & 0xff == 0 {
                return None;
            }
            Some(VarRequest {
                offset: ((value >> 8) as u32) & Self::MAX_OFFSET,
                mask: (value & 0xff) as u8,
                last: value & Self::LAST != 0,
            })
        }

        /// The requests that flip `bits` (bit 0 = lowest bit of byte `offset`; bit 63 of an
        /// f64 at `offset` is its sign) of the payload starting at byte `offset`, one per touched
        /// byte, in byte order, the last one marked `last`. Empty if `bits` is empty.
        pub fn for_bits(offset: u32, bits: &[u32]) -> Vec<VarRequest> {
            let mut masks: std::collections::BTreeMap<u32, u8> = Default::default();
            for &b in bits {
                *masks.entry(offset.saturating_add(b / 8)).or_default() ^= 1 << (b % 8);
            }
            masks.retain(|_, m| *m != 0);
            let n = masks.len();
            masks
                .into_iter()
                .enumerate()
                .map(|(i, (offset, mask))| VarRequest {
                    offset,
                    mask,
                    last: i + 1 == n,
                })
                .collect()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::handshake::{
        Hello, Ready, Rebind, Spare, HELLO_MAGIC, READY_MAGIC, REBIND_MAGIC, SPARE_MAGIC,
    };
    use super::signals::VarRequest;
    use super::MAX_PORTS;

    /// The injection signals are kernel numbers every C library leaves to programs: at or
    /// above this library's `SIGRTMIN()` (34 on glibc, 35 on musl), and distinct.
    #[test]
    fn the_injection_signals_are_real_time_signals_a_program_may_use() {
        use super::signals::{inject_cfe, inject_var};
        for sig in [inject_cfe(), inject_var()] {
            assert!(
                (libc::SIGRTMIN()..=libc::SIGRTMAX()).contains(&sig),
                "signal {sig} outside {}..={}",
                libc::SIGRTMIN(),
                libc::SIGRTMAX()
            );
            // musl keeps 32..=34 for itself: one built there must not collide either.
            assert!(sig >= 35, "signal {sig} is one a C library keeps");
        }
        assert_ne!(inject_cfe(), inject_var());
    }

    #[test]
    fn var_request_round_trips() {
        for r in [
            VarRequest {
                offset: 0,
                mask: 1,
                last: false,
            },
            VarRequest {
                offset: VarRequest::MAX_OFFSET,
                mask: 0xff,
                last: true,
            },
            VarRequest {
                offset: 15,
                mask: 0x80,
                last: true,
            },
        ] {
            let v = r.to_value().unwrap();
            assert!(v >= 0);
            assert_eq!(VarRequest::from_value(v), Some(r));
        }
        assert_eq!(
            VarRequest {
                offset: 1 << 22,
                mask: 1,
                last: false
            }
            .to_value(),
            None
        );
        assert_eq!(
            VarRequest {
                offset: 0,
                mask: 0,
                last: false
            }
            .to_value(),
            None
        );
        assert_eq!(VarRequest::from_value(-1), None);
    }

    #[test]
    fn f64_exponent_spans_two_bytes() {
        // Bits 52..63 of an f64 at offset 8: bits 4..7 of byte 14, bits 0..6 of byte 15.
        let reqs = VarRequest::for_bits(8, &[52, 62]);
        assert_eq!(
            reqs,
            vec![
                VarRequest {
                    offset: 14,
                    mask: 0x10,
                    last: false
                },
                VarRequest {
                    offset: 15,
                    mask: 0x40,
                    last: true
                },
            ]
        );
        assert!(VarRequest::for_bits(0, &[]).is_empty());
    }

    #[test]
    fn ready_roundtrips_with_its_frame_counts() {
        let mut frames_sent = [0u64; MAX_PORTS];
        frames_sent[1] = 7;
        frames_sent[MAX_PORTS - 1] = u64::MAX;
        let ready = Ready {
            magic: READY_MAGIC,
            pid: 4242,
            frames_sent,
        };
        assert_eq!(Ready::from_bytes(ready.to_bytes()), ready);
        assert_eq!(Ready::SIZE, 8 + 8 * MAX_PORTS);
    }

    #[test]
    fn rebind_roundtrips_with_its_frame_counts() {
        let rebind = Rebind {
            magic: REBIND_MAGIC,
            pid: 77,
            frames_taken: std::array::from_fn(|k| k as u64 * 3),
            frames_sent: std::array::from_fn(|k| u64::MAX - k as u64),
        };
        assert_eq!(Rebind::from_bytes(rebind.to_bytes()), rebind);
        assert_eq!(Rebind::SIZE, 8 + 16 * MAX_PORTS);
    }

    #[test]
    fn hello_and_spare_roundtrip_and_share_rebind_s_first_words() {
        let hello = Hello {
            magic: HELLO_MAGIC,
            nonce: 0xdead_beef,
            pid: -5,
        };
        assert_eq!(Hello::from_bytes(hello.to_bytes()), hello);
        assert_eq!(Hello::SIZE, 12);
        let spare = Spare {
            magic: SPARE_MAGIC,
            pid: 31,
        };
        assert_eq!(Spare::from_bytes(spare.to_bytes()), spare);
        // A voter's successor reads the first 8 bytes of a connection to tell a spare line
        // from a rebind: magic, then pid, in both.
        assert_eq!(Spare::SIZE, 8);
        let rebind = Rebind {
            magic: REBIND_MAGIC,
            pid: 31,
            frames_taken: [0; MAX_PORTS],
            frames_sent: [0; MAX_PORTS],
        };
        assert_eq!(rebind.to_bytes()[4..8], spare.to_bytes()[4..8]);
    }
}
