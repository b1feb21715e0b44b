//! `s3res-mapper`: builds the occupancy grid. See `--help`.

#![forbid(unsafe_code)]

use anyhow::{Context, Result};
use clap::Parser;
use s3res_robot::component::Downstream;
use s3res_robot::mapper::Mapper;
use s3res_robot::msg::Scan;

/// The robot's mapper (written for stream mode): integrates every cleaned scan on input `scan`
/// into a log-odds occupancy grid, and after every scan whose sequence number is a multiple of
/// --every sends the whole grid on output `map` (with the pose of that scan, for the planner).
///
/// Inputs and outputs are not one-to-one (one update per --every scans), so under a voter it
/// needs stream mode; the schedule depends on the scan numbers only, so every replica sends the
/// same k-th update. Frames that are not scans are skipped (logged).
#[derive(Parser)]
#[command(name = "s3res-mapper", version, verbatim_doc_comment)]
struct Cli {
    /// Send an update every this many scans.
    #[arg(long, default_value_t = 5, value_parser = clap::value_parser!(u32).range(1..))]
    every: u32,
}

fn main() -> Result<()> {
    replica_rt::init_logging("mapper");
    let cli = Cli::parse();
    let mut rt = replica_rt::init().context("starting the s3res runtime")?;
    let mut scans = rt.input("scan").context("opening input scan")?;
    let mut map = Downstream::new(Some(rt.output("map").context("opening output map")?));
    let mut mapper = Mapper::new(cli.every);
    let mut out = Vec::new();
    let mut updates = 0u64;
    while let Some(frame) = scans.recv().context("receiving a scan")? {
        let scan = match Scan::decode(frame) {
            Ok(s) => s,
            Err(e) => {
                tracing::warn!(error = %e, "not a scan; skipped");
                continue;
            }
        };
        if let Some(update) = mapper.on_scan(&scan) {
            update.encode(&mut out);
            map.send(&out)?;
            updates += 1;
        }
    }
    tracing::info!(updates, "end of input");
    Ok(())
}
