//! `s3res-bench echo`: round trips through `s3res-echo`, directly (no voter) and under the
//! voter at each replication level, for each frame size: the S³RES paper's Figure 3.

use std::time::Duration;

use anyhow::{Context, Result};
use indicatif::ProgressBar;
use replica_rt::frame::FrameBuf;

use crate::report::{self, histogram, Row, Summary};
use crate::system::{Setup, Spec, System};
use crate::Common;

/// Longest a single round trip may take before the run is abandoned as broken.
const ROUND_LIMIT: Duration = Duration::from_secs(5);

/// The echo that is measured (`--program`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Program {
    /// `s3res-echo`, which links replica-rt.
    Linked,
    /// `cat`, unmodified, with the preload library: s3res frames on its stdin and stdout.
    PreloadFrames,
    /// `cat`, unmodified, with the preload library: one line per frame (`framing: lines`).
    PreloadLines,
}

impl Program {
    /// Its name on the command line and in the results (`preload-lines`).
    pub fn name(self) -> &'static str {
        match self {
            Program::Linked => "linked",
            Program::PreloadFrames => "preload-frames",
            Program::PreloadLines => "preload-lines",
        }
    }
}

pub struct EchoOptions {
    pub program: Program,
    pub replicas: Vec<usize>,
    pub sizes: Vec<usize>,
    pub count: u64,
    pub warmup: u64,
    pub timeout_us: u64,
    pub setups: Vec<Setup>,
}

/// Payload of round `seq`: the seq, then bytes that depend on it, so a stale or mixed-up answer
/// is seen.
pub fn fill_frame(seq: u64, buf: &mut [u8]) {
    let s = seq.to_le_bytes();
    for (i, b) in buf.iter_mut().enumerate() {
        *b = if i < 8 {
            s[i]
        } else {
            (i as u8).wrapping_mul(31) ^ s[i % 8]
        };
    }
}

/// Payload of round `seq` for a line-framed program: printable, no newline (the seq in hex,
/// then letters that depend on it).
pub fn fill_line(seq: u64, buf: &mut [u8]) {
    let hex = format!("{seq:016x}");
    for (i, b) in buf.iter_mut().enumerate() {
        *b = match hex.as_bytes().get(i) {
            Some(&h) => h,
            None => b'a' + ((i as u64 ^ seq) % 26) as u8,
        };
    }
}

pub fn run(common: &Common, o: &EchoOptions) -> Result<Vec<Row>> {
    let (echo, preload) = match o.program {
        Program::Linked => (common.bins.component("s3res-echo")?, None),
        Program::PreloadFrames | Program::PreloadLines => {
            if o.replicas.contains(&0) {
                anyhow::bail!(
                    "--program {}: an unmodified program runs under a voter (--replicas 1,2,3); \
                     the no-voter baseline is `--program linked --replicas 0`",
                    o.program.name()
                );
            }
            let framing = if o.program == Program::PreloadLines {
                s3res_protocol::plan::Framing::Lines
            } else {
                s3res_protocol::plan::Framing::Frames
            };
            let library = common.bins.path("libs3res_preload.so")?;
            (
                std::path::PathBuf::from("/bin/cat"),
                Some((library, framing)),
            )
        }
    };
    let voter = if o.replicas.iter().any(|&r| r > 0) {
        Some(common.bins.path("s3res-voter")?)
    } else {
        None
    };
    let configs: Vec<(Setup, usize, usize)> = o
        .setups
        .iter()
        .flat_map(|&setup| {
            o.sizes
                .iter()
                .flat_map(move |&size| o.replicas.iter().map(move |&r| (setup, size, r)))
        })
        .collect();
    let bar = common.progress(configs.len() as u64 * (o.count + o.warmup), "echo");
    let mut rows = Vec::new();
    for &(setup, size, replicas) in &configs {
        bar.set_message(format!(
            "{} {} {}",
            setup.name(),
            report::level_name(replicas),
            report::bytes_name(size as u64)
        ));
        let spec = Spec {
            journal: common.journal,
            lock_memory: common.lock_memory,
            cpu_idle: common.cpu_idle,
            spin_us: common.spin_us,
            exec: echo.clone(),
            args: Vec::new(),
            replicas,
            timeout_us: o.timeout_us,
            max_frame: size.max(replica_rt::frame::DEFAULT_MAX_FRAME),
            voter: voter.clone(),
            setup,
            preload: preload.clone(),
        };
        let result = measure(&spec, setup, size, o, &bar);
        Setup::reset_bench();
        let mut row = result.with_context(|| {
            format!(
                "echo, {} replicas, {size} bytes, setup {}",
                replicas,
                setup.name()
            )
        })?;
        row.setup = setup.name();
        if o.program != Program::Linked {
            row.what = Some(o.program.name().to_owned());
        }
        rows.push(row);
    }
    bar.finish_and_clear();
    // Ratio to the no-voter row of the same size and setup, measured in this run.
    let baselines: Vec<(&'static str, u64, f64)> = rows
        .iter()
        .filter(|r| r.replicas == 0)
        .map(|r| (r.setup, r.size, r.median_us))
        .collect();
    for r in &mut rows {
        if let Some(&(_, _, base)) = baselines
            .iter()
            .find(|(s, z, _)| *s == r.setup && *z == r.size)
        {
            r.ratio = Some(r.median_us / base);
        }
    }
    Ok(rows)
}

fn measure(
    spec: &Spec,
    setup: Setup,
    size: usize,
    o: &EchoOptions,
    bar: &ProgressBar,
) -> Result<Row> {
    let mut system = System::start(spec)?;
    setup.apply(&system)?;
    // The payload lies where a frame buffer keeps one: copied behind its header, it does not
    // alias (see `frame::COPY_ALIGN`).
    let mut storage = FrameBuf::default();
    storage.encode(&vec![0u8; size]);
    let mut h = histogram();
    let total = o.warmup + o.count;
    let steal = report::Steal::start();
    for seq in 0..total {
        if o.program == Program::PreloadLines {
            fill_line(seq, storage.payload_mut());
        } else {
            fill_frame(seq, storage.payload_mut());
        }
        let answered = system
            .echo_round(storage.payload(), ROUND_LIMIT)
            .with_context(|| format!("round trip {seq}"))?;
        if let (Some(round_trip), true) = (answered, seq >= o.warmup) {
            h.record(round_trip).context("recording")?;
        }
        if seq % 512 == 511 {
            bar.inc(512);
        }
    }
    bar.inc(total % 512);
    let stolen = steal.ms();
    system.drain_events()?;
    let mut row = Row::new("echo", spec.replicas, size as u64, Summary::of(&h));
    row.steal_ms = stolen;
    if spec.replicas > 0 {
        row.timeout_us = Some(spec.timeout_us);
        row.faults = Some(system.faults.len() as u64);
        if system.lost.count > 0 || system.lost.late > 0 {
            row.extra = Some(serde_json::json!({
                "lost_rounds": system.lost.count,
                "late_answers": system.lost.late,
            }));
        }
    }
    Ok(row)
}

/// The echo table.
pub fn render(rows: &[Row]) -> String {
    let cells: Vec<Vec<String>> = rows
        .iter()
        .map(|r| {
            vec![
                r.what.clone().unwrap_or_else(|| "linked".to_owned()),
                r.setup.to_string(),
                report::level_name(r.replicas),
                report::bytes_name(r.size),
                r.count.to_string(),
                report::us(r.median_us),
                report::us(r.p99_us),
                report::us(r.p999_us),
                report::us(r.max_us),
                r.ratio.map(|x| format!("{x:.2}")).unwrap_or_default(),
                r.faults.map(|f| f.to_string()).unwrap_or_default(),
            ]
        })
        .collect();
    report::table(
        &[
            "program",
            "setup",
            "level",
            "size",
            "count",
            "median µs",
            "p99 µs",
            "p99.9 µs",
            "max µs",
            "×none",
            "faults",
        ],
        &cells,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::ValueEnum;

    #[test]
    fn a_program_is_named_in_results_as_on_the_command_line() {
        for p in Program::value_variants() {
            let on_command_line = p.to_possible_value().expect("not skipped");
            assert_eq!(p.name(), on_command_line.get_name());
        }
    }
}
