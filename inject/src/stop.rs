//! Stopping cleanly on SIGINT/SIGTERM: a campaign interrupted mid-run stops that run (bootstrap
//! is asked to stop, then its group killed, then the sweep), keeps the records of the runs it
//! completed, and exits 128 + the signal.

use std::cell::Cell;

use nix::sys::signal::{SigSet, Signal};
use nix::sys::signalfd::{SfdFlags, SignalFd};

/// The stop signals, taken through a signalfd instead of a handler.
pub struct StopSignals {
    fd: SignalFd,
    got: Cell<Option<i32>>,
}

impl StopSignals {
    /// Blocks SIGINT and SIGTERM in the calling thread (call it before any thread exists, so
    /// all inherit the mask; children get a clean mask from `Command`) and opens a signalfd.
    pub fn install() -> nix::Result<Self> {
        let mut mask = SigSet::empty();
        mask.add(Signal::SIGINT);
        mask.add(Signal::SIGTERM);
        mask.thread_block()?;
        let fd = SignalFd::with_flags(&mask, SfdFlags::SFD_CLOEXEC | SfdFlags::SFD_NONBLOCK)?;
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
