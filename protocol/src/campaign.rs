//! The records a campaign of `s3res-inject` writes, and the parameters they are built from:
//! `campaign.json` ([`CampaignInfo`]), `runs.jsonl` ([`RunRecord`]) and `injections.jsonl`
//! ([`InjectionRecord`]), one JSON object a line. `merge`, `--resume` and outside tools read
//! them back with these types; what an injection became is [`crate::outcome`]'s.
//!
//! The parameter enums are also command-line values of `s3res-inject`: with the `clap`
//! feature they derive `clap::ValueEnum` (their doc comments are the help), without it this
//! crate does not depend on clap.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::machine::{Build, LoadAverage, Machine};
use crate::outcome::{Match, Outcome};

/// What kind of fault a campaign injects.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum FaultKind {
    /// Nothing is injected: a baseline that counts false positives and task success.
    None,
    /// Execution error: SIGKILL.
    Exec,
    /// Silent data corruption: replica-rt flips one bit of the next outgoing frame (SIGUSR2).
    Sdc,
    /// Control-flow error: replica-rt spins forever (signal 36, glibc's SIGRTMIN+2).
    Cfe,
    /// Variable-level flip: chosen bits at a chosen byte offset of the next frame (signal 37,
    /// glibc's SIGRTMIN+3).
    Var,
    /// Register bit flip through ptrace (the s3res-regflip crate).
    Reg,
    /// Exec, sdc or cfe, drawn for each injection, each equally likely (the storm's mix, for a
    /// campaign: each injection's record says which it was).
    Mixed,
}

impl FaultKind {
    pub fn name(self) -> &'static str {
        match self {
            FaultKind::None => "none",
            FaultKind::Exec => "exec",
            FaultKind::Sdc => "sdc",
            FaultKind::Cfe => "cfe",
            FaultKind::Var => "var",
            FaultKind::Reg => "reg",
            FaultKind::Mixed => "mixed",
        }
    }
}

impl std::fmt::Display for FaultKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// One injection, fully decided.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum Action {
    Exec,
    /// `value` is the `sigqueue` value: the bit to flip, reduced by the replica modulo the
    /// frame's bit count (bit 0 = lowest bit of the first payload byte).
    Sdc {
        value: u32,
    },
    Cfe,
    /// Flip `bits` (bit 0 = lowest bit of byte `offset`, little-endian) of the next frame.
    Var {
        offset: u32,
        bits: Vec<u32>,
    },
    /// A register flip; `seed` seeds the ChaCha8 generator handed to the register injector.
    /// Written `reg_seed`: an injection record carries the campaign's `seed` beside its action,
    /// and a second `seed` made every line of a register campaign unreadable to `merge`.
    Reg {
        #[serde(rename = "reg_seed")]
        seed: u64,
    },
}

impl Action {
    pub fn kind(&self) -> FaultKind {
        match self {
            Action::Exec => FaultKind::Exec,
            Action::Sdc { .. } => FaultKind::Sdc,
            Action::Cfe => FaultKind::Cfe,
            Action::Var { .. } => FaultKind::Var,
            Action::Reg { .. } => FaultKind::Reg,
        }
    }
}

/// Options of the register injector, as given on the command line (see
/// `s3res-regflip`'s `RegFlipSpec`).
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct RegOptions {
    /// `source`, `destination` or `any` operand.
    pub role: String,
    /// Bits flipped per injection.
    pub bits: u32,
    /// `whole`, `sign`, `exponent` or `mantissa`.
    pub field: String,
    /// Only these registers (names as the injector spells them); all if `None`.
    pub registers: Option<Vec<String>>,
}

/// How inter-arrival times are drawn.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum Arrival {
    /// Exponential with mean 1/rate (a Poisson process).
    Exponential,
    /// Exactly 1/rate apart, the first one after 1/rate.
    Fixed,
}

/// Which bits of the value at `--var-offset` a variable-level injection may flip. The value is
/// read as a little-endian 64-bit word (an f64: bit 63 sign, 52..63 exponent, 0..52 mantissa).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum VarField {
    /// Bit 63 of the f64 (only one bit to flip).
    Sign,
    /// Bits 52..63 of the f64.
    Exponent,
    /// Bits 0..52 of the f64.
    Mantissa,
    /// Any of the 64 bits.
    Whole,
    /// Any bit of the single byte at the offset.
    Byte,
}

impl VarField {
    /// The bit range, relative to the offset.
    pub fn bits(self) -> std::ops::Range<u32> {
        match self {
            VarField::Sign => 63..64,
            VarField::Exponent => 52..63,
            VarField::Mantissa => 0..52,
            VarField::Whole => 0..64,
            VarField::Byte => 0..8,
        }
    }
}

/// What a variable-level injection flips.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct VarSpec {
    /// Byte offset of the value in the payload.
    pub offset: u32,
    pub field: VarField,
    /// How many distinct bits of the field each injection flips.
    pub flips: u32,
    /// Exactly these bits (relative to the offset) instead of a random choice.
    pub bits: Option<Vec<u32>>,
}

/// `s3res-inject`'s defaults: one bit of the whole 64-bit value at offset 0.
impl Default for VarSpec {
    fn default() -> Self {
        VarSpec {
            offset: 0,
            field: VarField::Whole,
            flips: 1,
            bits: None,
        }
    }
}

impl VarSpec {
    /// Checks that the request can be satisfied; the reason if not.
    pub fn validate(&self) -> Result<(), String> {
        let range = self.field.bits();
        if self.bits.is_none() && (self.flips == 0 || self.flips > range.len() as u32) {
            return Err(format!(
                "--var-flips {} does not fit field {:?} ({} bits)",
                self.flips,
                self.field,
                range.len()
            ));
        }
        if let Some(bits) = &self.bits {
            if bits.is_empty() {
                return Err("--var-bits names no bit".to_owned());
            }
            // The value is 64 bits wide: a bit past it would flip a byte of the next field.
            if let Some(b) = bits.iter().find(|&&b| b >= 64) {
                return Err(format!(
                    "--var-bits {b}: the value at the offset is 64 bits wide (bits 0..=63)"
                ));
            }
        }
        Ok(())
    }
}

/// How the replica of a protected component is chosen.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum Pick {
    /// Every slot equally likely (the same seed picks the same slots).
    Uniform,
    /// Proportional to each running replica's CPU time so far (user + system, from
    /// /proc/PID/stat): exposure to upsets grows with time on the CPU. The draw is the same for
    /// the same seed; the slot it lands on depends on the measured times.
    Cpu,
}

/// `campaign.json`: the parameters of a campaign (or of one shard of it).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CampaignInfo {
    /// Row label in the tables ("tmr", or what `--label` said).
    pub config: String,
    /// The description as given, and the system's name.
    pub system: PathBuf,
    pub system_name: String,
    /// [`description_digest`] of the description's text when the campaign began: a resume or
    /// a merge of runs of a description changed in between is refused (`None`: a campaign
    /// recorded before this was kept).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub system_digest: Option<String>,
    pub fault: FaultKind,
    pub rate_hz: f64,
    pub arrival: Arrival,
    pub window_ms: u64,
    /// Runs of the whole campaign (all shards).
    pub runs: u64,
    pub seed: u64,
    /// `(k, n)`: this output holds runs `r` with `r % n == k - 1`. `None`: all runs.
    pub shard: Option<(u64, u64)>,
    pub pick: Pick,
    pub components: Vec<String>,
    pub var: VarSpec,
    pub reg: RegOptions,
    pub match_window_ms: u64,
    pub run_limit_ms: u64,
    /// File (in each run's folder) the task writes its verdict to, if any.
    pub task_summary: Option<String>,
    /// Redundancy of every component of the system.
    pub redundancy: BTreeMap<String, String>,
    /// The machine and build the runs ran on (of the first input, after a `merge`). Each run's
    /// load average before and after it is in `runs.jsonl`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub machine: Option<MachineInfo>,
}

/// Where a campaign ran: the machine (with its load when the campaign began), the load when it
/// ended, and the build of s3res-bootstrap it ran.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MachineInfo {
    #[serde(flatten)]
    pub machine: Machine,
    #[serde(default)]
    pub load_at_end: Option<LoadAverage>,
    pub build: Build,
}

impl MachineInfo {
    /// This machine now, running the build of `bootstrap`.
    pub fn probe(bootstrap: &Path) -> MachineInfo {
        MachineInfo {
            machine: Machine::probe(),
            load_at_end: None,
            build: Build::of(bootstrap),
        }
    }
}

/// The highest injection rate, per second: of a description's `inject.rate_hz` and of
/// `s3res-inject`'s `--rate` (no target can take faults faster than it can be rebuilt, and a
/// storm asked for a billion a second would do nothing but inject).
pub const MAX_RATE_HZ: f64 = 1000.0;

/// The most injections one campaign run may plan: its schedule is planned whole before the
/// run (a million take ~50 MB; `--rate 1000 --duration 1e9` planned 10^12 and died of it).
pub const MAX_PLANNED_PER_RUN: f64 = 1e6;

/// Why an injection rate, or a run's schedule, is refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RateError {
    #[error("{0:?} is not a rate: give injections per second, above 0 (e.g. 2)")]
    NotARate(f64),
    #[error("{0:?} injections per second: at most {MAX_RATE_HZ}")]
    TooHigh(f64),
    #[error(
        "{rate:?} injections per second for {window_s:?} s plan {planned:.3e} injections in one \
         run: at most {MAX_PLANNED_PER_RUN:.0e} (a lower rate or a shorter window)"
    )]
    TooMany {
        rate: f64,
        window_s: f64,
        planned: f64,
    },
}

/// A rate of injections per second: finite, above 0, at most [`MAX_RATE_HZ`].
pub fn check_rate(rate: f64) -> Result<(), RateError> {
    if !(rate.is_finite() && rate > 0.0) {
        return Err(RateError::NotARate(rate));
    }
    if rate > MAX_RATE_HZ {
        return Err(RateError::TooHigh(rate));
    }
    Ok(())
}

/// [`check_rate`], and at most [`MAX_PLANNED_PER_RUN`] injections expected in a `window`.
pub fn check_schedule(rate: f64, window: std::time::Duration) -> Result<(), RateError> {
    check_rate(rate)?;
    let planned = rate * window.as_secs_f64();
    if planned > MAX_PLANNED_PER_RUN {
        return Err(RateError::TooMany {
            rate,
            window_s: window.as_secs_f64(),
            planned,
        });
    }
    Ok(())
}

/// A digest of a description's text (64-bit FNV-1a, in hex): not a cryptographic hash, a
/// check that two campaigns ran the same description.
pub fn description_digest(text: &[u8]) -> String {
    let hash = text.iter().fold(0xcbf2_9ce4_8422_2325_u64, |h, &b| {
        (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3)
    });
    format!("fnv1a64:{hash:016x}")
}

impl CampaignInfo {
    /// The same campaign whatever the shard: what shards must agree on to be merged. With a
    /// digest of the description, not where it was (shards run from checkouts of their own).
    pub fn identity(&self) -> CampaignInfo {
        CampaignInfo {
            shard: None,
            machine: None,
            system: match self.system_digest {
                Some(_) => PathBuf::new(),
                None => self.system.clone(),
            },
            ..self.clone()
        }
    }

    /// The runs this shard (or the whole campaign) does.
    pub fn run_indices(&self) -> impl Iterator<Item = u64> + '_ {
        (0..self.runs).filter(|&r| in_shard(self.shard, r))
    }
}

/// Run `r` is one of shard `(K, N)`'s (`r mod N = K − 1`), or there is no shard. A shard that
/// is not one (`K` outside `1..=N`, only a hand-edited file has it) has no run.
pub fn in_shard(shard: Option<(u64, u64)>, r: u64) -> bool {
    match shard {
        Some((k, n)) => (1..=n).contains(&k) && r % n == k - 1,
        None => true,
    }
}

/// How many of the runs `0..runs` are in `shard` (see [`in_shard`]), without listing them.
pub fn runs_in_shard(shard: Option<(u64, u64)>, runs: u64) -> u64 {
    match shard {
        Some((k, n)) if (1..=n).contains(&k) => runs / n + u64::from(runs % n >= k),
        Some(_) => 0,
        None => runs,
    }
}

/// One line of `injections.jsonl`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct InjectionRecord {
    pub config: String,
    /// The campaign seed (the run's own seed is in `runs.jsonl`).
    pub seed: u64,
    pub run: u64,
    pub index: usize,
    /// Planned instant, from the opening of the run's injection window.
    pub at_ns: u64,
    /// CLOCK_MONOTONIC when the signal went out; absent if it did not.
    #[serde(default)]
    pub ts_ns: Option<u64>,
    /// `kind` and its fields (`value`, `offset`, `bits`, `seed`).
    #[serde(flatten)]
    pub action: Action,
    pub component: String,
    /// Replica slot (absent for an unprotected component, or a missed injection whose draw
    /// chose no slot: one missed because its slot was being replaced names that slot).
    #[serde(default)]
    pub replica: Option<usize>,
    #[serde(default)]
    pub pid: Option<i32>,
    pub outcome: Outcome,
    /// Why it was not delivered (outcome `missed`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub miss: Option<String>,
    #[serde(flatten)]
    pub matched: Match,
    /// The injector's own record (register flips).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub injector: Option<serde_json::Value>,
}

/// One line of `runs.jsonl`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunRecord {
    pub config: String,
    pub seed: u64,
    pub run: u64,
    pub run_seed: u64,
    /// bootstrap's exit code, or the signal that ended it.
    #[serde(default)]
    pub exit_code: Option<i32>,
    #[serde(default)]
    pub exit_signal: Option<i32>,
    pub timed_out: bool,
    /// Every target ran before injection began.
    pub ready: bool,
    /// The task's verdict, from the task summary file (`ok`), if one was asked for.
    #[serde(default)]
    pub task_summary_ok: Option<bool>,
    /// The verdict: exit status 0, not timed out, and the task summary (if any) says ok.
    pub task_ok: bool,
    pub planned: u64,
    pub injected: u64,
    pub false_positives: u64,
    pub events: u64,
    pub duration_ms: u64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    /// The machine's load average just before the run started and just after it ended.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub load_before: Option<LoadAverage>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub load_after: Option<LoadAverage>,
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Lines as campaigns have written them: each parses and is written back byte for byte, so
    /// `merge` and `--resume` keep reading the files of earlier builds.
    #[test]
    fn records_keep_their_format() {
        fn same<T: Serialize + serde::de::DeserializeOwned>(line: &str) -> T {
            let record: T = serde_json::from_str(line).unwrap();
            assert_eq!(serde_json::to_string(&record).unwrap(), line);
            record
        }
        let info: CampaignInfo = same(
            r#"{"config":"tmr","system":"s.json","system_name":"s","fault":"var","rate_hz":2.0,"arrival":"exponential","window_ms":1000,"runs":4,"seed":1,"shard":[1,2],"pick":"cpu","components":["echo"],"var":{"offset":0,"field":"exponent","flips":1,"bits":null},"reg":{"role":"","bits":0,"field":"","registers":null},"match_window_ms":2000,"run_limit_ms":60000,"task_summary":null,"redundancy":{"echo":"tmr"},"machine":{"cpu_model":"x","cores":2,"usable_cores":2,"kernel":"6.1","load":null,"load_at_end":null,"build":{"profile":"release","commit":"abc","dirty":false}}}"#,
        );
        assert_eq!(info.run_indices().collect::<Vec<_>>(), vec![0, 2]);
        let inj: InjectionRecord = same(
            r#"{"config":"tmr","seed":1,"run":0,"index":0,"at_ns":5,"ts_ns":7,"kind":"var","offset":8,"bits":[63],"component":"echo","replica":1,"pid":42,"outcome":"recovered","detected_as":"sdc","detection_latency_us":120,"recovery_us":900,"recovered_after_us":1100,"recovery_method":"fork"}"#,
        );
        assert_eq!(inj.action.kind(), FaultKind::Var);
        same::<InjectionRecord>(
            r#"{"config":"tmr","seed":1,"run":1,"index":2,"at_ns":5,"ts_ns":null,"kind":"sdc","value":3,"component":"echo","replica":null,"pid":null,"outcome":"missed","miss":"target busy"}"#,
        );
        // A register flip's own seed beside the campaign's (once both were `seed`, and no
        // line of a register campaign could be read back).
        let reg: InjectionRecord = same(
            r#"{"config":"tmr","seed":1,"run":0,"index":0,"at_ns":5,"ts_ns":7,"kind":"reg","reg_seed":1594,"component":"navigator","replica":1,"pid":42,"outcome":"benign","injector":{"register":"rdx","seed":1594}}"#,
        );
        assert_eq!((reg.seed, reg.action), (1, Action::Reg { seed: 1594 }));
        same::<RunRecord>(
            r#"{"config":"tmr","seed":1,"run":0,"run_seed":99,"exit_code":0,"exit_signal":null,"timed_out":false,"ready":true,"task_summary_ok":null,"task_ok":true,"planned":3,"injected":2,"false_positives":0,"events":4,"duration_ms":1500,"load_before":{"one":0.5,"five":0.25,"fifteen":0.125}}"#,
        );
    }
}
