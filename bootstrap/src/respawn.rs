//! Restarting a voter that died (issue 13, item 2): bootstrap keeps what a voter leaves behind
//! — its socket, bound and listening; its journal; a copy of every fd it was handed — and
//! starts a successor on exactly the same fds, told to adopt (`plan.adopt`). The successor
//! takes the live replicas over from the journal (`voter/src/adopt.rs`).
//!
//! Every protected component is restartable ([`restartable`]), in either mode: a reactive
//! successor replays the unfinished round; a stream successor has every replica send again
//! the frames it kept since the last one committed (replica-rt's output history). An
//! unmodified program (`preload`) can neither count its input nor take fresh pipes, so its
//! voter parks its ends of the replicas' pipes in a socket pair bootstrap keeps
//! ([`park_pair`], `voter/src/park.rs`), and the successor takes them over.

use std::collections::VecDeque;
use std::os::fd::{AsRawFd, BorrowedFd, OwnedFd, RawFd};
use std::os::unix::fs::PermissionsExt;
use std::os::unix::net::UnixListener;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use s3res_protocol::plan::{Adoption, VoterPlan};

use crate::plan::ComponentPlan;

/// Whether the voter of `c` is restarted when it dies (see the module docs).
pub fn restartable(c: &ComponentPlan) -> bool {
    c.is_protected()
}

/// Whether the voter of `c` parks its replicas' pipes (an unmodified program's).
pub fn parks_pipes(c: &ComponentPlan) -> bool {
    restartable(c) && c.preload.is_some()
}

/// The socket pair an unmodified program's voter parks its replicas' pipes in: fds sent from
/// the first end wait in the second's queue for as long as bootstrap keeps it, whatever
/// becomes of the voter. `SOCK_SEQPACKET`: each parked set is one message.
pub fn park_pair() -> std::io::Result<(OwnedFd, OwnedFd)> {
    replica_rt::sys::seqpacket_pair()
}

/// The voter's socket, bound by bootstrap so that it outlives every voter: a replica whose
/// voter died connects to it and waits in its backlog while the successor starts. Only our
/// own user may connect (`SO_PEERCRED` then narrows it further).
pub fn bind_socket(path: &Path) -> std::io::Result<OwnedFd> {
    let _ = std::fs::remove_file(path);
    let listener = UnixListener::bind(path)?;
    std::fs::set_permissions(path, std::fs::Permissions::from_mode(0o600))?;
    Ok(OwnedFd::from(listener))
}

/// Everything needed to start a voter again, exactly as the first one was started.
#[derive(Debug)]
pub struct VoterSpawn {
    pub voter: PathBuf,
    pub plan: VoterPlan,
    /// bootstrap's copies of the voter's fds, each with the number it lands on in the voter.
    pub kept: Vec<(OwnedFd, RawFd)>,
    /// Where the voter's stdout and stderr go (a copy of bootstrap's pipe, on a terminal).
    pub stderr: Option<OwnedFd>,
    pub stdout_to_stderr: bool,
    pub log: Option<String>,
    /// The run's [`crate::keeper::ENV_SYSTEM_MARK`].
    pub mark: String,
    /// The restart budget: restarts within the window.
    pub budget: RestartBudget,
    /// Voters of this component started so far.
    pub generation: u32,
}

impl VoterSpawn {
    /// The fd mapping for a successor: bootstrap's copies onto the same numbers.
    pub fn mapping(&self) -> Vec<(RawFd, RawFd)> {
        self.kept
            .iter()
            .map(|(fd, target)| (fd.as_raw_fd(), *target))
            .collect()
    }

    /// The plan of the next voter: the first one's, told whom it succeeds.
    pub fn successor_plan(&mut self, previous_pid: i32, why: &str) -> VoterPlan {
        self.generation += 1;
        let mut plan = self.plan.clone();
        plan.adopt = Some(Adoption {
            previous_pid,
            gone_ns: s3res_protocol::clock::monotonic_ns(),
            why: why.to_owned(),
            generation: self.generation,
        });
        plan
    }
}

/// Copies of `fds` (each with the number it lands on) for bootstrap to keep.
pub fn keep(fds: &[(BorrowedFd<'_>, RawFd)]) -> std::io::Result<Vec<(OwnedFd, RawFd)>> {
    fds.iter()
        .map(|(fd, target)| Ok((fd.try_clone_to_owned()?, *target)))
        .collect()
}

/// OTP's restart intensity for voters: at most `max` restarts within `window`; one more and
/// the component has failed.
#[derive(Debug, Clone)]
pub struct RestartBudget {
    max: u32,
    window: Duration,
    recent: VecDeque<Instant>,
}

impl RestartBudget {
    pub fn new(max: u32, window: Duration) -> Self {
        RestartBudget {
            max,
            window,
            recent: VecDeque::new(),
        }
    }

    /// Takes one restart at `now`: `false` if the budget is spent (the restart must not
    /// happen).
    pub fn take(&mut self, now: Instant) -> bool {
        while self
            .recent
            .front()
            .is_some_and(|&t| now.saturating_duration_since(t) > self.window)
        {
            self.recent.pop_front();
        }
        if self.recent.len() >= self.max as usize {
            return false;
        }
        self.recent.push_back(now);
        true
    }

    pub fn describe(&self) -> String {
        format!(
            "{} restarts within {} ms",
            self.max,
            self.window.as_millis()
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_budget_allows_max_restarts_within_the_window_and_forgets_older_ones() {
        let mut b = RestartBudget::new(3, Duration::from_millis(1000));
        let t0 = Instant::now();
        for k in 0..3 {
            assert!(b.take(t0 + Duration::from_millis(k * 100)), "restart {k}");
        }
        assert!(
            !b.take(t0 + Duration::from_millis(400)),
            "a fourth within 1 s"
        );
        // The first fell out of the window.
        assert!(b.take(t0 + Duration::from_millis(1050)));
        assert!(!b.take(t0 + Duration::from_millis(1060)));
    }
}
