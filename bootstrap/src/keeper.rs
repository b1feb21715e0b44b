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
//! It cannot find a process that cleared its environment (`env -i`) or whose environment it may
//! not read (a set-uid program, when bootstrap is not root): those escape, as documented.

use std::io::{Read as _, Write as _};
use std::process::{ChildStdin, Command, Stdio};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use replica_rt::sys;

/// The variable every process of one run carries: `<bootstrap pid>-<start ns>`.
pub const ENV_SYSTEM_MARK: &str = "S3RES_SYSTEM_MARK";
/// Set on bootstrap's own binary to run it as the keeper of the mark it names.
pub const ENV_KEEPER_OF: &str = "S3RES_KEEPER_OF";
/// What bootstrap writes before it lets the keeper go: its sweep ran, nothing is left to do.
pub const ALL_CLEAR: &[u8] = b"clear\n";
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
    pid: libc::pid_t,
}

impl Keeper {
    /// Starts the keeper of `mark` (bootstrap's own binary). It is bootstrap's child: the final
    /// sweep reaps it like any other. It starts with the terminal's signals and SIGTERM
    /// blocked, since a Ctrl-C or a group-wide SIGTERM is bootstrap's to act on: bootstrap
    /// stops the system in order, and the keeper is let go at the end.
    pub fn start(exe: &std::path::Path, mark: &str) -> std::io::Result<Keeper> {
        let mut cmd = Command::new(exe);
        sys::start_with_signals_blocked(&mut cmd, sys::REPLICA_SIGNALS);
        cmd.env(ENV_KEEPER_OF, mark)
            .env_remove(ENV_SYSTEM_MARK)
            .stdin(Stdio::piped())
            .stdout(Stdio::null());
        let mut child = cmd.spawn()?;
        let to_keeper = child.stdin.take();
        Ok(Keeper {
            to_keeper,
            pid: child.id() as libc::pid_t,
        })
    }

    pub fn pid(&self) -> libc::pid_t {
        self.pid
    }

    /// Tells the keeper that bootstrap's own sweep ran: it ends without looking.
    pub fn all_clear(mut self) {
        if let Some(mut pipe) = self.to_keeper.take() {
            let _ = pipe.write_all(ALL_CLEAR);
        }
    }
}

/// The keeper's life (`s3res-bootstrap` started with [`ENV_KEEPER_OF`]): waits for bootstrap's
/// pipe to close; if bootstrap did not say all clear, kills every process that carries `mark`.
/// Returns the number of processes it killed.
pub fn keep(mark: &str) -> usize {
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
        let found: Vec<libc::pid_t> = processes()
            .into_iter()
            .filter(|&pid| pid != me && carries(pid, &needle))
            .collect();
        if found.is_empty() || Instant::now() >= deadline {
            break;
        }
        for pid in found {
            if sys::kill(pid, libc::SIGKILL).is_ok() {
                killed.insert(pid);
            }
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    killed.len()
}

/// Every pid in `/proc`.
fn processes() -> Vec<libc::pid_t> {
    let Ok(dir) = std::fs::read_dir("/proc") else {
        return Vec::new();
    };
    dir.filter_map(|e| e.ok()?.file_name().to_str()?.parse().ok())
        .collect()
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
        assert!(!carries(
            me,
            format!("PATH={}", &path[..path.len() - 1]).as_bytes()
        ));
        assert!(!carries(me, b"S3RES_SYSTEM_MARK=no-such-run"));
        assert!(processes().contains(&me));
    }
}
