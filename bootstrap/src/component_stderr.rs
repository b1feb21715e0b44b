//! An unprotected component's stderr: relayed line by line behind `[component pid N]`, and its
//! last words kept for the line that says it failed.
//!
//! A replica's lines carry their writer's name (the voter relays them, `stderr_relay.rs`), and
//! a component built on `replica-rt` used to write its own prefix; but a shell script, a C
//! program or a Python tool writes bare lines, and in a system of several the reader could not
//! tell whose `error: no such file` it was. Its stderr is a pipe of its own now, read by a
//! thread of bootstrap that writes each whole line above the status line, and
//! `ENV_STDERR_RELAYED` tells a `replica-rt` component to write no prefix of its own.

use std::os::fd::{AsFd as _, OwnedFd};
use std::sync::mpsc::{Receiver, RecvTimeoutError, Sender};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use replica_rt::stderr_relay::StderrRelay;
use replica_rt::sys;

/// The relay of one component's stderr, running on a thread of its own.
#[derive(Debug)]
pub struct ComponentStderr {
    last_line: Arc<Mutex<String>>,
    ended: Option<Receiver<()>>,
    /// Gives the thread its prefix once the component runs (its pid is in it); dropped
    /// unsent, the thread ends.
    prefix: Option<Sender<String>>,
}

impl ComponentStderr {
    /// Starts the thread that will relay `pipe` (the read end), before the component is
    /// started: a thread that could not start after it would leave the component a pipe no
    /// one reads (its first line a SIGPIPE). It begins once [`ComponentStderr::relay_as`]
    /// gives it its prefix, and runs until every writer has closed the pipe.
    pub fn start(pipe: OwnedFd) -> std::io::Result<ComponentStderr> {
        let last_line = Arc::new(Mutex::new(String::new()));
        let (tx, rx) = std::sync::mpsc::channel();
        let (prefix_tx, prefix_rx) = std::sync::mpsc::channel::<String>();
        let kept = Arc::clone(&last_line);
        std::thread::Builder::new()
            .name("component-stderr".to_owned())
            .spawn(move || {
                let Ok(prefix) = prefix_rx.recv() else {
                    return;
                };
                // Non-blocking, read when ready: a relay on a blocking pipe would go on reading
                // past a line (to its read limit) before the last line is shared.
                let _ = sys::set_nonblocking(pipe.as_fd(), true);
                let mut relay = StderrRelay::new(pipe);
                while let Some(fd) = relay.fd() {
                    if let Err(e) = sys::wait_readable(fd.as_fd(), Duration::from_secs(3600)) {
                        tracing::debug!(error = %e, "waiting on a component's stderr");
                    }
                    relay.relay_to(&prefix, &mut |line| crate::status::write_stderr(line));
                    let mut last = kept.lock().unwrap_or_else(|p| p.into_inner());
                    last.clone_from(&relay.last_line);
                }
                let _ = tx.send(());
            })?;
        Ok(ComponentStderr {
            last_line,
            ended: Some(rx),
            prefix: Some(prefix_tx),
        })
    }

    /// Begins relaying, each line behind `prefix` (`[component pid N] `).
    pub fn relay_as(&mut self, prefix: String) {
        if let Some(tx) = self.prefix.take() {
            let _ = tx.send(prefix);
        }
    }

    /// Waits until the pipe has ended (every writer gone) and its last lines are out, or until
    /// `deadline`.
    pub fn wait_ended(&mut self, deadline: std::time::Instant) {
        let left = deadline.saturating_duration_since(std::time::Instant::now());
        if let Some(ended) = self.ended.take() {
            if let Err(RecvTimeoutError::Timeout) = ended.recv_timeout(left) {
                self.ended = Some(ended);
            }
        }
    }

    /// The last line the component wrote that says something (not a backtrace, nor blank),
    /// once its pipe has ended or `grace` has passed (a process it started may hold the pipe
    /// open); `None` if it said nothing.
    pub fn last_words(&mut self, grace: Duration) -> Option<String> {
        // Still open after the grace: asked again later, it waits again.
        self.wait_ended(std::time::Instant::now() + grace);
        let last = self.last_line.lock().unwrap_or_else(|p| p.into_inner());
        (!last.is_empty()).then(|| last.clone())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_last_line_that_says_something_is_kept() {
        let (r, w) = sys::pipe().unwrap();
        let mut relayed = ComponentStderr::start(r).unwrap();
        relayed.relay_as("[t pid 1] ".to_owned());
        sys::write(
            w.as_fd(),
            b"loading\nerror: no map file map.bin\n  (looked in .)\n\n",
        )
        .unwrap();
        drop(w);
        assert_eq!(
            relayed.last_words(Duration::from_secs(10)).as_deref(),
            Some("error: no map file map.bin")
        );
    }

    #[test]
    fn a_component_that_said_nothing_has_no_last_words() {
        let (r, w) = sys::pipe().unwrap();
        let mut relayed = ComponentStderr::start(r).unwrap();
        relayed.relay_as("[t pid 1] ".to_owned());
        drop(w);
        assert_eq!(relayed.last_words(Duration::from_secs(10)), None);
    }

    #[test]
    fn a_pipe_held_open_is_waited_for_only_the_grace() {
        let (r, w) = sys::pipe().unwrap();
        let mut relayed = ComponentStderr::start(r).unwrap();
        relayed.relay_as("[t pid 1] ".to_owned());
        sys::write(w.as_fd(), b"still here\n").unwrap();
        let deadline = std::time::Instant::now() + Duration::from_secs(10);
        loop {
            if relayed.last_words(Duration::from_millis(10)).as_deref() == Some("still here") {
                break;
            }
            assert!(std::time::Instant::now() < deadline, "the line never came");
        }
        drop(w);
    }
}
