//! Unprotected outcome classification (after MAVFI's Fig. 5): run the system once without
//! injection (the golden run), then N times with exactly one injection each, and sort every
//! run into benign / SDC / crash / hang by comparing its output with the golden one.

use std::fmt::Write as _;
use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{bail, Context as _};
use serde::{Deserialize, Serialize};

use crate::fault::{Action, RegOptions};
use crate::runner::{run_once, RunResult, RunSetup};
use crate::schedule::{plan_single, ScheduleParams};
use crate::stop::StopSignals;
use crate::target::Pick;

/// The class of one run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Class {
    /// Exit status 0 and output identical to the golden run's.
    Benign,
    /// Exit status 0 but the output differs: silent data corruption.
    Sdc,
    /// The system exited with a failure (a component died or reported an error).
    Crash,
    /// The system did not finish within the limit.
    Hang,
    /// The injection could not be delivered (not counted).
    Missed,
}

/// How the output differs from the golden output.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct OutputDiff {
    /// Frames (4-byte length + payload) in this output and in the golden one.
    pub frames: u64,
    pub golden_frames: u64,
    /// Frames at the same position whose bytes differ.
    pub frames_differing: u64,
    /// Bits that differ over the bytes both outputs have.
    pub bits_differing: u64,
    /// The outputs have different lengths.
    pub length_differs: bool,
    /// Where the first difference is: frame index, byte offset in its payload, XOR of the
    /// two bytes there.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub first: Option<FirstDifference>,
}

/// The first differing byte of two outputs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct FirstDifference {
    pub frame: u64,
    /// Offset in the frame's payload (negative: in the 4-byte length header).
    pub payload_offset: i64,
    pub xor: u8,
}

/// Compares two outputs byte by byte and frame by frame.
pub fn diff(out: &[u8], golden: &[u8]) -> OutputDiff {
    let a = frames(out);
    let b = frames(golden);
    OutputDiff {
        frames: a.len() as u64,
        golden_frames: b.len() as u64,
        frames_differing: a.iter().zip(&b).filter(|(x, y)| x != y).count() as u64,
        bits_differing: out
            .iter()
            .zip(golden)
            .map(|(x, y)| u64::from((x ^ y).count_ones()))
            .sum(),
        length_differs: out.len() != golden.len(),
        first: first_difference(out, golden, &b),
    }
}

fn first_difference(out: &[u8], golden: &[u8], golden_frames: &[&[u8]]) -> Option<FirstDifference> {
    let at = out.iter().zip(golden).position(|(x, y)| x != y)?;
    let mut start = 0;
    for (i, f) in golden_frames.iter().enumerate() {
        if at < start + f.len() {
            return Some(FirstDifference {
                frame: i as u64,
                payload_offset: (at - start) as i64 - 4,
                xor: out[at] ^ golden[at],
            });
        }
        start += f.len();
    }
    None
}

/// Splits a byte stream into frames (a trailing partial frame is one more "frame").
fn frames(mut s: &[u8]) -> Vec<&[u8]> {
    let mut out = Vec::new();
    while !s.is_empty() {
        let len = s
            .get(..4)
            .map(|h| u32::from_le_bytes([h[0], h[1], h[2], h[3]]) as usize);
        let end = len.map_or(s.len(), |l| (4 + l).min(s.len()));
        out.push(&s[..end]);
        s = &s[end..];
    }
    out
}

/// One line of `classify.jsonl`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ClassRecord {
    pub seed: u64,
    pub run: u64,
    pub at_ns: u64,
    #[serde(default)]
    pub ts_ns: Option<u64>,
    #[serde(flatten)]
    pub action: Action,
    pub component: String,
    #[serde(default)]
    pub replica: Option<usize>,
    #[serde(default)]
    pub pid: Option<i32>,
    pub class: Class,
    #[serde(default)]
    pub exit_code: Option<i32>,
    #[serde(default)]
    pub exit_signal: Option<i32>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub miss: Option<String>,
    pub diff: OutputDiff,
}

/// `classify.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ClassSummary {
    pub system: PathBuf,
    pub fault: crate::fault::FaultKind,
    pub seed: u64,
    pub runs: u64,
    pub classified: u64,
    pub benign: u64,
    pub sdc: u64,
    pub crash: u64,
    pub hang: u64,
    pub missed: u64,
    pub pct_benign: f64,
    pub pct_sdc: f64,
    pub pct_crash: f64,
    pub pct_hang: f64,
}

/// What `classify` needs.
#[derive(Debug, Clone)]
pub struct ClassifyRun {
    pub system: PathBuf,
    pub bootstrap: PathBuf,
    pub out: PathBuf,
    pub params: ScheduleParams,
    pub seed: u64,
    pub runs: u64,
    pub pick: Pick,
    pub reg: RegOptions,
    /// The file holding the output, relative to the run's folder; `stdout` = bootstrap's.
    pub output: String,
    pub limit: Duration,
    pub ready_limit: Duration,
}

impl ClassifyRun {
    fn setup(&self, dir: &Path, mark: String) -> RunSetup {
        RunSetup {
            bootstrap: self.bootstrap.clone(),
            system: self.system.clone(),
            dir: dir.to_path_buf(),
            mark,
            targets: self.params.components.clone(),
            pick: self.pick,
            reg: self.reg.clone(),
            limit: self.limit,
            ready_limit: self.ready_limit,
        }
    }

    fn output_of(&self, dir: &Path) -> Vec<u8> {
        let path = if self.output == "stdout" {
            RunResult::stdout_path(dir)
        } else {
            dir.join(&self.output)
        };
        std::fs::read(path).unwrap_or_default()
    }
}

/// Runs the golden run and the N injected runs; writes `classify.jsonl`, `classify.json` and
/// `classify.md` into `c.out`.
pub fn run(c: &ClassifyRun, stop: &StopSignals) -> anyhow::Result<ClassSummary> {
    let stop = || stop.requested().is_some();
    std::fs::create_dir_all(&c.out)
        .with_context(|| format!("cannot create the output folder {}", c.out.display()))?;
    if c.out.join("classify.jsonl").exists() {
        bail!(
            "{} already holds a classification; give a new --out folder",
            c.out.display()
        );
    }
    let _ = replica_rt::sys::set_child_subreaper();
    let stamp = std::process::id();

    let golden_dir = tempfile::Builder::new().prefix("s3res-golden-").tempdir()?;
    let golden = run_once(
        &c.setup(golden_dir.path(), format!("{stamp}-golden")),
        &[],
        &stop,
    );
    if golden.interrupted {
        bail!("stopped by signal during the golden run");
    }
    if !golden.status.is_some_and(|s| s.success()) || golden.timed_out {
        bail!(
            "the golden run (no injection) did not succeed ({:?}, timed out: {}); stderr:\n{}",
            golden.status,
            golden.timed_out,
            std::fs::read_to_string(golden_dir.path().join("stderr")).unwrap_or_default()
        );
    }
    let golden_out = c.output_of(golden_dir.path());
    std::fs::write(c.out.join("golden.out"), &golden_out)?;
    tracing::info!(bytes = golden_out.len(), "golden run done");

    let mut file = std::fs::File::create(c.out.join("classify.jsonl"))?;
    let mut records = Vec::new();
    for r in 0..c.runs {
        let Some(planned) = plan_single(&c.params, c.seed, r) else {
            bail!("fault `none` or no component: nothing to classify");
        };
        let dir = tempfile::Builder::new()
            .prefix("s3res-classify-")
            .tempdir()?;
        let result = run_once(
            &c.setup(dir.path(), format!("{stamp}-{}-{r}", c.seed)),
            std::slice::from_ref(&planned),
            &stop,
        );
        if result.interrupted {
            eprintln!("s3res-inject: stopped by signal; the {r} completed run(s) are kept");
            break;
        }
        let out = c.output_of(dir.path());
        let attempt = result.attempts.first();
        let delivered = attempt.is_some_and(|a| a.ts_ns.is_some());
        let ok = result.status.is_some_and(|s| s.success());
        let class = if !delivered {
            Class::Missed
        } else if result.timed_out {
            Class::Hang
        } else if !ok {
            Class::Crash
        } else if out != golden_out {
            Class::Sdc
        } else {
            Class::Benign
        };
        let status = result.status.map(|s| {
            use std::os::unix::process::ExitStatusExt as _;
            (s.code(), s.signal())
        });
        let rec = ClassRecord {
            seed: c.seed,
            run: r,
            at_ns: planned.at_ns,
            ts_ns: attempt.and_then(|a| a.ts_ns),
            action: planned.action.clone(),
            component: planned.component.clone(),
            replica: attempt.and_then(|a| a.slot),
            pid: attempt.and_then(|a| a.pid),
            class,
            exit_code: status.and_then(|s| s.0),
            exit_signal: status.and_then(|s| s.1),
            miss: attempt.and_then(|a| a.miss.clone()),
            diff: diff(&out, &golden_out),
        };
        writeln!(file, "{}", serde_json::to_string(&rec)?)?;
        if (r + 1) % 10 == 0 || r + 1 == c.runs {
            eprintln!("s3res-inject: classify: run {}/{}", r + 1, c.runs);
        }
        records.push(rec);
    }
    let summary = summarise(c, &records);
    std::fs::write(
        c.out.join("classify.json"),
        serde_json::to_string_pretty(&summary)? + "\n",
    )?;
    std::fs::write(
        c.out.join("classify.md"),
        markdown(std::slice::from_ref(&summary)),
    )?;
    Ok(summary)
}

fn summarise(c: &ClassifyRun, recs: &[ClassRecord]) -> ClassSummary {
    let n = |k: Class| recs.iter().filter(|r| r.class == k).count() as u64;
    let classified = recs.len() as u64 - n(Class::Missed);
    let pct = |k: Class| {
        if classified == 0 {
            0.0
        } else {
            n(k) as f64 * 100.0 / classified as f64
        }
    };
    ClassSummary {
        system: c.system.clone(),
        fault: c.params.fault,
        seed: c.seed,
        runs: recs.len() as u64,
        classified,
        benign: n(Class::Benign),
        sdc: n(Class::Sdc),
        crash: n(Class::Crash),
        hang: n(Class::Hang),
        missed: n(Class::Missed),
        pct_benign: pct(Class::Benign),
        pct_sdc: pct(Class::Sdc),
        pct_crash: pct(Class::Crash),
        pct_hang: pct(Class::Hang),
    }
}

/// A markdown table, one row per classification.
pub fn markdown(rows: &[ClassSummary]) -> String {
    let mut s = String::from(
        "| System | Fault | Runs | Benign % | SDC % | Crash % | Hang % | Missed |\n|---|---|--:|--:|--:|--:|--:|--:|\n",
    );
    for r in rows {
        let _ = writeln!(
            s,
            "| {} | {} | {} | {:.1} | {:.1} | {:.1} | {:.1} | {} |",
            r.system.display(),
            r.fault,
            r.classified,
            r.pct_benign,
            r.pct_sdc,
            r.pct_crash,
            r.pct_hang,
            r.missed
        );
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(p: &[u8]) -> Vec<u8> {
        let mut v = (p.len() as u32).to_le_bytes().to_vec();
        v.extend_from_slice(p);
        v
    }

    #[test]
    fn diff_counts_frames_and_bits() {
        let golden = [frame(&[1, 2, 3]), frame(&[4, 5])].concat();
        let mut out = golden.clone();
        out[4 + 3 + 4 + 1] ^= 0x81; // second frame, second byte, two bits
        let d = diff(&out, &golden);
        assert_eq!((d.frames, d.golden_frames), (2, 2));
        assert_eq!((d.frames_differing, d.bits_differing), (1, 2));
        assert!(!d.length_differs);
        assert_eq!(
            d.first,
            Some(FirstDifference {
                frame: 1,
                payload_offset: 1,
                xor: 0x81
            })
        );
        let short = &golden[..golden.len() - 1];
        let d = diff(short, &golden);
        assert!(d.length_differs);
        assert_eq!(d.frames, 2);
        assert_eq!(d.frames_differing, 1);
    }
}
