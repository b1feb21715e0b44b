//! `s3res-source`: a load generator. See `--help`.

#![forbid(unsafe_code)]

use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use clap::Parser;
use s3res_components::{due_at, source_frame, SEQ_LEN};

/// Sends COUNT numbered frames on its output `out`, HZ per second, then exits.
///
/// Each frame is SIZE bytes: a little-endian u64 sequence number (0, 1, 2, ...) followed by
/// filler bytes computed from it, so that `s3res-sink` can tell missing, duplicated, reordered
/// and corrupted frames apart (the layout is documented in the s3res-components crate).
///
/// Pacing uses absolute deadlines (frame k is due at start + k/HZ), so a late frame does not
/// delay the ones after it and the rate does not drift.
///
/// Closing the output at the end tells the components downstream that the stream is over.
/// Started by hand (not by s3res-bootstrap), `out` is stdout:
///
///     s3res-source --count 5 --hz 0 | s3res-echo | s3res-sink --expect 5
#[derive(Parser)]
#[command(name = "s3res-source", version, verbatim_doc_comment)]
struct Cli {
    /// Number of frames to send.
    #[arg(long)]
    count: u64,
    /// Frames per second; 0 sends as fast as the output takes them. Fractions are allowed.
    #[arg(long)]
    hz: f64,
    /// Frame size in bytes (at least 8: the sequence number).
    #[arg(long, default_value_t = 16)]
    size: usize,
}

fn main() -> Result<()> {
    replica_rt::init_logging("source");
    let cli = Cli::parse();
    if cli.size < SEQ_LEN {
        bail!(
            "--size {} is too small: a frame holds at least its {SEQ_LEN}-byte sequence number",
            cli.size
        );
    }
    if !cli.hz.is_finite() || cli.hz < 0.0 {
        bail!(
            "--hz {} is not a rate: give a number of frames per second, or 0 for no pacing",
            cli.hz
        );
    }
    let mut rt = replica_rt::init().context("starting the s3res runtime")?;
    let mut out = rt.output("out").context("opening the output port")?;
    if cli.size > out.max_frame() {
        bail!(
            "--size {} exceeds the maximum frame size of port \"out\" ({})",
            cli.size,
            out.max_frame()
        );
    }
    let period = match cli.hz {
        0.0 => None,
        hz => Some(
            Duration::try_from_secs_f64(1.0 / hz)
                .with_context(|| format!("--hz {hz} is too slow to pace"))?,
        ),
    };
    tracing::info!(count = cli.count, hz = cli.hz, size = cli.size, "sending");
    let start = Instant::now();
    let mut frame = Vec::with_capacity(cli.size);
    for seq in 0..cli.count {
        if let Some(period) = period {
            // Deadline from the start, not from the last send: no accumulated drift.
            let due = due_at(start, period, seq).with_context(|| {
                format!(
                    "frame {seq} at --hz {} is due beyond the clock's range",
                    cli.hz
                )
            })?;
            let now = Instant::now();
            if due > now {
                std::thread::sleep(due - now);
            }
        }
        source_frame(seq, cli.size, &mut frame);
        out.send(&frame)
            .with_context(|| format!("sending frame {seq}"))?;
    }
    tracing::info!(count = cli.count, elapsed = ?start.elapsed(), "done");
    Ok(())
}
