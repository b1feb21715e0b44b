//! `s3res-logger`: records the robot's pose and speed. See `--help`.

#![forbid(unsafe_code)]

use std::io::Write;
use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Parser;
use replica_rt::wait_any;
use s3res_robot::component::{drain, optional_input};
use s3res_robot::msg::{LoadSum, Telemetry};

/// The robot's logger (unprotected): writes every pose and command in force that arrives on
/// input `telemetry` as a CSV line `seq,x,y,theta,v,w` to --out, and counts the load's
/// checksums on input `load` (if connected). Ends when its inputs end.
#[derive(Parser)]
#[command(name = "s3res-logger", version, verbatim_doc_comment)]
struct Cli {
    /// The CSV file to write (nothing is written without it; frames are still counted).
    #[arg(long)]
    out: Option<PathBuf>,
}

fn main() -> Result<()> {
    replica_rt::init_logging("logger");
    let cli = Cli::parse();
    let mut rt = replica_rt::init().context("starting the s3res runtime")?;
    let mut telemetry = Some(rt.input("telemetry").context("opening input telemetry")?);
    let mut load = optional_input(&mut rt, "load")?;
    let mut out = match &cli.out {
        Some(p) => {
            if let Some(dir) = p.parent().filter(|d| !d.as_os_str().is_empty()) {
                std::fs::create_dir_all(dir)
                    .with_context(|| format!("creating the folder {}", dir.display()))?;
            }
            let f =
                std::fs::File::create(p).with_context(|| format!("creating {}", p.display()))?;
            let mut w = std::io::BufWriter::new(f);
            writeln!(w, "seq,x,y,theta,v,w")?;
            Some(w)
        }
        None => None,
    };
    let (mut poses, mut sums, mut bad) = (0u64, 0u64, 0u64);
    let mut last_sum = None;
    while telemetry.is_some() || load.is_some() {
        let ready = match (&telemetry, &load) {
            (Some(t), Some(l)) => wait_any(&[t, l], None),
            (Some(t), None) => wait_any(&[t], None),
            (None, Some(l)) => wait_any(&[l], None),
            (None, None) => break,
        }
        .context("waiting for input")?;
        let (t_idx, l_idx) = if telemetry.is_some() {
            (0, 1)
        } else {
            (usize::MAX, 0)
        };
        if ready.is_ready(t_idx) {
            if let Some(port) = telemetry.as_mut() {
                let mut lines = Vec::new();
                let open = drain(port, |frame| match Telemetry::decode(frame) {
                    Ok(t) => {
                        poses += 1;
                        lines.push(format!(
                            "{},{:.4},{:.4},{:.4},{:.4},{:.4}",
                            t.seq, t.x, t.y, t.theta, t.v, t.w
                        ));
                    }
                    Err(_) => bad += 1,
                })?;
                if let Some(w) = out.as_mut() {
                    for l in lines {
                        writeln!(w, "{l}").context("writing the log")?;
                    }
                }
                if !open {
                    telemetry = None;
                }
            }
        }
        if ready.is_ready(l_idx) {
            if let Some(port) = load.as_mut() {
                let open = drain(port, |frame| match LoadSum::decode(frame) {
                    Ok(s) => {
                        sums += 1;
                        last_sum = Some(s);
                    }
                    Err(_) => bad += 1,
                })?;
                if !open {
                    load = None;
                }
            }
        }
    }
    if let Some(mut w) = out {
        w.flush().context("writing the log")?;
    }
    let last_sum = last_sum.map_or_else(
        || "-".to_owned(),
        |s| format!("{} (period {})", s.sum, s.seq),
    );
    tracing::info!(poses, load_sums = sums, bad_frames = bad, %last_sum, "end of input");
    Ok(())
}
