//! Small helpers the component binaries share.

use anyhow::{Context, Result};
use replica_rt::contract::Direction;
use replica_rt::{InPort, OutPort, Runtime, SendError, TryRecv};

/// Whether the component has a port `name` in direction `dir` (the system description may
/// leave optional ports unconnected).
pub fn has_port(rt: &Runtime, name: &str, dir: Direction) -> bool {
    rt.ports()
        .ports
        .iter()
        .any(|p| p.name == name && p.dir == dir)
}

/// The output `name` if the description declares it.
pub fn optional_output(rt: &mut Runtime, name: &str) -> Result<Option<OutPort>> {
    if !has_port(rt, name, Direction::Out) {
        return Ok(None);
    }
    Ok(Some(
        rt.output(name)
            .with_context(|| format!("opening output {name}"))?,
    ))
}

/// The input `name` if the description declares it.
pub fn optional_input(rt: &mut Runtime, name: &str) -> Result<Option<InPort>> {
    if !has_port(rt, name, Direction::In) {
        return Ok(None);
    }
    Ok(Some(
        rt.input(name)
            .with_context(|| format!("opening input {name}"))?,
    ))
}

/// Whether a send failed because the reader is gone (it finished first, at the end of a
/// mission): not an error of this component.
pub fn reader_gone(e: &SendError) -> bool {
    matches!(e, SendError::Io { source, .. } if source.kind() == std::io::ErrorKind::BrokenPipe)
}

/// An output whose reader may finish first: once it has, frames are dropped quietly.
#[derive(Debug)]
pub struct Downstream {
    port: Option<OutPort>,
}

impl Downstream {
    pub fn new(port: Option<OutPort>) -> Downstream {
        Downstream { port }
    }

    pub fn send(&mut self, payload: &[u8]) -> Result<()> {
        let Some(port) = self.port.as_mut() else {
            return Ok(());
        };
        match port.send(payload) {
            Ok(()) => Ok(()),
            Err(e) if reader_gone(&e) => {
                tracing::info!(
                    port = port.name(),
                    "the reader has finished; not sending any more"
                );
                self.port = None;
                Ok(())
            }
            Err(e) => Err(e).context("sending"),
        }
    }

    /// Closes the output (the reader sees end of stream).
    pub fn close(&mut self) {
        self.port = None;
    }
}

/// Takes every frame `port` holds right now, handing each to `f`; `Ok(false)` once the port
/// has reached its end.
pub fn drain(port: &mut InPort, mut f: impl FnMut(&[u8])) -> Result<bool> {
    loop {
        match port.try_recv().context("receiving")? {
            TryRecv::Frame(b) => f(b),
            TryRecv::Empty => return Ok(true),
            TryRecv::Closed => return Ok(false),
        }
    }
}
