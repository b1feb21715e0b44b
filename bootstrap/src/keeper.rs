//! The keeper: what a SIGKILLed bootstrap started does not outlive it.
//!
//! bootstrap sweeps its tree on every way out it can run code on (`sweep.rs`), and every child
//! gets `PR_SET_PDEATHSIG`; but a SIGKILLed bootstrap runs nothing, and the parent-death signal
//! reaches only its own children. What an unprotected component started itself — `sh -c
//! "worker &"`, a launcher's helpers — lived on, re-parented to init.
//!
//! So every process bootstrap starts carries one variable, [`ENV_SYSTEM_MARK`], with a value
//! no other run has (bootstrap's pid and start time), and the environment is inherited by
//! whatever they start. The keeper is a small second process, bootstrap's own binary started
//! with [`ENV_KEEPER_OF`]; it holds the read end of a pipe whose write end only bootstrap has.
//! When the read ends without the word [`ALL_CLEAR`] — bootstrap died without its sweep — the
//! keeper kills every process whose environment holds the mark, until a pass finds none.
//!
//! It cannot find a process that cleared or rewrote its environment (`env -i`, a program that
//! writes its title over it) or whose environment it may not read (a set-uid program, when
//! bootstrap is not root): those escape, as documented. Nor does anything keep a system whose
//! keeper could not start (bootstrap says so) or was killed on its own.

use std::io::{Read as _, Write as _};
use std::os::fd::AsFd as _;
use std::process::{ChildStdin, Command, Stdio};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use replica_rt::sys;

/// The variable every process of one run carries: `<bootstrap pid>-<start ns>`.
pub const ENV_SYSTEM_MARK: &str = "S3RES_SYSTEM_MARK";
/// Set on bootstrap's own binary to run it as the keeper of the mark it names.
pub const ENV_KEEPER_OF: &str = "S3RES_KEEPER_OF";
/// What bootstrap writes as it begins its own sweep: the keeper has nothing left to do.
pub const ALL_CLEAR: &[u8] = b"clear\n";
/// The keeper's process name (`/proc/PID/comm`).
pub const KEEPER_NAME: &str = "s3res-keeper";
/// How long the keeper goes on finding marked processes (one that survives SIGKILL this long
/// is stuck in the kernel).
const KEEP_LIMIT: Duration = Duration::from_secs(5);

/// A mark no other run of bootstrap on this machine has.
pub fn new_mark() -> String {
    let ns = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_nanos())
        .unwrap_or(0);
    format!("{}-{ns}", std::process::id())
}

/// bootstrap's end of the keeper: dropping it without [`Keeper::all_clear`] (bootstrap's death
/// does that) sets the keeper to work.
#[derive(Debug)]
pub struct Keeper {
    to_keeper: Option<ChildStdin>,
    child: std::process::Child,
}

impl Keeper {
    /// Starts the keeper of `mark` (bootstrap's own binary). It is bootstrap's child: the final
    /// sweep reaps it like any other. It starts with the terminal's signals and SIGTERM
    /// blocked, since a Ctrl-C or a group-wide SIGTERM is bootstrap's to act on: bootstrap
    /// stops the system in order, and the keeper is let go at the end. It runs in a process
    /// group of its own and names itself `s3res-keeper`: a SIGKILL to bootstrap's group
    /// (`kill -9 %1`, a runner that kills the group) or to every `s3res-bootstrap` is what
    /// it is there for, and must not take it too.
    pub fn start(exe: &std::path::Path, mark: &str) -> std::io::Result<Keeper> {
        let mut cmd = Command::new(exe);
        sys::start_with_signals_blocked(&mut cmd, sys::REPLICA_SIGNALS);
        std::os::unix::process::CommandExt::process_group(&mut cmd, 0);
        cmd.env(ENV_KEEPER_OF, mark)
            .env_remove(ENV_SYSTEM_MARK)
            .stdin(Stdio::piped())
            .stdout(Stdio::null());
        let mut child = cmd.spawn()?;
        let to_keeper = child.stdin.take();
        Ok(Keeper { to_keeper, child })
    }

    pub fn pid(&self) -> libc::pid_t {
        self.child.id() as libc::pid_t
    }

    /// Tells the keeper that bootstrap is about to sweep: it ends without looking, and is
    /// waited for (half a second at most), so that the sweep counts only true leftovers.
    pub fn all_clear(mut self) {
        if let Some(mut pipe) = self.to_keeper.take() {
            let _ = pipe.write_all(ALL_CLEAR);
        }
        let deadline = Instant::now() + Duration::from_millis(500);
        while Instant::now() < deadline {
            match self.child.try_wait() {
                Ok(None) => std::thread::sleep(Duration::from_millis(1)),
                // Ended, or reaped already: either way gone.
                Ok(Some(_)) | Err(_) => return,
            }
        }
    }
}

/// The keeper's life (`s3res-bootstrap` started with [`ENV_KEEPER_OF`]): waits for bootstrap's
/// pipe to close; if bootstrap did not say all clear, kills every process that carries `mark`.
/// Returns the number of processes it killed.
pub fn keep(mark: &str) -> usize {
    if let Err(e) = sys::set_process_name(KEEPER_NAME) {
        tracing::debug!(error = %e, "cannot name the keeper");
    }
    let mut said = Vec::new();
    // Blocks until bootstrap writes and closes, or dies (the kernel closes its end).
    let _ = std::io::stdin().lock().read_to_end(&mut said);
    if said.as_slice() == ALL_CLEAR {
        return 0;
    }
    let killed = kill_marked(mark, KEEP_LIMIT);
    if killed > 0 {
        eprintln!(
            "s3res-bootstrap's keeper: bootstrap died without stopping its system; killed {killed} \
             process(es) the system had started"
        );
    }
    killed
}

/// Kills every process whose environment holds `S3RES_SYSTEM_MARK=mark`, pass after pass, until
/// a pass finds none or `limit` has passed (a process may fork between passes).
pub fn kill_marked(mark: &str, limit: Duration) -> usize {
    let needle = format!("{ENV_SYSTEM_MARK}={mark}").into_bytes();
    let me = std::process::id() as libc::pid_t;
    let deadline = Instant::now() + limit;
    let mut killed = std::collections::BTreeSet::new();
    loop {
        let found: Vec<libc::pid_t> = sys::all_pids()
            .into_iter()
            .filter(|&pid| pid != me && carries(pid, &needle))
            .collect();
        if found.is_empty() || Instant::now() >= deadline {
            break;
        }
        for pid in found {
            // Through a pidfd, the environment read again once it is open: a pid that ended
            // and was reused since the scan is another process.
            let Ok(pidfd) = sys::pidfd_open(pid) else {
                continue;
            };
            if carries(pid, &needle) && sys::pidfd_send_signal(pidfd.as_fd(), libc::SIGKILL).is_ok()
            {
                killed.insert(pid);
            }
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    killed.len()
}

/// Whether `pid`'s environment holds the variable `needle` (`NAME=value`) exactly. A zombie's
/// or a kernel thread's environment reads empty; one we may not read is passed over.
fn carries(pid: libc::pid_t, needle: &[u8]) -> bool {
    let Ok(environ) = std::fs::read(format!("/proc/{pid}/environ")) else {
        return false;
    };
    environ.split(|&b| b == 0).any(|var| var == needle)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_mark_names_this_run_only() {
        let a = new_mark();
        std::thread::sleep(Duration::from_millis(1));
        let b = new_mark();
        assert_ne!(a, b);
        assert!(a.starts_with(&format!("{}-", std::process::id())));
    }

    #[test]
    fn a_variable_is_found_whole_and_only_whole() {
        let me = std::process::id() as libc::pid_t;
        let path = std::env::var("PATH").expect("tests run with PATH");
        assert!(carries(me, format!("PATH={path}").as_bytes()));
        // A prefix of the value is another mark.
        let mut shorter = path.clone();
        if shorter.pop().is_some() {
            assert!(!carries(me, format!("PATH={shorter}").as_bytes()));
        }
        assert!(!carries(me, b"S3RES_SYSTEM_MARK=no-such-run"));
        assert!(sys::all_pids().contains(&me));
    }
}
