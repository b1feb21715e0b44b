//! `s3res-sensor-filter`: cleans the robot's range readings. See `--help`.

#![forbid(unsafe_code)]

use anyhow::{Context, Result};
use clap::Parser;
use s3res_robot::component::{optional_output, Downstream};
use s3res_robot::filter::{MedianFilter, MAX_WINDOW};
use s3res_robot::msg::Scan;

/// The robot's sensor filter (reactive): every scan on input `raw` is answered with the cleaned
/// scan on output `nav` (for the navigator) and, if declared, on `map` (for the mapper). Each
/// range becomes the median of that beam over the last --window scans, which removes single
/// spurious or missed echoes. Pose and goal are passed through.
///
/// One frame in, exactly one frame out on each output: a reactive round of the voter is
/// `{"input": "raw", "outputs": ["nav", "map"]}`. A frame that is not a scan is answered with
/// the last good scan again (logged), so the round is still complete (before the first good
/// scan there is nothing to repeat, and the frame goes unanswered).
#[derive(Parser)]
#[command(name = "s3res-sensor-filter", version, verbatim_doc_comment)]
struct Cli {
    /// Median window, in scans (1 disables the filter).
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u64).range(1..=MAX_WINDOW as u64))]
    window: u64,
}

fn main() -> Result<()> {
    replica_rt::init_logging("sensor-filter");
    let cli = Cli::parse();
    let mut rt = replica_rt::init().context("starting the s3res runtime")?;
    let mut raw = rt.input("raw").context("opening input raw")?;
    let mut nav = Downstream::new(Some(rt.output("nav").context("opening output nav")?));
    let mut map = Downstream::new(optional_output(&mut rt, "map")?);
    let mut filter = MedianFilter::new(cli.window as usize);
    let mut out = Vec::with_capacity(Scan::LEN);
    let mut scans = 0u64;
    while let Some(frame) = raw.recv().context("receiving a scan")? {
        match Scan::decode(frame) {
            Ok(scan) => filter.apply(&scan).encode(&mut out),
            Err(e) => tracing::warn!(error = %e, "not a scan; repeating the last good one"),
        }
        if out.is_empty() {
            continue;
        }
        nav.send(&out)?;
        map.send(&out)?;
        scans += 1;
    }
    tracing::info!(scans, "end of input");
    Ok(())
}
