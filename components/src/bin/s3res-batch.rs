//! `s3res-batch`: a stream component; outputs are not one per input. See `--help`.

#![forbid(unsafe_code)]

use anyhow::{Context, Result};
use clap::Parser;
use s3res_components::{Batcher, Echo};

/// Collects the frames of input `in` and lets them out on `out` in batches: nothing for most
/// inputs, then a burst of answers. Each answer is the frame unchanged, with --stateful
/// prefixed like `s3res-echo --stateful` (a little-endian u64: frames answered before it), so
/// `s3res-sink --stateful` checks that every frame came once, in order, with the state intact.
///
/// The frames held back and the counter are state a replica must not lose: run under a voter
/// in stream mode ("mode": "stream"), a replica restarted by fork keeps both; one restarted
/// afresh loses the held frames (the sink counts them missing) and counts from 0 again.
///
/// Batch sizes: with --every N each batch is N frames. With --vary the size of each batch is
/// taken from the first frame of the batch (1 to N, from its bytes), so it changes from batch
/// to batch but is the same in every replica. At the end of the input the rest goes out.
///
/// Started by hand (not by s3res-bootstrap), `in` is stdin and `out` is stdout:
///
///     s3res-source --count 10 --hz 0 | s3res-batch --every 4 --stateful | s3res-sink --stateful --expect 10
#[derive(Parser)]
#[command(name = "s3res-batch", version, verbatim_doc_comment)]
struct Cli {
    /// Frames per batch (with --vary: the largest batch).
    #[arg(long, value_name = "N", default_value_t = 8, value_parser = clap::value_parser!(u32).range(1..))]
    every: u32,
    /// Vary the batch size (1 to N), deterministically from the frames.
    #[arg(long)]
    vary: bool,
    /// Prefix each answer with the number of frames answered before it.
    #[arg(long)]
    stateful: bool,
}

fn main() -> Result<()> {
    replica_rt::init_logging("batch");
    let cli = Cli::parse();
    let mut rt = replica_rt::init().context("starting the s3res runtime")?;
    let mut input = rt.input("in").context("opening the input port")?;
    let mut output = rt.output("out").context("opening the output port")?;
    let mut batcher = Batcher::new(cli.every as usize, cli.vary);
    let mut echo = Echo::new(cli.stateful);
    let mut sent: u64 = 0;
    while let Some(frame) = input.recv().context("receiving")? {
        for held in batcher.push(frame) {
            output.send(echo.answer(&held)).context("answering")?;
            sent += 1;
        }
    }
    for held in batcher.finish() {
        output.send(echo.answer(&held)).context("answering")?;
        sent += 1;
    }
    tracing::info!(sent, "end of input");
    Ok(())
}
