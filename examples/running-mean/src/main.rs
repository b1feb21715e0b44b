//! `s3res-running-mean`: answers every sample with how many samples came so far and their mean.
//!
//! Input port `samples`: frames of one f64 (8 bytes, little-endian). Output port `mean`: one
//! frame per sample, a u64 count then the f64 running mean (16 bytes, little-endian).
//!
//! Single-threaded on purpose: a replica is restarted by `fork`, and fork copies only the thread
//! that takes the restart signal. Any other thread would be missing in the new replica.

#![forbid(unsafe_code)]

use anyhow::{bail, Context, Result};
use clap::Parser;

/// Answers every sample on port `samples` (one f64) with the count so far and the running mean
/// on port `mean`. Started by s3res-bootstrap: see docs/writing-a-component.md.
#[derive(Parser)]
#[command(name = "s3res-running-mean", version)]
struct Cli {}

fn main() -> Result<()> {
    // `--help` and `--version` answer before any port is opened; there are no other options.
    let Cli {} = Cli::parse();
    // Logs go to stderr (stdout may be a port), each line prefixed with component and pid.
    replica_rt::init_logging("running-mean");
    // Reads the port map and installs the restart and fault-injection signal handlers.
    let mut rt = replica_rt::init().context("starting the s3res runtime")?;
    let mut samples = rt.input("samples").context("opening port `samples`")?;
    let mut mean = rt.output("mean").context("opening port `mean`")?;

    // The component's state: plain variables. A replica forked from a healthy one keeps them.
    let (mut count, mut sum) = (0u64, 0.0f64);
    // recv() returns one whole frame, or None once the input has ended.
    while let Some(frame) = samples.recv().context("receiving a sample")? {
        sum += parse_sample(frame)?;
        count += 1;
        // Exactly one answer per sample: that is what the voter waits for in each round.
        let answer = encode_answer(count, sum / count as f64);
        mean.send(&answer).context("sending the mean")?;
    }
    tracing::info!(count, "end of input");
    Ok(()) // exit 0
}

/// One sample frame is exactly 8 bytes. Anything else is an error (main returns it, the process
/// prints it and exits with status 1), never a panic.
fn parse_sample(frame: &[u8]) -> Result<f64> {
    let Ok(bytes) = <[u8; 8]>::try_from(frame) else {
        let len = frame.len();
        bail!("a sample frame must be 8 bytes (one f64), got {len}");
    };
    Ok(f64::from_le_bytes(bytes))
}

/// The answer frame: count then mean, both little-endian.
fn encode_answer(count: u64, mean: f64) -> [u8; 16] {
    let mut out = [0u8; 16];
    out[..8].copy_from_slice(&count.to_le_bytes());
    out[8..].copy_from_slice(&mean.to_le_bytes());
    out
}

#[cfg(test)]
mod tests; // unit tests, in src/tests.rs
