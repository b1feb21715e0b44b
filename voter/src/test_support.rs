//! Helpers for the crate's unit tests.

use std::process::{Child, Command};

/// A `sleep` child process (it never exits on its own within a test), killed and reaped when
/// the test ends, passed or not, so that a failing test leaves no process behind.
pub(crate) struct Sleeper(pub(crate) Child);

impl Sleeper {
    pub(crate) fn start() -> Sleeper {
        Sleeper(
            Command::new("sleep")
                .arg("30")
                .spawn()
                .expect("starting sleep"),
        )
    }

    pub(crate) fn pid(&self) -> libc::pid_t {
        self.0.id() as libc::pid_t
    }
}

impl Drop for Sleeper {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}
