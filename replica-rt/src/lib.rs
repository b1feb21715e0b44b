//! # replica-rt
//!
//! The library an s3res component binary links. The same binary runs unprotected (started by
//! `s3res-bootstrap`), as one replica of a protected component (started by `s3res-voter`), or by
//! hand in a shell pipeline, without change.
//!
//! ```no_run
//! fn main() -> anyhow::Result<()> {
//!     replica_rt::init_logging("echo");
//!     let mut rt = replica_rt::init()?;
//!     let mut input = rt.input("in")?;
//!     let mut output = rt.output("out")?;
//!     while let Some(frame) = input.recv()? {
//!         output.send(frame)?;
//!     }
//!     Ok(())
//! }
//! ```
//!
//! ## Modes
//!
//! - **standalone** (`S3RES_PORTS` unset): input `in` is stdin, output `out` is stdout, frames up
//!   to [`frame::DEFAULT_MAX_FRAME`], so `printf ... | s3res-echo` works by hand. No other port
//!   exists.
//! - **unprotected** (`S3RES_PORTS` set, no `S3RES_VOTER_SOCKET`): ports as the port map says.
//! - **replica** (`S3RES_VOTER_SOCKET` set as well): additionally the restart handler is
//!   installed, SIGCHLD is ignored (see [`restart`]), and memory is locked with `mlockall`.
//!
//! In every mode the fault-injection hooks are installed ([`inject`]).
//!
//! ## Rules for components
//!
//! - Be single-threaded: restart by fork copies only the thread that took the signal.
//! - Do not rely on SIGCHLD or on waiting for child processes (replica mode ignores SIGCHLD).
//! - Keep all channel I/O on the ports: a port's fd number stays the same across a restart, but
//!   the pipe behind it changes.
//! - Do not print to stdout: in standalone mode it *is* the output port `out` (and dropping the
//!   [`OutPort`] closes it). Log with `tracing` instead ([`init_logging`]); logs go to stderr.
//! - Take the RESTART signal only after `init`: before it, SIGUSR1 still has its default action
//!   (terminate). A voter should restart-by-fork only from replicas that have answered at least
//!   once.

mod answers;
pub mod cow;
pub mod heartbeat;
mod history;
pub mod inject;
mod logging;
pub mod memory;
mod port;
pub(crate) mod rebind;
pub mod restart;
pub mod select;
pub mod shared;
pub mod stamps;
pub mod stderr_relay;
pub mod sys;

/// The contract, the framing and the machine records are the protocol's (`s3res-protocol`),
/// re-exported so that components keep writing `replica_rt::contract`, `replica_rt::frame` and
/// `replica_rt::machine`.
pub use s3res_protocol::{contract, frame, machine};

use std::sync::atomic::{AtomicBool, Ordering};

use thiserror::Error;

use contract::{Direction, PortMap, PortSpec};
pub use logging::{error_chain, init_cli_logging, init_cli_logging_to, init_logging};
pub use port::{InPort, OutPort, RecvError, SendError};
pub use select::{wait_any, Ready, TryRecv};

static INITIALIZED: AtomicBool = AtomicBool::new(false);

/// How the process was started.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Mode {
    /// By hand: stdin is `in`, stdout is `out`.
    Standalone,
    /// By s3res-bootstrap, without a voter.
    Unprotected,
    /// By s3res-voter, as one of several replicas.
    Replica,
}

/// [`init`] failed.
#[derive(Debug, Error)]
pub enum InitError {
    #[error("replica_rt::init was already called in this process")]
    AlreadyInitialized,
    #[error("environment variable {var} is not a valid port map")]
    BadPortMap {
        var: &'static str,
        #[source]
        source: serde_json::Error,
    },
    #[error("invalid port map in {var}: {reason}")]
    InvalidPortMap { var: &'static str, reason: String },
    #[error("{var} is set but {ports} is not: a replica needs its port map")]
    ReplicaWithoutPorts {
        var: &'static str,
        ports: &'static str,
    },
    #[error(transparent)]
    SocketPath(#[from] restart::PathTooLong),
    #[error("installing the signal handler for {what} failed")]
    Signal {
        what: &'static str,
        #[source]
        source: std::io::Error,
    },
}

/// A port could not be opened.
#[derive(Debug, Error)]
pub enum PortError {
    #[error("no {dir} port named {name:?}; this component's {dir} ports are: {known}")]
    Unknown {
        name: String,
        dir: &'static str,
        known: String,
    },
    #[error(
        "no {dir} port named {name:?}: this process was not started by s3res-bootstrap \
         ({var} is unset), so only input \"in\" (stdin) and output \"out\" (stdout) exist"
    )]
    Standalone {
        name: String,
        dir: &'static str,
        var: &'static str,
    },
    #[error("{dir} port {name:?} was already taken")]
    AlreadyTaken { name: String, dir: &'static str },
    #[error("{dir} port {name:?} should be on fd {fd}, which is not open")]
    NotOpen {
        name: String,
        dir: &'static str,
        fd: i32,
        #[source]
        source: std::io::Error,
    },
    #[error("{dir} port {name:?} is on fd {fd}, which is not open for {want}")]
    WrongAccess {
        name: String,
        dir: &'static str,
        fd: i32,
        want: &'static str,
    },
}

/// The component's runtime: hands out its ports.
#[derive(Debug)]
pub struct Runtime {
    mode: Mode,
    ports: PortMap,
    taken: Vec<bool>,
    replica: Option<usize>,
}

/// Sets up the runtime: reads the port map, installs the signal handlers, and in replica mode
/// prepares restart by fork and locks memory. Call it once, early, before starting any thread
/// (there should be none: components are single-threaded).
pub fn init() -> Result<Runtime, InitError> {
    if INITIALIZED.swap(true, Ordering::SeqCst) {
        return Err(InitError::AlreadyInitialized);
    }
    let result = init_inner();
    if result.is_err() {
        // Nothing that cannot be redone was kept: let a corrected retry through.
        INITIALIZED.store(false, Ordering::SeqCst);
    }
    result
}

fn init_inner() -> Result<Runtime, InitError> {
    let ports_env = std::env::var(contract::ENV_PORTS).ok();
    let socket = std::env::var(contract::ENV_VOTER_SOCKET).ok();
    let replica = std::env::var(contract::ENV_REPLICA)
        .ok()
        .and_then(|r| r.parse().ok());
    let (mode, ports) = match (ports_env, &socket) {
        (None, None) => (Mode::Standalone, standalone_ports()),
        (None, Some(_)) => {
            return Err(InitError::ReplicaWithoutPorts {
                var: contract::ENV_VOTER_SOCKET,
                ports: contract::ENV_PORTS,
            })
        }
        (Some(json), _) => {
            let map = parse_port_map(&json)?;
            let mode = if socket.is_some() {
                Mode::Replica
            } else {
                Mode::Unprotected
            };
            (mode, map)
        }
    };
    // Cached now so the restart handler only reads it.
    cow::page_size();
    inject::install().map_err(|source| InitError::Signal {
        what: "fault injection",
        source,
    })?;
    if let Some(path) = &socket {
        restart::prepare(path)?;
        for port in ports.ports.iter().filter(|p| p.dir == Direction::In) {
            if let Ok(position) = usize::try_from(port.fd - contract::FIRST_PORT_FD) {
                restart::register_input(position);
            }
        }
        history::configure_from_env();
        take_stamp_page();
        sys::ignore_signal(libc::SIGCHLD).map_err(|source| InitError::Signal {
            what: "SIGCHLD (ignore)",
            source,
        })?;
        restart::install().map_err(|source| InitError::Signal {
            what: "restart",
            source,
        })?;
        let policy = memory::policy_from_env();
        match memory::lock(policy) {
            Ok(left) => tracing::debug!(
                policy = policy.as_str(),
                stack_on_fault = left.stack_on_fault,
                alt_stack_on_fault = left.alt_stack_on_fault,
                relro_read_only = left.relro_read_only,
                "memory locked"
            ),
            // Bootstrap said the limit once for the system.
            Err(e) if memory::lock_limit_said() => tracing::debug!(
                error = %e,
                "mlockall refused; running with unlocked memory"
            ),
            Err(e) => tracing::warn!(
                error = %e,
                "mlockall refused (raise RLIMIT_MEMLOCK or run with CAP_IPC_LOCK); \
                 running with unlocked memory, so page faults may add latency"
            ),
        }
        // Kept open for the page walk of our fork children (`cow`, "The donor lists the
        // mappings").
        cow::open_own_maps();
        if std::env::var_os(contract::ENV_SPARE_LINE).is_some() {
            restart::use_spare_lines();
            restart::between_rounds();
        }
    }
    say_started();
    tracing::debug!(
        ?mode,
        replica,
        ports = ports.ports.len(),
        "replica-rt initialised"
    );
    let taken = vec![false; ports.ports.len()];
    Ok(Runtime {
        mode,
        ports,
        taken,
        replica,
    })
}

/// The fd the voter handed this process under the environment variable `var` (its number),
/// taken once: the variable is removed, so that nothing the component starts later uses a
/// number that may have been reused by then. `None`: not handed.
fn handed_fd(var: &str) -> Option<(std::os::fd::RawFd, std::io::Result<std::os::fd::OwnedFd>)> {
    let fd = std::env::var(var)
        .ok()
        .and_then(|v| v.parse::<std::os::fd::RawFd>().ok())?;
    // `init` runs before any thread is started (its contract), so nothing reads the environment
    // concurrently.
    std::env::remove_var(var);
    // SAFETY: the number comes from the variable the voter set for this process, which is read
    // once (removed above); nothing else in the process knows it.
    Some((fd, unsafe { sys::try_adopt_inherited_fd(fd) }))
}

/// The start handshake (see [`contract::ENV_STARTED_FD`]): one byte to the voter, then the fd
/// is closed.
fn say_started() {
    match handed_fd(contract::ENV_STARTED_FD) {
        None => {}
        Some((fd, Ok(owned))) => {
            if let Err(e) = sys::write(std::os::fd::AsFd::as_fd(&owned), &[contract::STARTED]) {
                tracing::warn!(fd, error = %e, "could not tell the voter that the runtime started");
            }
        }
        Some((fd, Err(e))) => {
            tracing::warn!(fd, error = %e, "the start handshake's fd is not open")
        }
    }
}

/// The answer stamps (see [`contract::ENV_STAMPS_FD`]): maps the page the voter handed, if it
/// handed one. Without it the runtime works as before; the voter looks for answers on a timer.
fn take_stamp_page() {
    let Some((fd, owned)) = handed_fd(contract::ENV_STAMPS_FD) else {
        return;
    };
    match owned.and_then(stamps::AnswerStamps::adopt) {
        Ok(page) => stamps::install(page),
        Err(e) => tracing::warn!(fd, error = %e, "the answer-stamp page is not usable"),
    }
}

fn standalone_ports() -> PortMap {
    let port = |name: &str, dir, fd| PortSpec {
        name: name.to_owned(),
        dir,
        fd,
        max_frame: frame::DEFAULT_MAX_FRAME,
    };
    PortMap {
        ports: vec![port("in", Direction::In, 0), port("out", Direction::Out, 1)],
    }
}

/// Reads and checks the port map of [`contract::ENV_PORTS`] as a component receives it: at most
/// [`contract::MAX_PORTS`] ports, fds not negative and not shared, a frame size a header can
/// announce, no port listed twice.
pub fn parse_port_map(json: &str) -> Result<PortMap, InitError> {
    let map = PortMap::from_env(json).map_err(|source| InitError::BadPortMap {
        var: contract::ENV_PORTS,
        source,
    })?;
    validate(&map)?;
    Ok(map)
}

fn validate(map: &PortMap) -> Result<(), InitError> {
    let invalid = |reason: String| InitError::InvalidPortMap {
        var: contract::ENV_PORTS,
        reason,
    };
    if map.ports.len() > contract::MAX_PORTS {
        return Err(invalid(format!(
            "{} ports, the limit is {}",
            map.ports.len(),
            contract::MAX_PORTS
        )));
    }
    for (i, p) in map.ports.iter().enumerate() {
        if p.fd < 0 {
            return Err(invalid(format!("port {:?} has fd {}", p.name, p.fd)));
        }
        if p.max_frame > u32::MAX as usize {
            return Err(invalid(format!(
                "port {:?} allows {} bytes, more than a frame header can announce",
                p.name, p.max_frame
            )));
        }
        for q in &map.ports[..i] {
            if q.fd == p.fd {
                return Err(invalid(format!(
                    "ports {:?} and {:?} share fd {}",
                    q.name, p.name, p.fd
                )));
            }
            if q.name == p.name && q.dir == p.dir {
                return Err(invalid(format!("port {:?} is listed twice", p.name)));
            }
        }
    }
    Ok(())
}

fn dir_name(dir: Direction) -> &'static str {
    match dir {
        Direction::In => "input",
        Direction::Out => "output",
    }
}

impl Runtime {
    pub fn mode(&self) -> Mode {
        self.mode
    }

    /// `S3RES_REPLICA` as read at init (`None` when not a replica). A replica forked from a donor
    /// keeps the donor's value: it is a copy of the donor's memory.
    pub fn replica_index(&self) -> Option<usize> {
        self.replica
    }

    /// All ports of this component.
    pub fn ports(&self) -> &PortMap {
        &self.ports
    }

    /// Takes the input port `name` (once).
    pub fn input(&mut self, name: &str) -> Result<InPort, PortError> {
        let (spec, fd) = self.take(name, Direction::In)?;
        Ok(InPort::new(
            spec.name,
            fd,
            spec.max_frame,
            self.mode == Mode::Replica,
        ))
    }

    /// Takes the output port `name` (once).
    pub fn output(&mut self, name: &str) -> Result<OutPort, PortError> {
        let (spec, fd) = self.take(name, Direction::Out)?;
        Ok(OutPort::new(
            spec.name,
            fd,
            spec.max_frame,
            self.mode == Mode::Replica,
        ))
    }

    fn take(
        &mut self,
        name: &str,
        dir: Direction,
    ) -> Result<(PortSpec, std::os::fd::OwnedFd), PortError> {
        let dname = dir_name(dir);
        let Some(i) = self
            .ports
            .ports
            .iter()
            .position(|p| p.name == name && p.dir == dir)
        else {
            return Err(self.unknown(name, dir));
        };
        if self.taken[i] {
            return Err(PortError::AlreadyTaken {
                name: name.to_owned(),
                dir: dname,
            });
        }
        let spec = self.ports.ports[i].clone();
        let fd = sys::take_inherited_fd(spec.fd).map_err(|source| PortError::NotOpen {
            name: name.to_owned(),
            dir: dname,
            fd: spec.fd,
            source,
        })?;
        // A swapped fd would otherwise fail later with a bare EBADF on the first read or write.
        let (ok, want) = match (dir, sys::access_mode(std::os::fd::AsFd::as_fd(&fd))) {
            (Direction::In, Ok(m)) => (m != libc::O_WRONLY, "reading"),
            (Direction::Out, Ok(m)) => (m != libc::O_RDONLY, "writing"),
            (_, Err(_)) => (true, ""),
        };
        if !ok {
            // Not ours to close: leave the fd as it was inherited.
            std::mem::forget(fd);
            return Err(PortError::WrongAccess {
                name: name.to_owned(),
                dir: dname,
                fd: spec.fd,
                want,
            });
        }
        self.taken[i] = true;
        Ok((spec, fd))
    }

    fn unknown(&self, name: &str, dir: Direction) -> PortError {
        let dname = dir_name(dir);
        if self.mode == Mode::Standalone {
            return PortError::Standalone {
                name: name.to_owned(),
                dir: dname,
                var: contract::ENV_PORTS,
            };
        }
        let known: Vec<String> = self
            .ports
            .ports
            .iter()
            .filter(|p| p.dir == dir)
            .map(|p| format!("{:?}", p.name))
            .collect();
        PortError::Unknown {
            name: name.to_owned(),
            dir: dname,
            known: if known.is_empty() {
                "(none)".to_owned()
            } else {
                known.join(", ")
            },
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn map(ports: &[(&str, Direction, i32)]) -> PortMap {
        PortMap {
            ports: ports
                .iter()
                .map(|&(n, d, fd)| PortSpec {
                    name: n.into(),
                    dir: d,
                    fd,
                    max_frame: 1024,
                })
                .collect(),
        }
    }

    #[test]
    fn validate_rejects_shared_fds_and_duplicates() {
        assert!(validate(&map(&[
            ("in", Direction::In, 3),
            ("out", Direction::Out, 4)
        ]))
        .is_ok());
        assert!(validate(&map(&[
            ("in", Direction::In, 3),
            ("out", Direction::Out, 3)
        ]))
        .is_err());
        assert!(validate(&map(&[("a", Direction::In, 3), ("a", Direction::In, 4)])).is_err());
        assert!(validate(&map(&[("a", Direction::In, -1)])).is_err());
        // The same name in both directions is two ports.
        assert!(validate(&map(&[("a", Direction::In, 3), ("a", Direction::Out, 4)])).is_ok());
    }

    #[test]
    fn unknown_port_errors_name_the_known_ones() {
        let rt = Runtime {
            mode: Mode::Unprotected,
            ports: map(&[
                ("cmd", Direction::In, 3),
                ("pose", Direction::In, 4),
                ("out", Direction::Out, 5),
            ]),
            taken: vec![false; 3],
            replica: None,
        };
        let msg = rt.unknown("in", Direction::In).to_string();
        assert!(msg.contains("\"cmd\", \"pose\""), "{msg}");
        let rt = Runtime {
            mode: Mode::Standalone,
            ports: standalone_ports(),
            taken: vec![false; 2],
            replica: None,
        };
        let msg = rt.unknown("pose", Direction::In).to_string();
        assert!(msg.contains("not started by s3res-bootstrap"), "{msg}");
    }

    /// The only test that calls `init` (it is process-wide): standalone, then refused twice.
    /// It takes no port, so the test binary's stdin/stdout stay open.
    #[test]
    fn init_once_only() {
        if std::env::var_os(contract::ENV_PORTS).is_some() {
            eprintln!("skipped: S3RES_PORTS is set in the test environment");
            return;
        }
        let mut rt = init().expect("standalone init");
        assert_eq!(rt.mode(), Mode::Standalone);
        assert!(matches!(init(), Err(InitError::AlreadyInitialized)));
        assert!(matches!(
            rt.input("pose"),
            Err(PortError::Standalone { .. })
        ));
    }
}
