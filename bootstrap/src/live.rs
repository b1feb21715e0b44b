//! Bootstrap's side of the live view (`--state FILE`): the view of its system before anything
//! is spawned, and the writer shared by its main thread and its events reader. The view itself,
//! its reader and its atomic write are the protocol's ([`s3res_protocol::live`]), so that
//! injectors read it without depending on bootstrap.

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

pub use s3res_protocol::live::{LiveComponent, LiveReplica, LiveView, ReplicaState};

use crate::plan::SystemPlan;

/// Every component of `plan`, nothing spawned yet.
pub fn initial_view(plan: &SystemPlan) -> LiveView {
    let components = plan
        .components
        .iter()
        .map(|c| {
            let replicas = (0..c.replicas)
                .map(|slot| LiveReplica {
                    slot,
                    pid: None,
                    state: ReplicaState::Starting,
                    since_ns: 0,
                })
                .collect();
            (
                c.name.clone(),
                LiveComponent {
                    redundancy: c.redundancy.to_string(),
                    protected: c.is_protected(),
                    pid: None,
                    voter_pid: None,
                    replicas,
                },
            )
        })
        .collect();
    LiveView {
        system: plan.name.clone(),
        bootstrap_pid: std::process::id() as i32,
        updated_ns: replica_rt::sys::monotonic_ns(),
        running: true,
        components,
    }
}

/// The pid of another running s3res-bootstrap whose live view is the state file at `path`,
/// if there is one (its view says it runs, and its pid is a process of that name).
pub fn running_bootstrap_of(path: &Path) -> Option<i32> {
    let view = LiveView::read(path).ok()?;
    (view.running && crate::runtime_dir::is_other_bootstrap(view.bootstrap_pid))
        .then_some(view.bootstrap_pid)
}

/// The view shared by bootstrap's main thread and its events reader, and the file it goes to.
#[derive(Debug, Clone)]
pub struct LiveState {
    inner: Arc<Mutex<Inner>>,
}

#[derive(Debug)]
struct Inner {
    view: LiveView,
    path: PathBuf,
    /// A write failed once; said so, and stopped trying.
    broken: bool,
    /// The file is about to go (it lives in bootstrap's private folder, removed at the end):
    /// the view is still kept, the file no longer written.
    closed: bool,
}

impl LiveState {
    /// Writes the first version of the view to `path`.
    pub fn create(view: LiveView, path: PathBuf) -> std::io::Result<Self> {
        view.write(&path)?;
        tracing::info!(path = %path.display(), "live view (state file)");
        Ok(LiveState {
            inner: Arc::new(Mutex::new(Inner {
                view,
                path,
                broken: false,
                closed: false,
            })),
        })
    }

    /// Changes the view with `f`; rewrites the file if `f` returns `true`.
    pub fn update(&self, f: impl FnOnce(&mut LiveView) -> bool) {
        // A panic elsewhere while holding the lock leaves a usable view; keep going.
        let mut inner = self.inner.lock().unwrap_or_else(|p| p.into_inner());
        if !f(&mut inner.view) || inner.broken || inner.closed {
            return;
        }
        inner.view.updated_ns = replica_rt::sys::monotonic_ns();
        if let Err(e) = inner.view.write(&inner.path) {
            tracing::warn!(
                path = %inner.path.display(),
                "cannot update the state file ({e}); it is no longer kept current"
            );
            inner.broken = true;
        }
    }

    /// Stops writing the file (the view is still kept): for a file in bootstrap's private
    /// folder, which the final sweep removes, so that the last updates neither fail nor warn.
    pub fn close(&self) {
        self.inner.lock().unwrap_or_else(|p| p.into_inner()).closed = true;
    }

    /// A copy of the current view.
    pub fn snapshot(&self) -> LiveView {
        self.inner
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .view
            .clone()
    }
}

#[cfg(test)]
mod tests {
    use s3res_protocol::event::{Event, EventKind};

    use super::*;

    #[test]
    fn updates_reach_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("state.json");
        let mut view = LiveView {
            system: "s".to_owned(),
            bootstrap_pid: 1,
            updated_ns: 0,
            running: true,
            components: Default::default(),
        };
        view.components.insert(
            "echo".to_owned(),
            LiveComponent {
                redundancy: "smr".to_owned(),
                protected: true,
                pid: None,
                voter_pid: Some(10),
                replicas: vec![LiveReplica {
                    slot: 0,
                    pid: None,
                    state: ReplicaState::Starting,
                    since_ns: 0,
                }],
            },
        );
        let live = LiveState::create(view, path.clone()).unwrap();
        let mut start = Event::new("s", "echo", EventKind::Start);
        start.replica = Some(0);
        start.pid = Some(7);
        live.update(|v| v.apply(&start));
        let back = LiveView::read(&path).unwrap();
        assert_eq!(back.components["echo"].replicas[0].pid, Some(7));
        assert_eq!(back, live.snapshot());

        // Closed (its folder about to go): the view changes, the file no longer.
        live.close();
        std::fs::remove_file(&path).unwrap();
        live.update(|v| {
            v.running = false;
            true
        });
        assert!(!live.snapshot().running);
        assert!(!path.exists(), "a closed view was written");
    }
}
