//! `s3res-signal`: smooth numeric telemetry, one frame per input frame (or in bursts). See
//! `--help`.

#![forbid(unsafe_code)]

use anyhow::{Context, Result};
use clap::Parser;
use s3res_components::{check_source_frame, Signal, SIGNAL_FRAME};

/// Answers every source frame on input `in` with a frame of smooth telemetry on output `out`:
/// seq (u64 at byte 0), x, y, speed and odometer (f64 at bytes 8, 16, 24, 32), little-endian.
///
/// It stands in for a robot's control output when trying the anomaly detectors: x and y move
/// smoothly, speed is the distance from the previous point, and the odometer (the sum of the
/// speeds) is state: a replica restarted afresh starts it again at 0. The values are a function
/// of the input's sequence numbers only, so a run is reproducible byte for byte.
///
/// With --every N it answers in bursts, for stream mode ("mode": "stream"): it holds the
/// sequence numbers of N inputs and then sends their N frames at once (nothing for the other
/// inputs); at the end of the input the rest goes out. The frames are the same as without it.
///
///     s3res-source --count 5 --hz 0 | s3res-signal | od -A d -t f8 -j 4 -N 40
#[derive(Parser)]
#[command(name = "s3res-signal", version, verbatim_doc_comment)]
struct Cli {
    /// Added to every sequence number: the same motion further along (held-out data).
    #[arg(long, default_value_t = 0)]
    offset: u64,
    /// Answer in bursts of N frames, one burst every N inputs (a stream component).
    #[arg(long, value_name = "N", default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..))]
    every: u32,
}

fn main() -> Result<()> {
    replica_rt::init_logging("signal");
    let cli = Cli::parse();
    let mut rt = replica_rt::init().context("starting the s3res runtime")?;
    let mut input = rt.input("in").context("opening the input port")?;
    let mut output = rt.output("out").context("opening the output port")?;
    if output.max_frame() < SIGNAL_FRAME {
        anyhow::bail!(
            "output `out` allows frames of {} bytes; a signal frame is {SIGNAL_FRAME}",
            output.max_frame()
        );
    }
    let mut signal = Signal::new(cli.offset);
    // Sequence numbers received and not answered yet (state, like the odometer).
    let mut held: Vec<u64> = Vec::with_capacity(cli.every as usize);
    while let Some(frame) = input.recv().context("receiving")? {
        let seq = check_source_frame(frame)
            .context("input frame is not a source frame (too short or corrupt)")?;
        held.push(seq);
        if held.len() >= cli.every as usize {
            for seq in held.drain(..) {
                output.send(&signal.answer(seq)).context("answering")?;
            }
        }
    }
    for seq in held.drain(..) {
        output.send(&signal.answer(seq)).context("answering")?;
    }
    Ok(())
}
