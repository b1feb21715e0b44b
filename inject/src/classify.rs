//! Unprotected outcome classification (after MAVFI's Fig. 5): run the system once without
//! injection (the golden run), then N times with exactly one injection each, and sort every
//! run into benign / SDC / crash / hang by comparing its output with the golden one.
//!
//! A system whose output is not the same from one fault-free run to the next (a robot in
//! closed loop with a simulator: its poses depend on timing) is classified by its mission
//! instead ([`MissionVerdict`], `--mission FILE`): what the simulator says of the mission is
//! the output, as MAVFI's end-to-end analysis takes flight success and time (its Table 2).

use std::fmt::Write as _;
use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{bail, Context as _};
use serde::{Deserialize, Serialize};

use crate::fault::{Action, RegOptions};
use crate::interval::Rate;
use crate::runner::{run_once, RunResult, RunSetup};
use crate::schedule::{plan_single, ScheduleParams};
use crate::scratch::ScratchDir;
use crate::stop::StopSignals;
use crate::target::Pick;
use s3res_protocol::campaign::{in_shard, runs_in_shard, VarSpec};

/// The class of one run. By output (the default), or by mission (`--mission`, see
/// [`mission_class`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Class {
    /// Exit status 0 and output identical to the golden run's (by mission: the goal reached).
    Benign,
    /// Exit status 0 but the output differs: silent data corruption (by mission: the robot
    /// collided, the injected component still running).
    Sdc,
    /// The system exited with a failure (a component died or reported an error; by mission:
    /// the mission was aborted or left no verdict).
    Crash,
    /// The system did not finish within the limit (by mission: also the simulator's own time
    /// limit passed before the goal).
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

/// What a simulator says of its mission: the fields of the summary it writes in the run's
/// folder (the maze robot's `s3res-sim --summary mission.json`) that classification reads.
/// Other fields are ignored.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MissionVerdict {
    /// The goal was reached without collision.
    pub success: bool,
    /// `goal`, `collision`, `time_limit`, `aborted` (the robot's words; any other is taken as
    /// an abort).
    pub outcome: String,
    /// Simulated time from start to the end of the mission.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mission_time_s: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub collisions: Option<u64>,
}

impl MissionVerdict {
    /// Reads `path`; why not if it is missing (the simulator was stopped before it could write
    /// one) or is not such a summary.
    pub fn read(path: &Path) -> Result<MissionVerdict, String> {
        let text = std::fs::read_to_string(path)
            .map_err(|e| format!("cannot read {}: {e}", path.display()))?;
        serde_json::from_str(&text)
            .map_err(|e| format!("{}: not a mission summary: {e}", path.display()))
    }
}

/// The class of a run by its mission. `timed_out`: killed at the run's limit; `failed`: the
/// injected component failed (bootstrap said so: [`component_failure`]); `exit_ok`: bootstrap
/// exited 0. What happened to the injected process comes first, as in MAVFI's classes: a
/// component that died is a crash, whatever the robot then did on its last command. Then the
/// mission is the output: the goal reached is benign; a collision, the injected component
/// still running, is a silent corruption of the commands; a mission that never ended (the simulator's time
/// limit: the robot stood still or wandered) is a hang; an aborted mission or none at all is
/// a crash, and so is a goal reached by a system that then failed.
pub fn mission_class(
    exit_ok: bool,
    timed_out: bool,
    failed: bool,
    verdict: Option<&MissionVerdict>,
) -> Class {
    if timed_out {
        return Class::Hang;
    }
    if failed {
        return Class::Crash;
    }
    match verdict {
        None => Class::Crash,
        Some(v) if v.success => {
            if exit_ok {
                Class::Benign
            } else {
                Class::Crash
            }
        }
        Some(v) => match v.outcome.as_str() {
            "collision" => Class::Sdc,
            "time_limit" => Class::Hang,
            _ => Class::Crash,
        },
    }
}

/// How `component` failed, if bootstrap's stderr says it did: bootstrap ends with one line
/// `s3res-bootstrap: component NAME failed: STATUS` per component that failed before any stop
/// (its documented exit contract), e.g. `killed by signal 11`. The components share that
/// stderr, so the line is looked for anywhere in a line (a component that died in the middle
/// of a line of its own leaves no newline before it), and the last one counts.
pub fn component_failure(stderr: &str, component: &str) -> Option<String> {
    let head = format!("s3res-bootstrap: component {component} failed: ");
    stderr
        .lines()
        .rev()
        .find_map(|l| l.rfind(&head).map(|at| &l[at + head.len()..]))
        .map(str::to_owned)
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
    /// How the injected component failed, as bootstrap reported it (`killed by signal 11`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub failure: Option<String>,
    /// By mission (`--mission`): the simulator's verdict, `None` if it wrote none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mission: Option<MissionVerdict>,
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
    /// Each class among the classified runs, with its 95 % interval (absent with none).
    #[serde(default)]
    pub rates: ClassRates,
    /// The components injected into.
    #[serde(default)]
    pub components: Vec<String>,
    /// Bits flipped per injection (`--fault reg`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reg_bits: Option<u32>,
    /// By mission (`--mission`): missions and their times.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub missions: Option<MissionSummary>,
}

/// The rate of each class among the classified runs.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct ClassRates {
    pub benign: Option<Rate>,
    pub sdc: Option<Rate>,
    pub crash: Option<Rate>,
    pub hang: Option<Rate>,
}

/// Missions of a classification by mission, as MAVFI's Table 2 gives flights: how many
/// succeeded, and how long the successful ones took against the golden run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MissionSummary {
    /// The golden run's verdict.
    pub golden: MissionVerdict,
    /// Successful missions among the classified runs.
    pub successful: Option<Rate>,
    /// Mission time of the successful injected runs: mean and longest, simulated seconds.
    pub time_mean_s: Option<f64>,
    pub time_max_s: Option<f64>,
}

/// `classify-run.json`: what a classification (or a shard of one) runs with, and what its
/// golden run gave. `merge` joins the shards of one classification by it, and `--resume`
/// checks it before it continues a folder.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ClassifyInfo {
    pub system: PathBuf,
    /// The description's digest (`s3res_protocol::campaign::description_digest`): a resume or
    /// merge across a change of the description is refused (`None`: recorded before this).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub system_digest: Option<String>,
    pub fault: crate::fault::FaultKind,
    pub components: Vec<String>,
    pub seed: u64,
    /// Runs of the whole classification (all shards).
    pub runs: u64,
    /// `(K, N)`: only the runs `r` with `r mod N = K − 1`.
    #[serde(default)]
    pub shard: Option<(u64, u64)>,
    /// The injection instant is uniform in this long after every target runs.
    pub window_ms: u64,
    /// The file holding the output, relative to the run's folder; `stdout` = bootstrap's.
    pub output: String,
    /// Classify by the mission summary this file in the run's folder holds, not by output.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mission: Option<String>,
    pub pick: Pick,
    pub var: VarSpec,
    pub reg: RegOptions,
    /// A run longer than this is killed: a hang.
    pub run_limit_ms: u64,
    /// The golden run's mission (by mission), once it ran.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub golden_mission: Option<MissionVerdict>,
}

impl ClassifyInfo {
    /// The runs this shard (or the whole classification) does.
    pub fn run_indices(&self) -> impl Iterator<Item = u64> + '_ {
        (0..self.runs).filter(|&r| self.has_run(r))
    }

    /// Run `r` is one of this shard's (or of the whole classification's).
    pub fn has_run(&self, r: u64) -> bool {
        r < self.runs && in_shard(self.shard, r)
    }

    /// How many runs this shard (or the whole classification) does.
    pub fn run_count(&self) -> u64 {
        runs_in_shard(self.shard, self.runs)
    }

    fn params(&self) -> ScheduleParams {
        ScheduleParams {
            fault: self.fault,
            rate_hz: 1.0,
            arrival: crate::schedule::Arrival::Fixed,
            window: Duration::from_millis(self.window_ms),
            components: self.components.clone(),
            var: self.var.clone(),
        }
    }

    /// The same classification, whatever shard and golden run: what shards share.
    fn whole(&self) -> ClassifyInfo {
        ClassifyInfo {
            shard: None,
            golden_mission: None,
            ..self.clone()
        }
    }
}

/// What `classify` needs.
#[derive(Debug, Clone)]
pub struct ClassifyRun {
    pub info: ClassifyInfo,
    pub bootstrap: PathBuf,
    pub out: PathBuf,
    /// Continue the classification `out` holds (the same parameters): run its missing runs.
    pub resume: bool,
    pub ready_limit: Duration,
}

impl ClassifyRun {
    fn setup(&self, dir: &Path, mark: String) -> RunSetup {
        RunSetup {
            bootstrap: self.bootstrap.clone(),
            system: self.info.system.clone(),
            dir: dir.to_path_buf(),
            mark,
            targets: self.info.components.clone(),
            pick: self.info.pick,
            reg: self.info.reg.clone(),
            limit: Duration::from_millis(self.info.run_limit_ms),
            ready_limit: self.ready_limit,
        }
    }

    fn output_of(&self, dir: &Path) -> Vec<u8> {
        let path = if self.info.output == "stdout" {
            RunResult::stdout_path(dir)
        } else {
            dir.join(&self.info.output)
        };
        std::fs::read(path).unwrap_or_default()
    }
}

/// The files of a classification's folder.
const INFO_FILE: &str = "classify-run.json";
const RECORDS_FILE: &str = "classify.jsonl";
const GOLDEN_FILE: &str = "golden.out";
pub(crate) const OUTPUT_FILES: [&str; 5] = [
    INFO_FILE,
    RECORDS_FILE,
    GOLDEN_FILE,
    "classify.json",
    "classify.md",
];

/// What a classification folder holds: its parameters, the golden output and the records of
/// the runs done (a record cut short by a kill is left out).
#[derive(Debug, Clone)]
pub struct ClassifyOutput {
    pub info: ClassifyInfo,
    pub golden: Vec<u8>,
    pub records: Vec<ClassRecord>,
}

impl ClassifyOutput {
    /// Reads `dir`; `None` if it holds no classification (no `classify-run.json`).
    pub fn read(dir: &Path) -> Result<Option<ClassifyOutput>, String> {
        let info_path = dir.join(INFO_FILE);
        let info = match std::fs::read_to_string(&info_path) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(format!("cannot read {}: {e}", info_path.display())),
        };
        // Written before classify-run.json: missing, the folder was cut or copied in part.
        let golden_path = dir.join(GOLDEN_FILE);
        let golden = std::fs::read(&golden_path).map_err(|e| {
            format!(
                "cannot read {} ({e}): the folder holds a classification without its golden \
                 output",
                golden_path.display()
            )
        })?;
        let path = dir.join(RECORDS_FILE);
        let records = match std::fs::read_to_string(&path) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => String::new(),
            Err(e) => return Err(format!("cannot read {}: {e}", path.display())),
        };
        let labels = [&info_path, &path].map(|p| p.display().to_string());
        ClassifyOutput::parse(labels, [&info, &records], golden).map(Some)
    }

    /// The same from the texts of `classify-run.json` and `classify.jsonl` (`labels` name
    /// them in errors) and the golden output. A last record cut short by a kill is left out.
    pub fn parse(
        labels: [String; 2],
        texts: [&String; 2],
        golden: Vec<u8>,
    ) -> Result<ClassifyOutput, String> {
        let info: ClassifyInfo = serde_json::from_str(texts[0])
            .map_err(|e| format!("{}: not a classification's parameters: {e}", labels[0]))?;
        if let Some((k, n)) = info.shard {
            if n == 0 || k == 0 || k > n {
                return Err(format!("{}: shard {k}/{n} is not one of 1..=N", labels[0]));
            }
        }
        Ok(ClassifyOutput {
            info,
            golden,
            records: crate::report::parse_jsonl(&labels[1], texts[1], true)?,
        })
    }

    /// The summary of the records (as `classify.json` has it).
    pub fn summary(&self) -> ClassSummary {
        summarise(&self.info, &self.records)
    }

    /// Writes the folder, each file whole (a kill leaves the old file or the new one): golden
    /// output, records (by run), summary and table, and the parameters last, so that a folder
    /// with `classify-run.json` has its golden output.
    pub fn write(&self, dir: &Path) -> anyhow::Result<ClassSummary> {
        use crate::report::write_whole;
        write_whole(&dir.join(GOLDEN_FILE), &self.golden)?;
        let mut records = self.records.clone();
        records.sort_by_key(|r| r.run);
        let mut text = String::new();
        for r in &records {
            text.push_str(&serde_json::to_string(r)?);
            text.push('\n');
        }
        write_whole(&dir.join(RECORDS_FILE), text.as_bytes())?;
        let summary = summarise(&self.info, &records);
        let json = serde_json::to_string_pretty(&summary)? + "\n";
        write_whole(&dir.join("classify.json"), json.as_bytes())?;
        let table = markdown(std::slice::from_ref(&summary));
        write_whole(&dir.join("classify.md"), table.as_bytes())?;
        let info = serde_json::to_string_pretty(&self.info)? + "\n";
        write_whole(&dir.join(INFO_FILE), info.as_bytes())?;
        Ok(summary)
    }
}

/// Runs the golden run and the injected runs of `c.info` (its shard); writes
/// `classify-run.json`, `golden.out`, `classify.jsonl`, `classify.json` and `classify.md`
/// into `c.out`. With `c.resume`, a folder holding the same classification keeps its golden
/// run and the runs it completed, and only the missing ones are run.
pub fn run(c: &ClassifyRun, stop: &StopSignals) -> anyhow::Result<ClassSummary> {
    let stop = || stop.requested().is_some();
    crate::scratch::check_out(&c.out, crate::scratch::OutKind::Classification)?;
    std::fs::create_dir_all(&c.out)
        .with_context(|| format!("cannot create the output folder {}", c.out.display()))?;
    let _lock = crate::scratch::lock_and_sweep(&c.out)?;
    let found = if c.resume {
        ClassifyOutput::read(&c.out).map_err(anyhow::Error::msg)?
    } else {
        None
    };
    let _ = replica_rt::sys::set_child_subreaper();
    let stamp = std::process::id();
    let mut output = match found {
        Some(old) => resumed(c, old)?,
        None => {
            if let Some(f) = OUTPUT_FILES.iter().find(|f| c.out.join(f).exists()) {
                if c.resume {
                    bail!(
                        "{} holds {f} but no {INFO_FILE}: a classification whose golden run did \
                         not finish, or one written before classifications could be resumed; \
                         it cannot be resumed (give a new --out folder)",
                        c.out.display()
                    );
                }
                bail!(
                    "{} already holds a classification ({f}); give a new --out folder, or \
                     --resume (with the same parameters) to finish its missing runs",
                    c.out.display()
                );
            }
            golden_run(c, stamp, &stop)?
        }
    };
    let records_path = c.out.join(RECORDS_FILE);
    let mut file = std::fs::OpenOptions::new()
        .append(true)
        .open(&records_path)
        .with_context(|| format!("cannot open {}", records_path.display()))?;
    let done: std::collections::BTreeSet<u64> = output.records.iter().map(|r| r.run).collect();
    let todo: Vec<u64> = c.info.run_indices().filter(|r| !done.contains(r)).collect();
    let params = c.info.params();
    for (i, &r) in todo.iter().enumerate() {
        let Some(planned) = plan_single(&params, c.info.seed, r) else {
            bail!("fault `none` or no component: nothing to classify");
        };
        let dir = ScratchDir::new(&c.out, "s3res-classify-")?;
        let result = run_once(
            &c.setup(dir.path(), format!("{stamp}-{}-{r}", c.info.seed)),
            std::slice::from_ref(&planned),
            &stop,
        );
        if result.interrupted {
            eprintln!(
                "s3res-inject: stopped by signal; the {} completed run(s) are kept (the same \
                 command with --resume runs the rest)",
                output.records.len()
            );
            break;
        }
        let rec = record(c, &output, r, &planned, &result, dir.path());
        writeln!(file, "{}", serde_json::to_string(&rec)?)?;
        if (i + 1) % 10 == 0 || i + 1 == todo.len() {
            eprintln!("s3res-inject: classify: run {}/{}", i + 1, todo.len());
        }
        output.records.push(rec);
    }
    drop(file);
    output.write(&c.out)
}

/// The golden run: its output (and mission) become the reference, written to `c.out` with the
/// parameters and an empty record file.
fn golden_run(
    c: &ClassifyRun,
    stamp: u32,
    stop: &dyn Fn() -> bool,
) -> anyhow::Result<ClassifyOutput> {
    let golden_dir = ScratchDir::new(&c.out, "s3res-golden-")?;
    let golden = run_once(
        &c.setup(golden_dir.path(), format!("{stamp}-golden")),
        &[],
        stop,
    );
    if golden.interrupted {
        bail!("stopped by signal during the golden run");
    }
    if !golden.status.is_some_and(|s| s.success()) || golden.timed_out {
        let stderr = std::fs::read(golden_dir.path().join("stderr")).unwrap_or_default();
        let stderr = String::from_utf8_lossy(&stderr);
        let lines: Vec<&str> = stderr.lines().collect();
        bail!(
            "the golden run (no injection) did not succeed ({:?}, timed out: {}); the last \
             lines of its stderr:\n{}",
            golden.status,
            golden.timed_out,
            lines[lines.len().saturating_sub(40)..].join("\n")
        );
    }
    // A file the golden run never wrote would be compared, empty, with every injected run's
    // empty one: every run benign. Refused as a mission summary it left no trace of is.
    if c.info.mission.is_none() && c.info.output != "stdout" {
        let path = golden_dir.path().join(&c.info.output);
        if !path.is_file() {
            bail!(
                "the golden run left no output file that --output {} names (no {} in the \
                 folder it ran in, removed since): give --output the file the system writes \
                 in its working directory, or leave it out to compare bootstrap's stdout",
                c.info.output,
                c.info.output,
            );
        }
    }
    let mut info = c.info.clone();
    info.golden_mission = match &c.info.mission {
        None => None,
        Some(file) => match MissionVerdict::read(&golden_dir.path().join(file)) {
            Ok(v) if v.success => Some(v),
            Ok(v) => bail!(
                "the golden run's mission did not succeed (outcome `{}`): runs with a fault \
                 cannot be told from it",
                v.outcome
            ),
            Err(e) => bail!(
                "the golden run left no mission summary that --mission {file} can read ({e}); \
                 give --mission the file the simulator writes in its folder, a JSON object \
                 with `success` and `outcome`"
            ),
        },
    };
    let output = ClassifyOutput {
        info,
        golden: c.output_of(golden_dir.path()),
        records: Vec::new(),
    };
    output.write(&c.out)?;
    tracing::info!(bytes = output.golden.len(), "golden run done");
    Ok(output)
}

/// The classification `old` found in `c.out`, to be continued: the same parameters, its
/// golden run, and the records of this shard's runs (each once).
fn resumed(c: &ClassifyRun, mut old: ClassifyOutput) -> anyhow::Result<ClassifyOutput> {
    let differ = differences(&old.info, &c.info, true)?;
    if !differ.is_empty() {
        bail!(
            "{} holds another classification, so --resume cannot continue it: {} (folder vs \
             command line); resume with the command that started it, or give a new --out folder",
            c.out.display(),
            differ.join(", ")
        );
    }
    let mut kept = std::collections::BTreeSet::new();
    old.records
        .retain(|r| c.info.has_run(r.run) && kept.insert(r.run));
    eprintln!(
        "s3res-inject: resuming: {} run(s) already done in {}, {} to go",
        old.records.len(),
        c.out.display(),
        c.info.run_count() - old.records.len() as u64
    );
    old.write(&c.out)?;
    Ok(old)
}

/// The parameters in which `a` and `b` differ (`key: A vs B`), their shards too if
/// `with_shard`; never their golden runs.
fn differences(
    a: &ClassifyInfo,
    b: &ClassifyInfo,
    with_shard: bool,
) -> anyhow::Result<Vec<String>> {
    // The description's digest only if both have one (one begun before it was recorded).
    let digest = a.system_digest.is_some() && b.system_digest.is_some();
    let value = |i: &ClassifyInfo| {
        let mut w = i.whole();
        if with_shard {
            w.shard = i.shard;
        }
        w.system_digest = w.system_digest.filter(|_| digest);
        serde_json::to_value(w)
    };
    Ok(crate::report::field_differences(&value(a)?, &value(b)?))
}

/// The record of run `r`.
fn record(
    c: &ClassifyRun,
    output: &ClassifyOutput,
    r: u64,
    planned: &crate::schedule::Planned,
    result: &RunResult,
    dir: &Path,
) -> ClassRecord {
    let out = c.output_of(dir);
    let attempt = result.attempts.first();
    let delivered = attempt.is_some_and(|a| a.ts_ns.is_some());
    let ok = result.status.is_some_and(|s| s.success());
    // The components share this file with bootstrap: a flipped one may write anything.
    let stderr = std::fs::read(dir.join("stderr")).unwrap_or_default();
    let failure = component_failure(&String::from_utf8_lossy(&stderr), &planned.component);
    let mission = c
        .info
        .mission
        .as_ref()
        .and_then(|file| MissionVerdict::read(&dir.join(file)).ok());
    let class = if !delivered {
        Class::Missed
    } else if c.info.mission.is_some() {
        mission_class(ok, result.timed_out, failure.is_some(), mission.as_ref())
    } else if result.timed_out {
        Class::Hang
    } else if !ok {
        Class::Crash
    } else if out != output.golden {
        Class::Sdc
    } else {
        Class::Benign
    };
    let status = result.status.map(|s| {
        use std::os::unix::process::ExitStatusExt as _;
        (s.code(), s.signal())
    });
    ClassRecord {
        seed: c.info.seed,
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
        failure,
        mission,
        diff: diff(&out, &output.golden),
    }
}

/// What [`merge`] made: the whole classification, and what it left out.
#[derive(Debug)]
pub struct Merged {
    pub output: ClassifyOutput,
    /// Runs of the classification in no input.
    pub missing: u64,
    /// Records dropped: a run not of its folder's shard, or beyond the classification's runs.
    pub stray: usize,
}

/// Joins the shards of one classification (folders `classify` wrote, named for errors) into
/// the whole: the records of every shard, each run once, and the first shard's golden run.
/// Refuses shards of different classifications, shards whose golden outputs differ (a run is
/// classified against its shard's golden output), and a run present twice.
pub fn merge(parts: Vec<(PathBuf, ClassifyOutput)>) -> Result<Merged, String> {
    let mut parts = parts.into_iter();
    let (first_dir, first) = parts.next().ok_or("nothing to merge")?;
    let mut stray = 0;
    let mut keep = |info: &ClassifyInfo, records: Vec<ClassRecord>| -> Vec<ClassRecord> {
        let (kept, dropped): (Vec<_>, Vec<_>) =
            records.into_iter().partition(|r| info.has_run(r.run));
        stray += dropped.len();
        kept
    };
    let records = keep(&first.info, first.records);
    let mut merged = ClassifyOutput {
        info: ClassifyInfo {
            shard: None,
            ..first.info.clone()
        },
        golden: first.golden,
        records,
    };
    for (dir, p) in parts {
        let differ = differences(&first.info, &p.info, false).map_err(|e| e.to_string())?;
        if !differ.is_empty() {
            return Err(format!(
                "{} and {} are not shards of one classification: {}; merge each one's shards \
                 apart",
                first_dir.display(),
                dir.display(),
                differ.join(", ")
            ));
        }
        if merged.info.mission.is_none() && p.golden != merged.golden {
            return Err(format!(
                "{} and {} made different golden outputs, so their runs were classified \
                 against different references; the system's output is not the same from one \
                 fault-free run to the next (classify it --mission, or keep the shards apart)",
                first_dir.display(),
                dir.display()
            ));
        }
        let records = keep(&p.info, p.records);
        merged.records.extend(records);
    }
    let mut seen = std::collections::BTreeSet::new();
    if let Some(r) = merged.records.iter().find(|r| !seen.insert(r.run)) {
        return Err(format!(
            "run {} is in more than one input (the same shard twice?)",
            r.run
        ));
    }
    // Every record is of a run of the whole, each once.
    let missing = merged.info.run_count() - merged.records.len() as u64;
    Ok(Merged {
        output: merged,
        missing,
        stray,
    })
}

fn summarise(info: &ClassifyInfo, recs: &[ClassRecord]) -> ClassSummary {
    let n = |k: Class| recs.iter().filter(|r| r.class == k).count() as u64;
    let (benign, sdc, crash, hang, missed) = (
        n(Class::Benign),
        n(Class::Sdc),
        n(Class::Crash),
        n(Class::Hang),
        n(Class::Missed),
    );
    let classified = recs.len() as u64 - missed;
    let rates = ClassRates {
        benign: Rate::of(benign, classified),
        sdc: Rate::of(sdc, classified),
        crash: Rate::of(crash, classified),
        hang: Rate::of(hang, classified),
    };
    // The plain percentages of earlier files: the rates', 0 with nothing classified.
    let pct = |r: Option<Rate>| r.map_or(0.0, |r| r.pct);
    let missions = info.golden_mission.clone().map(|golden| {
        let succeeded: Vec<&MissionVerdict> = recs
            .iter()
            .filter(|r| r.class != Class::Missed)
            .filter_map(|r| r.mission.as_ref())
            .filter(|m| m.success)
            .collect();
        let done: Vec<f64> = succeeded.iter().filter_map(|m| m.mission_time_s).collect();
        MissionSummary {
            golden,
            successful: Rate::of(succeeded.len() as u64, classified),
            time_mean_s: (!done.is_empty()).then(|| done.iter().sum::<f64>() / done.len() as f64),
            time_max_s: done.iter().copied().reduce(f64::max),
        }
    });
    ClassSummary {
        system: info.system.clone(),
        fault: info.fault,
        seed: info.seed,
        runs: recs.len() as u64,
        classified,
        benign,
        sdc,
        crash,
        hang,
        missed,
        pct_benign: pct(rates.benign),
        pct_sdc: pct(rates.sdc),
        pct_crash: pct(rates.crash),
        pct_hang: pct(rates.hang),
        rates,
        components: info.components.clone(),
        reg_bits: (info.fault == crate::fault::FaultKind::Reg).then_some(info.reg.bits),
        missions,
    }
}

/// A markdown table, one row per classification: each class's share of the classified runs
/// with its 95 % interval, and, by mission, the successful missions and their times.
pub fn markdown(rows: &[ClassSummary]) -> String {
    let by_mission = rows.iter().any(|r| r.missions.is_some());
    let mut s = String::from(
        "| System | Into | Fault | Runs | Benign % | SDC % | Crash % | Hang % | Missed |",
    );
    if by_mission {
        s.push_str(" Successful missions | Mission time, s: golden / mean / max |");
    }
    s.push_str("\n|---|---|---|--:|--:|--:|--:|--:|--:|");
    if by_mission {
        s.push_str("--:|--:|");
    }
    s.push('\n');
    let rate = |r: &Option<Rate>| match r {
        Some(r) => format!("{:.1} {}", r.pct, r.interval()),
        None => "–".to_owned(),
    };
    let secs = |t: Option<f64>| t.map_or("–".to_owned(), |t| format!("{t:.1}"));
    for r in rows {
        let fault = match r.reg_bits {
            Some(b) => format!("{} ({b} bit{})", r.fault, if b == 1 { "" } else { "s" }),
            None => r.fault.to_string(),
        };
        let _ = write!(
            s,
            "| {} | {} | {fault} | {} | {} | {} | {} | {} | {} |",
            r.system.display(),
            r.components.join(", "),
            r.classified,
            rate(&r.rates.benign),
            rate(&r.rates.sdc),
            rate(&r.rates.crash),
            rate(&r.rates.hang),
            r.missed
        );
        if by_mission {
            match &r.missions {
                Some(m) => {
                    let ok = match &m.successful {
                        Some(x) => format!("{}/{} {}", x.k, x.n, x.interval()),
                        None => "–".to_owned(),
                    };
                    let _ = write!(
                        s,
                        " {ok} | {} / {} / {} |",
                        secs(m.golden.mission_time_s),
                        secs(m.time_mean_s),
                        secs(m.time_max_s)
                    );
                }
                None => s.push_str(" – | – |"),
            }
        }
        s.push('\n');
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

    fn info(golden_mission: Option<MissionVerdict>) -> ClassifyInfo {
        ClassifyInfo {
            system: "robot.json".into(),
            system_digest: Some("fnv1a64:0".into()),
            fault: crate::fault::FaultKind::Exec,
            components: vec!["navigator".into()],
            seed: 1,
            runs: 5,
            shard: None,
            window_ms: 1000,
            output: "stdout".into(),
            mission: Some("mission.json".into()),
            pick: Pick::Uniform,
            var: VarSpec {
                offset: 0,
                field: s3res_protocol::campaign::VarField::Byte,
                flips: 1,
                bits: None,
            },
            reg: RegOptions::default(),
            run_limit_ms: 1000,
            golden_mission,
        }
    }

    fn verdict(success: bool, outcome: &str) -> MissionVerdict {
        MissionVerdict {
            success,
            outcome: outcome.to_owned(),
            mission_time_s: Some(20.0),
            collisions: None,
        }
    }

    #[test]
    fn a_mission_is_classified_by_its_outcome() {
        let goal = verdict(true, "goal");
        assert_eq!(
            mission_class(true, false, false, Some(&goal)),
            Class::Benign
        );
        // The goal reached, then a component failed: the system did not come through.
        assert_eq!(
            mission_class(false, false, false, Some(&goal)),
            Class::Crash
        );
        // The simulator exits 1 on a failed mission: the exit status says nothing more.
        for exit_ok in [true, false] {
            let c = |o| mission_class(exit_ok, false, false, Some(&verdict(false, o)));
            assert_eq!(c("collision"), Class::Sdc);
            assert_eq!(c("time_limit"), Class::Hang);
            assert_eq!(c("aborted"), Class::Crash);
            assert_eq!(c("something new"), Class::Crash);
            assert_eq!(mission_class(exit_ok, false, false, None), Class::Crash);
            // The injected component died: a crash, though the robot then hit a wall on its
            // last command (or even reached the goal).
            let collision = verdict(false, "collision");
            assert_eq!(
                mission_class(exit_ok, false, true, Some(&collision)),
                Class::Crash
            );
            assert_eq!(
                mission_class(exit_ok, false, true, Some(&goal)),
                Class::Crash
            );
            // Killed at the run's limit: a hang, whatever was written before.
            assert_eq!(
                mission_class(exit_ok, true, false, Some(&goal)),
                Class::Hang
            );
            assert_eq!(mission_class(exit_ok, true, true, None), Class::Hang);
        }
    }

    #[test]
    fn a_failure_is_read_from_bootstraps_last_lines() {
        let stderr = "2026-11-27T06:28:30Z  WARN failed: killed by signal 9 component=navigator\n\
                      s3res-bootstrap: component sim failed: exit status 1\n\
                      s3res-bootstrap: component navigator failed: killed by signal 9\n";
        assert_eq!(
            component_failure(stderr, "navigator").as_deref(),
            Some("killed by signal 9")
        );
        assert_eq!(
            component_failure(stderr, "sim").as_deref(),
            Some("exit status 1")
        );
        // A name that is a prefix of another's is not taken for it.
        assert_eq!(component_failure(stderr, "nav"), None);
        assert_eq!(component_failure(stderr, "planner"), None);
        // Behind a line a dying component left without its newline; the last one counts.
        let cut = "s3res-bootstrap: component planner failed: exit status 101\n\
                   {\"x\":1.5, partials3res-bootstrap: component planner failed: killed by signal 7\n";
        assert_eq!(
            component_failure(cut, "planner").as_deref(),
            Some("killed by signal 7")
        );
        let bytes = b"\xff\xfe garbage\ns3res-bootstrap: component sim failed: exit status 1\n";
        let text = String::from_utf8_lossy(bytes);
        assert_eq!(
            component_failure(&text, "sim").as_deref(),
            Some("exit status 1")
        );
    }

    fn output(info: ClassifyInfo, golden: &[u8], runs: &[u64]) -> (PathBuf, ClassifyOutput) {
        let records = runs
            .iter()
            .map(|&run| ClassRecord {
                seed: info.seed,
                run,
                at_ns: run * 10,
                ts_ns: Some(1),
                action: Action::Exec,
                component: "navigator".into(),
                replica: None,
                pid: None,
                class: Class::Crash,
                exit_code: Some(1),
                exit_signal: None,
                miss: None,
                failure: Some("killed by signal 9".into()),
                mission: None,
                diff: OutputDiff::default(),
            })
            .collect();
        let dir = PathBuf::from(format!("shard-{:?}", info.shard));
        (
            dir,
            ClassifyOutput {
                info,
                golden: golden.to_vec(),
                records,
            },
        )
    }

    fn shard(k: u64, n: u64) -> ClassifyInfo {
        ClassifyInfo {
            shard: Some((k, n)),
            mission: None,
            ..info(None)
        }
    }

    #[test]
    fn a_shard_counts_the_runs_it_does() {
        for runs in 0..12 {
            for n in 1..5 {
                for k in 1..=n {
                    let i = ClassifyInfo {
                        runs,
                        ..shard(k, n)
                    };
                    assert_eq!(
                        i.run_count(),
                        i.run_indices().count() as u64,
                        "{runs} {k}/{n}"
                    );
                    assert!(!i.has_run(runs), "{runs} {k}/{n}");
                }
            }
            let whole = ClassifyInfo { runs, ..info(None) };
            assert_eq!(whole.run_count(), runs);
        }
        // A shard that is not one (only a hand-edited file has it) does no run.
        let odd = shard(3, 2);
        assert_eq!((odd.run_count(), odd.has_run(2)), (0, false));
        let zero = shard(0, 0);
        assert_eq!((zero.run_count(), zero.has_run(0)), (0, false));
    }

    #[test]
    fn shards_merge_into_the_whole_and_nothing_else() {
        // Runs 0..5 in two shards: 0, 2, 4 and 1, 3. Run 3 in the first shard's folder is not
        // its run: left out, not counted.
        let a = output(shard(1, 2), b"golden", &[0, 2, 4, 3]);
        let b = output(shard(2, 2), b"golden", &[1]);
        let m = merge(vec![a.clone(), b.clone()]).unwrap();
        let runs: Vec<u64> = m.output.records.iter().map(|r| r.run).collect();
        assert_eq!(runs, [0, 2, 4, 1]);
        assert_eq!((m.missing, m.stray), (1, 1));
        assert_eq!(m.output.info.shard, None);
        assert_eq!(summarise(&m.output.info, &m.output.records).crash, 4);

        let twice = merge(vec![a.clone(), a.clone()]).unwrap_err();
        assert!(twice.contains("run 0 is in more than one input"), "{twice}");

        let other = ClassifyInfo {
            seed: 2,
            window_ms: 500,
            ..shard(2, 2)
        };
        let e = merge(vec![a.clone(), output(other, b"golden", &[1])]).unwrap_err();
        assert!(
            e.contains("seed: 1 vs 2") && e.contains("window_ms: 1000 vs 500"),
            "{e}"
        );

        let e = merge(vec![a.clone(), output(shard(2, 2), b"other", &[1])]).unwrap_err();
        assert!(e.contains("different golden outputs"), "{e}");
        // By mission, the goldens' outputs may differ: the mission is the reference.
        let by_mission = |k| ClassifyInfo {
            mission: Some("mission.json".into()),
            golden_mission: Some(verdict(true, "goal")),
            ..shard(k, 2)
        };
        let m = merge(vec![
            output(by_mission(1), b"one", &[0, 2, 4]),
            output(by_mission(2), b"two", &[1, 3]),
        ])
        .unwrap();
        assert_eq!(m.missing, 0);
        assert_eq!(m.output.golden, b"one");
    }

    #[test]
    fn a_folder_is_read_back_as_written_and_refused_without_its_golden_output() {
        let dir = tempfile::tempdir().unwrap();
        assert!(ClassifyOutput::read(dir.path()).unwrap().is_none());
        let (_, out) = output(shard(1, 2), b"golden", &[2, 0]);
        let s = out.write(dir.path()).unwrap();
        assert_eq!((s.runs, s.crash), (2, 2));
        let back = ClassifyOutput::read(dir.path()).unwrap().unwrap();
        assert_eq!(back.info, out.info);
        assert_eq!(back.golden, b"golden");
        let runs: Vec<u64> = back.records.iter().map(|r| r.run).collect();
        assert_eq!(runs, [0, 2], "written in run order");

        // A record cut short by a kill is left out; a folder without its golden output is not
        // taken for one with an empty output.
        let path = dir.path().join(RECORDS_FILE);
        let mut text = std::fs::read_to_string(&path).unwrap();
        text.push_str("{\"seed\":1,\"run\":4,");
        std::fs::write(&path, text).unwrap();
        assert_eq!(
            ClassifyOutput::read(dir.path())
                .unwrap()
                .unwrap()
                .records
                .len(),
            2
        );
        std::fs::remove_file(dir.path().join(GOLDEN_FILE)).unwrap();
        let e = ClassifyOutput::read(dir.path()).unwrap_err();
        assert!(e.contains("without its golden output"), "{e}");
    }

    #[test]
    fn a_mission_summary_is_read_from_the_simulators_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("mission.json");
        assert!(MissionVerdict::read(&path)
            .unwrap_err()
            .contains("cannot read"));
        std::fs::write(
            &path,
            r#"{"success":false,"outcome":"collision","periods":12,"mission_time_s":0.6,
               "collisions":1,"trajectory":[[0.1,0.2,0.3]]}"#,
        )
        .unwrap();
        let v = MissionVerdict::read(&path).unwrap();
        assert_eq!((v.success, v.outcome.as_str()), (false, "collision"));
        assert_eq!((v.mission_time_s, v.collisions), (Some(0.6), Some(1)));
        std::fs::write(&path, r#"{"success":true"#).unwrap();
        assert!(MissionVerdict::read(&path).is_err(), "truncated");
        std::fs::write(&path, r#"{"ok":true}"#).unwrap();
        let e = MissionVerdict::read(&path).unwrap_err();
        assert!(
            e.contains("not a mission summary") && e.contains("success"),
            "{e}"
        );
    }

    #[test]
    fn the_table_gives_every_rate_with_its_interval() {
        let rec = |class, mission: Option<MissionVerdict>| ClassRecord {
            seed: 1,
            run: 0,
            at_ns: 0,
            ts_ns: Some(1),
            action: Action::Exec,
            component: "navigator".into(),
            replica: None,
            pid: None,
            class,
            exit_code: None,
            exit_signal: None,
            miss: None,
            failure: None,
            mission,
            diff: OutputDiff::default(),
        };
        let mut fast = verdict(true, "goal");
        fast.mission_time_s = Some(19.0);
        let recs = [
            rec(Class::Benign, Some(fast)),
            rec(Class::Benign, Some(verdict(true, "goal"))),
            rec(Class::Sdc, Some(verdict(false, "collision"))),
            rec(Class::Crash, None),
            rec(Class::Missed, Some(verdict(true, "goal"))),
        ];
        let info = info(Some(verdict(true, "goal")));
        let s = summarise(&info, &recs);
        assert_eq!((s.classified, s.missed, s.benign), (4, 1, 2));
        let m = s.missions.as_ref().unwrap();
        // The missed run's mission is not counted: it had no fault.
        assert_eq!(m.successful.map(|r| (r.k, r.n)), Some((2, 4)));
        assert_eq!((m.time_mean_s, m.time_max_s), (Some(19.5), Some(20.0)));
        let table = markdown(&[s]);
        let row = table.lines().nth(2).unwrap();
        assert!(row.contains("| 50.0 [6.76, 93.24] |"), "{row}");
        assert!(
            row.contains("| 2/4 [6.76, 93.24] | 20.0 / 19.5 / 20.0 |"),
            "{row}"
        );
        assert!(row.contains("| navigator | exec | 4 |"), "{row}");
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
