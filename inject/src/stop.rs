//! Stopping cleanly on SIGINT/SIGTERM: a campaign interrupted mid-run stops that run (bootstrap
//! is asked to stop, then its group killed, then the sweep), keeps the records of the runs it
//! completed, and exits 128 + the signal.

use std::cell::Cell;

use nix::sys::signal::Signal;
use nix::sys::signalfd::SignalFd;

/// The stop signals, taken through a signalfd instead of a handler.
pub struct StopSignals {
    fd: SignalFd,
    got: Cell<Option<i32>>,
}

impl StopSignals {
    /// Blocks SIGINT and SIGTERM in the calling thread (call it before any thread exists, so
    /// all inherit the mask; children get a clean mask from `Command`) and opens a signalfd.
    pub fn install() -> nix::Result<Self> {
        let fd = replica_rt::sys::signal_fd(&[Signal::SIGINT, Signal::SIGTERM])?;
        Ok(StopSignals {
            fd,
            got: Cell::new(None),
        })
    }

    /// The first stop signal received so far, if any (never blocks).
    pub fn requested(&self) -> Option<i32> {
        if self.got.get().is_none() {
            if let Ok(Some(info)) = self.fd.read_signal() {
                self.got.set(Some(info.ssi_signo as i32));
            }
        }
        self.got.get()
    }
}
