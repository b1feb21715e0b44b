//! The final sweep: nothing bootstrap caused to exist may outlive it.
//!
//! bootstrap is a child subreaper, so every descendant whose parent dies is re-parented to it.
//! Killing every child and reaping, again and again until no child is left, therefore reaches
//! the whole tree, including processes that were forked after the first pass.

use crate::keeper::Keeper;
use crate::runtime_dir::RuntimeDir;
use std::time::Duration;

/// Upper bound of one sweep; a process that survives SIGKILL this long is stuck in the kernel
/// and waiting longer would not help.
pub const SWEEP_LIMIT: Duration = Duration::from_secs(5);

pub use replica_rt::sys::children_of;

pub use replica_rt::sys::{sweep_children as sweep, SweepReport};

/// Sweeps when dropped, so that every way out of [`crate::run`] — including an early `?` —
/// leaves nothing behind; also removes the socket folder.
#[derive(Debug, Default)]
pub struct SweepGuard {
    socket_dir: Option<RuntimeDir>,
    /// Told all clear just before the sweep: from there the sweep does its work.
    keeper: Option<Keeper>,
    done: bool,
}

impl SweepGuard {
    pub fn new() -> Self {
        SweepGuard::default()
    }

    /// The folder to remove after the sweep (its lock is let go once it is gone).
    pub fn own_socket_dir(&mut self, dir: RuntimeDir) {
        self.socket_dir = Some(dir);
    }

    /// The keeper to let go at the sweep.
    pub fn own_keeper(&mut self, keeper: Keeper) {
        self.keeper = Some(keeper);
    }

    /// Sweeps now (once); later calls and the drop do nothing.
    pub fn finish(&mut self) -> SweepReport {
        if self.done {
            return SweepReport::default();
        }
        self.done = true;
        // Whatever the keeper would kill, the sweep kills now; a keeper killed in the sweep
        // would count as a leftover of every run.
        if let Some(keeper) = self.keeper.take() {
            keeper.all_clear();
        }
        let report = sweep(SWEEP_LIMIT);
        if report.killed > 0 {
            tracing::debug!(
                killed = report.killed,
                "final sweep killed leftover processes"
            );
        }
        if !report.resisted.is_empty() {
            tracing::error!(
                pids = ?report.resisted,
                "processes survived SIGKILL for {} s; they are stuck in the kernel",
                SWEEP_LIMIT.as_secs()
            );
        }
        if let Some(dir) = self.socket_dir.take() {
            dir.remove();
        }
        report
    }
}

impl Drop for SweepGuard {
    fn drop(&mut self) {
        self.finish();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use replica_rt::sys;
    use std::process::Command;

    // Only this test in the crate's unit tests starts processes, so sweeping every child of
    // the test process is safe here.
    #[test]
    fn sweep_kills_children_and_grandchildren() {
        let _ = sys::set_child_subreaper();
        let mut child = Command::new("/bin/sh")
            .args(["-c", "sleep 100 & sleep 100 & exec sleep 100"])
            .spawn()
            .unwrap();
        let me = std::process::id() as libc::pid_t;
        assert!(children_of(me).contains(&(child.id() as libc::pid_t)));
        let tmp = tempfile::tempdir().unwrap();
        let runtime = crate::runtime_dir::make(tmp.path()).unwrap();
        let dir = runtime.path().to_owned();
        let mut guard = SweepGuard::new();
        guard.own_socket_dir(runtime);
        let report = guard.finish();
        assert!(report.killed >= 1, "{report:?}");
        assert!(report.resisted.is_empty());
        assert!(children_of(me).is_empty());
        assert!(!dir.exists());
        // Already reaped by the sweep.
        assert!(child.try_wait().is_err() || child.try_wait().unwrap().is_some());
    }
}
