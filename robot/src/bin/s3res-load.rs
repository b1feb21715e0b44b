//! `s3res-load`: steady background CPU load. See `--help`.

#![forbid(unsafe_code)]

use anyhow::{Context, Result};
use clap::Parser;
use s3res_robot::component::Downstream;
use s3res_robot::load::work;
use s3res_robot::msg::Tick;

/// Background load (reactive, lowest priority), as in the S³RES evaluation: for every tick on
/// input `tick` it does --work rounds of CPU-bound integer work and answers with their checksum
/// on output `sum` — one frame in, one frame out, deterministic, so replicas agree.
#[derive(Parser)]
#[command(name = "s3res-load", version, verbatim_doc_comment)]
struct Cli {
    /// Rounds of work per tick (about 1 ns each in a release build, ten times that in debug).
    #[arg(long, default_value_t = 100_000)]
    work: u32,
}

fn main() -> Result<()> {
    replica_rt::init_logging("load");
    let cli = Cli::parse();
    let mut rt = replica_rt::init().context("starting the s3res runtime")?;
    let mut ticks = rt.input("tick").context("opening input tick")?;
    let mut sums = Downstream::new(Some(rt.output("sum").context("opening output sum")?));
    let mut buf = Vec::new();
    let mut n = 0u64;
    while let Some(frame) = ticks.recv().context("receiving a tick")? {
        let tick = match Tick::decode(frame) {
            Ok(t) => t,
            Err(e) => {
                tracing::warn!(error = %e, "not a tick; working on tick 0");
                Tick { seq: 0 }
            }
        };
        work(tick, cli.work).encode(&mut buf);
        sums.send(&buf)?;
        n += 1;
    }
    tracing::info!(ticks = n, "end of input");
    Ok(())
}
