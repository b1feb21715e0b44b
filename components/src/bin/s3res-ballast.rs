//! `s3res-ballast`: a stateful echo that carries a given amount of private memory. See `--help`.

#![forbid(unsafe_code)]

use anyhow::{bail, Context, Result};
use clap::Parser;
use s3res_components::Echo;

/// A stateful echo with ballast: private memory that a replica restarted by fork must copy.
///
/// At start it allocates --mib/--kib of memory and writes every page (so the state is really
/// resident and private, not shared zero pages), then answers every frame on `in` like
/// `s3res-echo --stateful`: a little-endian u64 counting the frames answered before, then the
/// frame. The counter shows whether a restarted replica kept its state (fork) or lost it
/// (exec). Used by `s3res-bench restart` to time restarts by component size.
///
///     s3res-ballast --mib 64
#[derive(Parser)]
#[command(name = "s3res-ballast", version, verbatim_doc_comment)]
struct Cli {
    /// Ballast in MiB.
    #[arg(long, conflicts_with = "kib")]
    mib: Option<u64>,
    /// Ballast in KiB.
    #[arg(long)]
    kib: Option<u64>,
}

fn main() -> Result<()> {
    replica_rt::init_logging("ballast");
    let cli = Cli::parse();
    let bytes = match (cli.mib, cli.kib) {
        (Some(m), None) => m.checked_mul(1 << 20),
        (None, Some(k)) => k.checked_mul(1 << 10),
        (None, None) => Some(0),
        (Some(_), Some(_)) => unreachable!("clap rejects --mib with --kib"),
    };
    let Some(bytes) = bytes.and_then(|b| usize::try_from(b).ok()) else {
        bail!("the ballast size does not fit in memory addresses");
    };
    // Before init: in replica mode init locks memory (mlockall), which then covers the ballast.
    let ballast = make_ballast(bytes);
    let mut rt = replica_rt::init().context("starting the s3res runtime")?;
    let mut input = rt.input("in").context("opening the input port")?;
    let mut output = rt.output("out").context("opening the output port")?;
    let mut echo = Echo::new(true);
    while let Some(frame) = input.recv().context("receiving")? {
        output.send(echo.answer(frame)).context("answering")?;
    }
    // Keep the ballast alive (and observable) to the end.
    tracing::info!(
        bytes = ballast.len(),
        checksum = checksum(&ballast),
        "end of input"
    );
    Ok(())
}

/// `bytes` of memory with every page written (a non-zero pattern: the pages are private).
fn make_ballast(bytes: usize) -> Vec<u8> {
    let mut v = vec![0u8; bytes];
    for (i, b) in v.iter_mut().enumerate().step_by(512) {
        *b = (i >> 9) as u8 | 1;
    }
    std::hint::black_box(&mut v);
    v
}

fn checksum(v: &[u8]) -> u64 {
    v.iter().step_by(4096).map(|&b| b as u64).sum()
}
