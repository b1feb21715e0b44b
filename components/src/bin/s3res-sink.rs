//! `s3res-sink`: checks the frames of `s3res-source` (through any echoes). See `--help`.

#![forbid(unsafe_code)]

use std::path::PathBuf;

use std::io::Write as _;

use anyhow::{Context, Result};
use clap::Parser;
use s3res_components::Checker;

/// Reads frames from input `in` until it ends and checks them: sequence numbers must be
/// 0, 1, 2, ... (it counts missing, duplicated and reordered frames), every frame's filler must
/// match its sequence number (else it counts as corrupt), and with --stateful the echo's prefix
/// must be the number of frames the echo answered before it (else it is a state break).
///
/// At the end it prints one line, for example
///
///     sink: 2000 frames, 0 missing, 0 duplicated, 0 reordered, 0 corrupt, 0 state breaks: OK
///
/// and exits 0 if everything was right (and, with --expect, exactly N frames came), 1 if not.
/// A broken input stream (a cut or oversized frame) also fails the run.
///
/// Started by hand (not by s3res-bootstrap), `in` is stdin:
///
///     s3res-source --count 5 --hz 0 | s3res-echo --stateful | s3res-sink --stateful --expect 5
#[derive(Parser)]
#[command(name = "s3res-sink", version, verbatim_doc_comment)]
struct Cli {
    /// Number of frames that must arrive; missing ones at the end count as missing.
    #[arg(long, value_name = "N")]
    expect: Option<u64>,
    /// Frames carry the 8-byte counter prefix of `s3res-echo --stateful`.
    #[arg(long)]
    stateful: bool,
    /// Also write the counters as JSON to FILE: {"frames", "missing", "duplicated",
    /// "reordered", "corrupt", "state_breaks", "ok", "expected"}.
    #[arg(long, value_name = "FILE")]
    summary: Option<PathBuf>,
}

fn main() -> Result<()> {
    replica_rt::init_logging("sink");
    let cli = Cli::parse();
    let mut rt = replica_rt::init().context("starting the s3res runtime")?;
    let mut input = rt.input("in").context("opening the input port")?;
    let mut checker = Checker::new(cli.stateful);
    let stream_error = loop {
        match input.recv() {
            Ok(Some(frame)) => checker.frame(frame),
            Ok(None) => break None,
            Err(e) => break Some(e),
        }
    };
    let mut summary = checker.finish(cli.expect);
    if let Some(e) = stream_error {
        let e = anyhow::Error::from(e);
        tracing::error!("input stream broken ({e:#}); counted what arrived before it");
        summary.ok = false;
    }
    if let Some(path) = &cli.summary {
        let json = serde_json::to_string(&summary).context("serialising the summary")?;
        std::fs::write(path, json + "\n").with_context(|| format!("writing {}", path.display()))?;
    }
    // Not `println!`, which panics when stdout cannot be written (a full disk behind it).
    writeln!(std::io::stdout(), "{summary}").context("writing the summary to stdout")?;
    std::process::exit(if summary.ok { 0 } else { 1 });
}
