//! `s3res-inject`: fault injection into s3res systems. See `--help` and docs/campaigns.md.

#![forbid(unsafe_code)]

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Duration;

use anyhow::{bail, Context as _};
use clap::parser::ValueSource;
use clap::{
    ArgAction, ArgMatches, Args, CommandFactory as _, FromArgMatches as _, Parser, Subcommand,
};
use rand::SeedableRng as _;

use s3res_description::description::{self, HostContext};
use s3res_description::exec;
use s3res_description::plan::SystemPlan;
use s3res_inject::campaign::{self, CampaignRun};
use s3res_inject::classify::{self, ClassifyInfo, ClassifyRun};
use s3res_inject::fault::{check_available, check_reg_options, fire, FaultKind, RegOptions};
use s3res_inject::report::{self, CampaignInfo, CampaignOutput, MachineInfo};
use s3res_inject::schedule::{draw_injection, Arrival, ScheduleParams, VarField, VarSpec};
use s3res_inject::scratch::{check_out, OutKind};
use s3res_inject::stop::StopSignals;
use s3res_inject::storm::{self, StormOptions};
use s3res_inject::target::{resolve, Pick, Target};
use s3res_protocol::live::LiveView;

const BOOTSTRAP_BIN: &str = "s3res-bootstrap";
/// Overrides where s3res-bootstrap is taken from.
const BOOTSTRAP_ENV: &str = "S3RES_BOOTSTRAP";

const LONG_ABOUT: &str = "\
Inject faults into s3res systems and measure what the voters make of them.

Fault kinds (--fault):
  exec  execution error: SIGKILL to the process
  sdc   silent data corruption: replica-rt flips one bit of the next frame the process sends
        (SIGUSR2, sigqueue value = the bit, reduced modulo the frame's bits)
  cfe   control-flow error: replica-rt makes the process spin forever (signal 36, glibc's SIGRTMIN+2)
  var   variable-level flip: chosen bits at a chosen byte offset of the next frame
        (--var-offset, --var-field, --var-flips, --var-bits; signal 37, glibc's SIGRTMIN+3)
  reg   register bit flip through ptrace (provided by the s3res-regflip crate)
  mixed exec, sdc or cfe, drawn for each injection, equally likely (campaign and inject;
        each injection's record says which it was)
  none  nothing (campaign baseline: false positives and task success without faults)

Targets are found in bootstrap's live view (s3res-bootstrap --state FILE), never by name
matching: each component's pid, or its voter's pid and each replica slot's current pid.

Subcommands:
  inject    one injection into a running system
  campaign  run a system N times with injections; tables of detection, recovery, errors
  classify  run a system once clean and N times with one injection; benign/SDC/crash/hang
  merge     combine the outputs of campaign shards (--shard K/N) or several campaigns
  storm     faults into a running system for as long as it runs (what a description's
            `inject` starts)

The guide, the matching rule and a Slurm example: docs/campaigns.md.";

const AFTER_LONG_HELP: &str = "\
Exit status: 0 done; 1 failed or refused (a value out of range, options of another fault kind,
a folder in use, a run that never started: the reason on stderr); 2 a command line the parser
cannot read (an unknown option, a missing value, options that exclude each other); 130/143 stopped by
SIGINT/SIGTERM (the run in progress is stopped and discarded; completed runs are written, and
`campaign --resume` with the same command runs the rest). If s3res-inject is killed outright
(SIGKILL), the system it was running dies with it, and the run's temporary folder (named by a
note OUT/running-…) is removed by the next campaign or classify started on OUT. While one runs,
it holds a lock on OUT (OUT/.s3res-inject.lock), and a second one started on OUT stops.

Environment:
  RUST_LOG         log filter (overrides -v/-q)
  S3RES_BOOTSTRAP  path of s3res-bootstrap (default: beside s3res-inject, then PATH)";

#[derive(Debug, Parser)]
#[command(
    name = "s3res-inject",
    version,
    about = "Inject faults into s3res systems and measure what the voters make of them.",
    long_about = LONG_ABOUT,
    after_long_help = AFTER_LONG_HELP
)]
struct Cli {
    /// More log output (-v debug, -vv trace).
    #[arg(short, long, action = ArgAction::Count, global = true, conflicts_with = "quiet")]
    verbose: u8,
    /// Only warnings and errors.
    #[arg(short, long, global = true)]
    quiet: bool,
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// One injection into a running system; prints one JSON line saying what was done.
    ///
    /// Start the system with `s3res-bootstrap --state state.json system.json`, then e.g.
    ///
    ///     s3res-inject inject --state state.json --component echo --fault sdc
    ///     s3res-inject inject --state state.json --component echo --replica 2 --fault cfe
    ///     s3res-inject inject --state state.json --component echo --fault var \
    ///         --var-offset 8 --var-field exponent --var-flips 2
    #[command(verbatim_doc_comment)]
    Inject(InjectArgs),
    /// Run a system N times with injections and tabulate what the voters made of them.
    ///
    /// Each run starts s3res-bootstrap on the description in a fresh folder (its working
    /// directory: a sink's `--summary task.json` lands there), waits until every target
    /// runs, injects on the seeded schedule for --duration, waits for the end (killing the
    /// run at --run-timeout), then matches every injection with the voters' events.
    ///
    /// Writes into --out: campaign.json (parameters), injections.jsonl (one line per
    /// injection: time, seed, kind, component, replica, pid, outcome, latencies),
    /// runs.jsonl (one line per run: exit, task verdict, false positives), summary.json and
    /// table.md (S³RES Tables 2 and 3 layout). The same seed gives the same schedule of
    /// targets, bits and instants.
    ///
    ///     s3res-inject campaign --system echo-tmr.json --fault exec --rate 2 \
    ///         --runs 100 --seed 1 --out out/tmr-exec --task-summary task.json
    #[command(verbatim_doc_comment)]
    Campaign(CampaignArgs),
    /// Outcome classification without protection (MAVFI Fig. 5): benign / SDC / crash / hang.
    ///
    /// Runs the system once without injection (golden), then --runs times with one injection
    /// at a uniform instant of --duration, and compares each run's output (bootstrap's stdout,
    /// or --output FILE in the run's folder) with the golden one. Writes classify.jsonl (one
    /// line per run, with how many frames and bits differ), classify.json and classify.md.
    ///
    ///     s3res-inject classify --system echo-none.json --components echo --fault sdc \
    ///         --runs 100 --seed 1 --out out/classify-sdc
    ///
    /// A robot's output differs from run to run without a fault (it runs in closed loop with
    /// its simulator): classify it by the mission summary its simulator writes instead. Goal
    /// = benign, collision = SDC, time limit = hang, aborted = crash; classify.json also
    /// counts the successful missions and their times:
    ///
    ///     s3res-inject classify --system examples/robot/campaign/none-classify.json \
    ///         --components navigator --fault reg --reg-bits 3 --duration 4 \
    ///         --run-timeout 30 --mission mission.json --runs 1000 --seed 1 \
    ///         --out out/classify-nav-reg3
    ///
    /// --shard K/N, --resume and `merge` work as for a campaign.
    #[command(verbatim_doc_comment)]
    Classify(ClassifyArgs),
    /// Combine campaign outputs: shards of one campaign become the whole campaign; different
    /// campaigns become rows of one table. Shards of one classification (`classify --shard`)
    /// become the whole classification.
    ///
    ///     s3res-inject merge --out out/all out/shard-*
    #[command(verbatim_doc_comment)]
    Merge(MergeArgs),
    /// Inject a seeded mix of faults into a running system until it stops (or SIGTERM).
    ///
    /// Waits until every target runs, then injects at --rate (Poisson arrivals), each time a
    /// kind drawn from --faults and a target drawn from --components, one fault at a time per
    /// component (a component with a replica still being replaced is skipped: missed). Each
    /// injection is one JSON line in --log (as `inject` prints it, with `index`, and `miss`
    /// when not delivered). bootstrap starts it for a description with `inject`:
    ///
    ///     s3res-inject storm --state state.json --faults exec,sdc,cfe --rate 2 --seed 1 \
    ///         --log injections.jsonl
    #[command(verbatim_doc_comment)]
    Storm(StormArgs),
}

#[derive(Debug, Args)]
struct StormArgs {
    /// The live view written by `s3res-bootstrap --state FILE`.
    #[arg(long, value_name = "FILE")]
    state: PathBuf,
    /// Fault kinds to mix, comma-separated, each equally likely.
    #[arg(
        long,
        value_enum,
        value_delimiter = ',',
        default_value = "exec,sdc,cfe"
    )]
    faults: Vec<FaultKind>,
    /// Injections per second (Poisson arrivals).
    #[arg(long, value_name = "HZ", default_value_t = 2.0)]
    rate: f64,
    /// Seed of the arrivals, kinds and targets: the same seed, the same storm.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Components to inject into, comma-separated (default: every protected component).
    #[arg(long, value_name = "LIST", value_delimiter = ',')]
    components: Option<Vec<String>>,
    /// Seconds to wait after every target runs before the first injection.
    #[arg(long, value_name = "SECS", default_value_t = 1.0)]
    after: f64,
    /// Seconds after an injection into a component before the next one into it (a fault not
    /// yet detected does not show in the live view; two at once are beyond what TMR masks).
    #[arg(long, value_name = "SECS", default_value_t = 0.5)]
    settle: f64,
    /// Write the injections here (JSON lines) instead of stdout.
    #[arg(long, value_name = "FILE")]
    log: Option<PathBuf>,
    #[command(flatten)]
    var: VarArgs,
    #[command(flatten)]
    reg: RegArgs,
}

#[derive(Debug, Args)]
struct VarArgs {
    /// var: byte offset of the value in the frame's payload.
    #[arg(long, value_name = "BYTE", default_value_t = 0)]
    var_offset: u32,
    /// var: which bits of the little-endian 64-bit value at the offset may flip
    /// (an f64: sign = bit 63, exponent = 52..63, mantissa = 0..52; byte = the byte only).
    #[arg(long, value_enum, default_value_t = VarField::Whole)]
    var_field: VarField,
    /// var: how many distinct bits of the field each injection flips (chosen by the seed).
    #[arg(long, value_name = "K", default_value_t = 1)]
    var_flips: u32,
    /// var: flip exactly these bits (relative to the offset), e.g. 52,62; overrides the field.
    #[arg(long, value_name = "LIST", value_delimiter = ',')]
    var_bits: Option<Vec<u32>>,
}

impl VarArgs {
    fn spec(&self) -> anyhow::Result<VarSpec> {
        let spec = VarSpec {
            offset: self.var_offset,
            field: self.var_field,
            flips: self.var_flips,
            bits: self.var_bits.clone(),
        };
        spec.validate().map_err(anyhow::Error::msg)?;
        Ok(spec)
    }
}

#[derive(Debug, Args)]
struct RegArgs {
    /// reg: which operand of the interrupted instruction: source, destination or any.
    #[arg(long, value_name = "ROLE", default_value = "any")]
    reg_role: String,
    /// reg: bits flipped per injection.
    #[arg(long, value_name = "N", default_value_t = 1)]
    reg_bits: u32,
    /// reg: part of a floating-point register: whole, sign, exponent, mantissa.
    #[arg(long, value_name = "FIELD", default_value = "whole")]
    reg_field: String,
    /// reg: only these registers (comma-separated).
    #[arg(long, value_name = "LIST", value_delimiter = ',')]
    reg_registers: Option<Vec<String>>,
}

impl RegArgs {
    fn options(&self) -> RegOptions {
        RegOptions {
            role: self.reg_role.clone(),
            bits: self.reg_bits,
            field: self.reg_field.clone(),
            registers: self.reg_registers.clone(),
        }
    }
}

#[derive(Debug, Args)]
struct InjectArgs {
    /// The live view written by `s3res-bootstrap --state FILE`.
    #[arg(long, value_name = "FILE")]
    state: PathBuf,
    /// Component to inject into.
    #[arg(long)]
    component: String,
    /// Replica slot (protected components); default: chosen with --pick.
    #[arg(long, value_name = "SLOT", conflicts_with = "pid")]
    replica: Option<usize>,
    /// Inject into this pid instead (it must be in the live view).
    #[arg(long)]
    pid: Option<i32>,
    #[arg(long, value_enum)]
    fault: FaultKind,
    /// sdc: the bit to flip (default: chosen by the seed).
    #[arg(long)]
    bit: Option<u32>,
    /// Seed for every random choice (default: from the clock; printed in the record).
    #[arg(long)]
    seed: Option<u64>,
    #[arg(long, value_enum, default_value_t = Pick::Uniform)]
    pick: Pick,
    #[command(flatten)]
    var: VarArgs,
    #[command(flatten)]
    reg: RegArgs,
}

#[derive(Debug, Args)]
struct CampaignArgs {
    /// The system description to run.
    #[arg(long, value_name = "S.json")]
    system: PathBuf,
    #[arg(long, value_enum)]
    fault: FaultKind,
    /// Injections per second during each run's window (S³RES used 2).
    #[arg(long, value_name = "HZ", default_value_t = 2.0)]
    rate: f64,
    /// Inter-arrival times: exponential (Poisson process) or fixed.
    #[arg(long, value_enum, default_value_t = Arrival::Exponential)]
    arrival: Arrival,
    /// Injection window of each run, from the moment every target runs, in seconds. Keep it
    /// shorter than the system's own run.
    #[arg(long, value_name = "SECS", default_value_t = 3.0)]
    duration: f64,
    /// Number of runs (of the whole campaign; a shard does its slice).
    #[arg(long)]
    runs: u64,
    /// Seed of every run's schedule (instants, targets, bits): the same seed, the same
    /// campaign; run r's schedule depends on the seed and r only, whatever the sharding.
    #[arg(long)]
    seed: u64,
    /// Output folder (new or empty; see --resume).
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
    /// If --out already holds this campaign (one stopped by a signal, a kill, a time limit),
    /// keep its completed runs and do only the missing ones, then write the tables as an
    /// uninterrupted campaign would. The parameters must be the same (give the same command).
    /// If --out holds no campaign, start one.
    #[arg(long)]
    resume: bool,
    /// Components to inject into, comma-separated (default: every protected component).
    #[arg(long, value_name = "LIST", value_delimiter = ',')]
    components: Option<Vec<String>>,
    /// How a replica is chosen: uniform over the slots, or weighted by CPU time.
    #[arg(long, value_enum, default_value_t = Pick::Uniform)]
    pick: Pick,
    /// Do runs r with r % N == K-1 only (K in 1..=N), for job arrays; `merge` joins shards.
    #[arg(long, value_name = "K/N", value_parser = parse_shard)]
    shard: Option<(u64, u64)>,
    /// Row label in the tables (default: the targets' redundancy, e.g. tmr).
    #[arg(long)]
    label: Option<String>,
    /// JSON file the task writes in its run folder with an `ok` field (e.g. the sink's
    /// --summary task.json); a run succeeds only if it says ok (missing = failed).
    #[arg(long, value_name = "FILE")]
    task_summary: Option<String>,
    /// A fault event counts as an injection's consequence only this long after it.
    #[arg(long, value_name = "MS", default_value_t = 2000)]
    match_window_ms: u64,
    /// A run longer than this is killed and counts as failed.
    #[arg(long, value_name = "SECS", default_value_t = 120.0)]
    run_timeout: f64,
    /// Keep each run's folder (events, state, stdout, stderr) under OUT/runs/.
    #[arg(long)]
    keep_runs: bool,
    #[command(flatten)]
    var: VarArgs,
    #[command(flatten)]
    reg: RegArgs,
}

#[derive(Debug, Args)]
struct ClassifyArgs {
    /// The system description to run (unprotected or protected).
    #[arg(long, value_name = "S.json")]
    system: PathBuf,
    #[arg(long, value_enum)]
    fault: FaultKind,
    /// Number of runs, each with one injection (plus the golden run).
    #[arg(long)]
    runs: u64,
    /// Seed of every run's instant, target and bits: the same seed, the same runs.
    #[arg(long)]
    seed: u64,
    /// Output folder (new or empty; see --resume).
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
    /// Components to inject into, comma-separated (default: every component).
    #[arg(long, value_name = "LIST", value_delimiter = ',')]
    components: Option<Vec<String>>,
    /// The injection instant is uniform in this many seconds after every target runs.
    #[arg(long, value_name = "SECS", default_value_t = 1.0)]
    duration: f64,
    /// What is compared with the golden run: `stdout` (bootstrap's) or a file the system
    /// writes in its run folder.
    #[arg(long, value_name = "FILE", default_value = "stdout")]
    output: String,
    /// Classify by the mission summary the system writes in its run folder (JSON with
    /// `success` and `outcome`, as `s3res-sim --summary FILE`), not by --output.
    #[arg(long, value_name = "FILE", conflicts_with = "output")]
    mission: Option<String>,
    /// A run longer than this is killed and classified as a hang.
    #[arg(long, value_name = "SECS", default_value_t = 30.0)]
    run_timeout: f64,
    #[arg(long, value_enum, default_value_t = Pick::Uniform)]
    pick: Pick,
    /// Do runs r with r % N == K-1 only (K in 1..=N), for job arrays; `merge` joins shards.
    #[arg(long, value_name = "K/N", value_parser = parse_shard)]
    shard: Option<(u64, u64)>,
    /// Finish the classification --out holds (the same command): keep its golden run and
    /// completed runs, run the missing ones. If --out holds none, start one.
    #[arg(long)]
    resume: bool,
    #[command(flatten)]
    var: VarArgs,
    #[command(flatten)]
    reg: RegArgs,
}

#[derive(Debug, Args)]
struct MergeArgs {
    /// Output folder (new or empty).
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
    /// Campaign output folders (shards or whole campaigns), or the shards of one
    /// classification.
    #[arg(value_name = "DIR", required = true)]
    inputs: Vec<PathBuf>,
}

fn parse_shard(s: &str) -> Result<(u64, u64), String> {
    let (k, n) = s
        .split_once('/')
        .ok_or_else(|| format!("`{s}` is not K/N (e.g. 3/10)"))?;
    let k: u64 = k
        .trim()
        .parse()
        .map_err(|_| format!("`{k}` is not a number"))?;
    let n: u64 = n
        .trim()
        .parse()
        .map_err(|_| format!("`{n}` is not a number"))?;
    if n == 0 || k == 0 || k > n {
        return Err(format!("shard {k}/{n}: K must be in 1..={n}"));
    }
    Ok((k, n))
}

fn seconds(what: &str, s: f64) -> anyhow::Result<Duration> {
    Duration::try_from_secs_f64(s)
        // `{:?}`: 1e300 as written, not as three hundred digits.
        .map_err(|_| anyhow::anyhow!("{what} {s:?} is not a duration in seconds"))
}

/// The options of one fault kind given with another (`--reg-bits 4 --fault exec`), which
/// would do nothing: said, not ignored. `None` if every option given applies.
fn options_of_another_kind(command: &Command, matches: &ArgMatches) -> Option<String> {
    let (name, sub) = matches.subcommand()?;
    let kinds: &[FaultKind] = match command {
        Command::Inject(a) => std::slice::from_ref(&a.fault),
        Command::Campaign(a) => std::slice::from_ref(&a.fault),
        Command::Classify(a) => std::slice::from_ref(&a.fault),
        Command::Storm(a) => &a.faults,
        Command::Merge(_) => return None,
    };
    const OPTIONS: [(FaultKind, [&str; 4]); 2] = [
        (
            FaultKind::Reg,
            ["reg_role", "reg_bits", "reg_field", "reg_registers"],
        ),
        (
            FaultKind::Var,
            ["var_offset", "var_field", "var_flips", "var_bits"],
        ),
    ];
    let (kind, id) = OPTIONS
        .iter()
        .filter(|(kind, _)| !kinds.contains(kind))
        .flat_map(|(kind, ids)| ids.iter().map(move |id| (kind, id)))
        .find(|(_, id)| sub.value_source(id) == Some(ValueSource::CommandLine))?;
    let these: Vec<&str> = kinds.iter().map(|k| k.name()).collect();
    Some(format!(
        "--{} applies to {} faults only, and this {name} injects {}: drop it, or choose that \
         kind",
        id.replace('_', "-"),
        kind.name(),
        these.join(", ")
    ))
}

fn main() -> ExitCode {
    let matches = Cli::command().get_matches();
    let cli = match Cli::from_arg_matches(&matches) {
        Ok(cli) => cli,
        Err(e) => e.exit(),
    };
    if let Some(why) = options_of_another_kind(&cli.command, &matches) {
        eprintln!("error: {why}");
        return ExitCode::from(1);
    }
    // Before any thread: SIGINT/SIGTERM are taken through a signalfd, so a long campaign
    // stops its current run cleanly instead of leaving it running.
    let stop = match StopSignals::install() {
        Ok(s) => s,
        Err(e) => {
            eprintln!("error: cannot set up signal handling: {e}");
            return ExitCode::from(1);
        }
    };
    if matches!(cli.command, Command::Storm(_)) {
        // Started beside the components: its lines carry a prefix as theirs do.
        replica_rt::init_logging("injector");
    } else {
        replica_rt::init_cli_logging(cli.quiet, cli.verbose);
    }
    let kind = match &cli.command {
        Command::Inject(a) => Some(a.fault),
        Command::Campaign(a) => Some(a.fault),
        Command::Classify(a) => Some(a.fault),
        Command::Merge(_) => None,
        Command::Storm(a) => a
            .faults
            .iter()
            .copied()
            .find(|f| check_available(*f).is_err()),
    };
    if let Some(Err(e)) = kind.map(check_available) {
        eprintln!("error: {e}");
        return ExitCode::from(1);
    }
    // Register options are refused once, here, not met by every injection of a campaign (each
    // run went ahead and every flip was 'missed', exit 0).
    let reg = match &cli.command {
        Command::Inject(a) => (a.fault == FaultKind::Reg).then_some(&a.reg),
        Command::Campaign(a) => (a.fault == FaultKind::Reg).then_some(&a.reg),
        Command::Classify(a) => (a.fault == FaultKind::Reg).then_some(&a.reg),
        Command::Storm(a) => a.faults.contains(&FaultKind::Reg).then_some(&a.reg),
        Command::Merge(_) => None,
    };
    if let Some(Err(e)) = reg.map(|r| check_reg_options(&r.options())) {
        eprintln!("error: {e}");
        return ExitCode::from(1);
    }
    let res = match &cli.command {
        Command::Inject(a) => cmd_inject(a),
        Command::Campaign(a) => cmd_campaign(a, &stop),
        Command::Classify(a) => cmd_classify(a, &stop),
        Command::Merge(a) => cmd_merge(a),
        Command::Storm(a) => cmd_storm(a, &stop),
    };
    // A storm ends when it is told to: that is its normal end.
    if matches!(cli.command, Command::Storm(_)) && stop.requested().is_some() && res.is_ok() {
        return ExitCode::SUCCESS;
    }
    if let Some(sig) = stop.requested() {
        if let Err(e) = &res {
            eprintln!("error: {}", replica_rt::error_chain(e.as_ref()));
        }
        return ExitCode::from((128 + sig).clamp(0, 255) as u8);
    }
    match res {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {}", replica_rt::error_chain(e.as_ref()));
            ExitCode::from(1)
        }
    }
}

/// `$S3RES_BOOTSTRAP`, else s3res-bootstrap beside us, else on PATH.
fn find_bootstrap() -> anyhow::Result<PathBuf> {
    exec::find_tool(BOOTSTRAP_BIN, BOOTSTRAP_ENV)
        .map_err(|e| anyhow::anyhow!("cannot find {BOOTSTRAP_BIN}: {e}"))
}

fn load_system(path: &Path) -> anyhow::Result<(PathBuf, SystemPlan)> {
    let abs = exec::absolute(path);
    let plan = description::load(&abs, &HostContext::for_file(&abs))
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    Ok((abs, plan))
}

/// The digest of the description at `path` (read again: it was just loaded).
fn system_digest(path: &Path) -> anyhow::Result<String> {
    let text = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    Ok(s3res_protocol::campaign::description_digest(&text))
}

/// The target components: as given (each must exist), else `default`.
fn targets(
    plan: &SystemPlan,
    given: &Option<Vec<String>>,
    default: impl Fn(&SystemPlan) -> Vec<String>,
) -> anyhow::Result<Vec<String>> {
    let list = match given {
        Some(l) => l.clone(),
        None => default(plan),
    };
    for c in &list {
        if !plan.components.iter().any(|p| &p.name == c) {
            let names: Vec<&str> = plan.components.iter().map(|p| p.name.as_str()).collect();
            bail!(
                "--components: system {} has no component `{c}` (it has: {})",
                plan.name,
                names.join(", ")
            );
        }
    }
    if list.is_empty() {
        bail!(
            "system {} has no protected component to inject into; name targets with --components",
            plan.name
        );
    }
    Ok(list)
}

fn cmd_inject(a: &InjectArgs) -> anyhow::Result<()> {
    if a.fault == FaultKind::None {
        bail!("--fault none injects nothing; choose exec, sdc, cfe, var, reg or mixed");
    }
    if a.bit.is_some() && a.fault != FaultKind::Sdc {
        bail!("--bit chooses the bit of an sdc flip; it goes with --fault sdc only");
    }
    let seed = a.seed.unwrap_or_else(replica_rt::sys::monotonic_ns);
    // The request itself first: a wrong one is wrong whatever the system.
    let var = a.var.spec()?;
    let view = LiveView::read(&a.state).map_err(anyhow::Error::msg)?;
    let params = ScheduleParams {
        fault: a.fault,
        rate_hz: 1.0,
        arrival: Arrival::Fixed,
        window: Duration::ZERO,
        components: vec![a.component.clone()],
        var,
    };
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let mut planned = draw_injection(&params, &mut rng, 0, 0).context("nothing to inject")?;
    if let (Some(bit), s3res_inject::fault::Action::Sdc { value }) = (a.bit, &mut planned.action) {
        *value = bit;
    }
    let c = view.components.get(&a.component).with_context(|| {
        let names: Vec<&str> = view.components.keys().map(String::as_str).collect();
        format!(
            "no component `{}` in {} (it has: {})",
            a.component,
            a.state.display(),
            names.join(", ")
        )
    })?;
    let target = match (a.replica, a.pid) {
        (Some(slot), _) => {
            let r = c.replicas.get(slot).with_context(|| {
                if c.protected {
                    format!(
                        "{} has {} replica slot(s); there is no slot {slot}",
                        a.component,
                        c.replicas.len()
                    )
                } else {
                    format!(
                        "{} is not protected: it has no replicas (give --pid, or leave out \
                         --replica to hit the component itself)",
                        a.component
                    )
                }
            })?;
            Target {
                component: a.component.clone(),
                slot: Some(slot),
                pid: r.pid.with_context(|| {
                    format!(
                        "slot {slot} of {} has no process ({:?})",
                        a.component, r.state
                    )
                })?,
            }
        }
        (None, Some(pid)) => {
            let slot = c
                .replicas
                .iter()
                .find(|r| r.pid == Some(pid))
                .map(|r| r.slot);
            if slot.is_none() && c.pid != Some(pid) {
                bail!(
                    "pid {pid} is not a process of {} in {}",
                    a.component,
                    a.state.display()
                );
            }
            Target {
                component: a.component.clone(),
                slot,
                pid,
            }
        }
        (None, None) => resolve(&view, &a.component, planned.draw, a.pick)?,
    };
    let asked = replica_rt::sys::monotonic_ns();
    let injector = fire(&planned.action, target.pid, &a.reg.options())?;
    let mut line = serde_json::json!({
        "ts_ns": s3res_inject::fault::injected_at(asked, injector.as_ref()),
        "seed": seed,
        "system": view.system,
        "component": target.component,
        "replica": target.slot,
        "pid": target.pid,
    });
    if let (Some(obj), serde_json::Value::Object(act)) =
        (line.as_object_mut(), serde_json::to_value(&planned.action)?)
    {
        obj.extend(act);
        if let Some(i) = injector {
            obj.insert("injector".to_owned(), i);
        }
    }
    println!("{line}");
    Ok(())
}

/// The most runs of one campaign or classification (a million runs of a few seconds are a
/// month of one machine): every shard walks the run numbers.
const MAX_RUNS: u64 = 1_000_000;

/// `--rate`: injections per second, above 0 and at most `campaign::MAX_RATE_HZ` (a mistyped
/// 1e9 planned a billion injections into memory).
fn check_rate(rate: f64) -> anyhow::Result<()> {
    s3res_protocol::campaign::check_rate(rate).map_err(|e| anyhow::anyhow!("--rate {e}"))
}

/// `--rate` over `--duration`: a campaign run's schedule is planned whole, at most
/// `campaign::MAX_PLANNED_PER_RUN` injections.
fn check_schedule(rate: f64, duration: f64) -> anyhow::Result<()> {
    let window = seconds("--duration", duration)?;
    s3res_protocol::campaign::check_schedule(rate, window)
        .map_err(|e| anyhow::anyhow!("--rate and --duration: {e}"))
}

/// `--runs`, and `--duration` against `--run-timeout`: each run injects for `duration` and
/// must end within `run_timeout`.
fn check_runs_and_window(runs: u64, duration: f64, run_timeout: f64) -> anyhow::Result<()> {
    if runs == 0 {
        bail!("--runs 0: nothing to do");
    }
    if runs > MAX_RUNS {
        bail!("--runs {runs}: at most {MAX_RUNS} (split it into campaigns of their own seeds)");
    }
    seconds("--duration", duration)?;
    seconds("--run-timeout", run_timeout)?;
    if run_timeout <= duration {
        bail!(
            "--run-timeout {run_timeout} s is not longer than --duration {duration} s: every \
             run would be killed before its injections end (give each run time to start and end)"
        );
    }
    Ok(())
}

/// A file each run writes in its own folder (`--task-summary`, `--output`, `--mission`): a
/// relative path without `..`. An absolute one, or one out of the folder, is the same file for
/// every run (a stale one judged them all).
fn check_in_run_folder(flag: &str, file: Option<&str>) -> anyhow::Result<()> {
    let Some(file) = file else { return Ok(()) };
    let path = Path::new(file);
    if path.is_absolute()
        || path
            .components()
            .any(|c| c == std::path::Component::ParentDir)
    {
        bail!(
            "{flag} {file}: give a file in the run's folder (a relative path without `..`): \
             each run has a folder of its own"
        );
    }
    Ok(())
}

/// `--duration` of a fault kind that injects: a window of 0 s injects nothing (a campaign plans
/// no injection in it, and runs as a baseline would, under the fault's name).
fn check_window(fault: FaultKind, duration: f64) -> anyhow::Result<()> {
    if fault != FaultKind::None && duration == 0.0 {
        bail!(
            "--duration 0: a window of 0 s leaves no time to inject {fault} faults; give the \
             window in seconds (above 0), or --fault none for a baseline"
        );
    }
    Ok(())
}

/// `--components` names each component once: a name given twice drew it twice as often.
fn check_components(given: &Option<Vec<String>>) -> anyhow::Result<()> {
    let mut seen = std::collections::BTreeSet::new();
    if let Some(twice) = given.iter().flatten().find(|c| !seen.insert(c.as_str())) {
        bail!(
            "--components names {twice} twice: each name given is drawn equally often; name \
             each component once"
        );
    }
    Ok(())
}

fn cmd_campaign(a: &CampaignArgs, stop: &StopSignals) -> anyhow::Result<()> {
    check_runs_and_window(a.runs, a.duration, a.run_timeout)?;
    check_window(a.fault, a.duration)?;
    check_components(&a.components)?;
    if a.match_window_ms == 0 {
        bail!(
            "--match-window-ms 0: no fault event can follow an injection within 0 ms, so every \
             detected fault would count as a false positive and its injection as benign; give \
             the window in ms (default 2000)"
        );
    }
    check_in_run_folder("--task-summary", a.task_summary.as_deref())?;
    if a.fault != FaultKind::None {
        check_rate(a.rate)?;
        check_schedule(a.rate, a.duration)?;
    }
    let var = a.var.spec()?;
    check_out(&a.out, OutKind::Campaign)?;
    let (system, plan) = load_system(&a.system)?;
    let components = targets(&plan, &a.components, |p| {
        p.components
            .iter()
            .filter(|c| c.is_protected())
            .map(|c| c.name.clone())
            .collect()
    })?;
    let redundancy: BTreeMap<String, String> = plan
        .components
        .iter()
        .map(|c| (c.name.clone(), c.redundancy.to_string()))
        .collect();
    let config = a.label.clone().unwrap_or_else(|| {
        let mut levels: Vec<&str> = components.iter().map(|c| redundancy[c].as_str()).collect();
        levels.dedup();
        if levels.len() == 1 {
            levels[0].to_owned()
        } else {
            components
                .iter()
                .map(|c| format!("{c}={}", redundancy[c]))
                .collect::<Vec<_>>()
                .join(",")
        }
    });
    let info = CampaignInfo {
        config,
        system_digest: Some(system_digest(&system)?),
        system,
        system_name: plan.name.clone(),
        fault: a.fault,
        rate_hz: a.rate,
        arrival: a.arrival,
        window_ms: seconds("--duration", a.duration)?.as_millis() as u64,
        runs: a.runs,
        seed: a.seed,
        shard: a.shard,
        pick: a.pick,
        components,
        var,
        reg: a.reg.options(),
        match_window_ms: a.match_window_ms,
        run_limit_ms: seconds("--run-timeout", a.run_timeout)?.as_millis() as u64,
        task_summary: a.task_summary.clone(),
        redundancy,
        machine: None,
    };
    let bootstrap = find_bootstrap()?;
    let mut run = CampaignRun {
        info,
        bootstrap,
        // Absolute: each run's bootstrap works in its own folder and is given paths inside OUT.
        out: exec::absolute(&a.out),
        keep_runs: a.keep_runs,
        resume: a.resume,
        ready_limit: Duration::from_secs(30),
    };
    run.info.machine = Some(MachineInfo::probe(&run.bootstrap));
    eprintln!(
        "s3res-inject: campaign {} {} on {}: {} run(s){}, seed {}",
        run.info.config,
        run.info.fault,
        run.info.system_name,
        s3res_protocol::campaign::runs_in_shard(run.info.shard, run.info.runs),
        a.shard
            .map_or(String::new(), |(k, n)| format!(" (shard {k}/{n})")),
        a.seed
    );
    let (s, _interrupted) = campaign::run(&run, stop)?;
    print!("{}", report::markdown(&[s]));
    eprintln!("s3res-inject: outputs in {}", run.out.display());
    Ok(())
}

fn cmd_classify(a: &ClassifyArgs, stop: &StopSignals) -> anyhow::Result<()> {
    if a.fault == FaultKind::None {
        bail!("--fault none injects nothing; choose exec, sdc, cfe, var or reg");
    }
    if a.fault == FaultKind::Mixed {
        bail!(
            "classify gives each fault kind its own row; run it once per kind (exec, sdc, cfe) \
             instead of --fault mixed"
        );
    }
    check_in_run_folder("--output", Some(&a.output))?;
    check_in_run_folder("--mission", a.mission.as_deref())?;
    check_runs_and_window(a.runs, a.duration, a.run_timeout)?;
    check_window(a.fault, a.duration)?;
    check_components(&a.components)?;
    check_out(&a.out, OutKind::Classification)?;
    let (system, plan) = load_system(&a.system)?;
    let components = targets(&plan, &a.components, |p| {
        p.components.iter().map(|c| c.name.clone()).collect()
    })?;
    let window = seconds("--duration", a.duration)?;
    let limit = seconds("--run-timeout", a.run_timeout)?;
    let c = ClassifyRun {
        info: ClassifyInfo {
            system_digest: Some(system_digest(&system)?),
            system,
            fault: a.fault,
            components,
            seed: a.seed,
            runs: a.runs,
            shard: a.shard,
            window_ms: window.as_millis() as u64,
            output: a.output.clone(),
            mission: a.mission.clone(),
            pick: a.pick,
            var: a.var.spec()?,
            reg: a.reg.options(),
            run_limit_ms: limit.as_millis() as u64,
            golden_mission: None,
        },
        bootstrap: find_bootstrap()?,
        out: exec::absolute(&a.out),
        resume: a.resume,
        ready_limit: Duration::from_secs(30),
    };
    // As a campaign says it: what runs, and the seed that reproduces it.
    eprintln!(
        "s3res-inject: classify {} on {}: {} run(s){}, seed {}",
        c.info.fault,
        c.info.system.display(),
        s3res_protocol::campaign::runs_in_shard(c.info.shard, c.info.runs),
        a.shard
            .map_or(String::new(), |(k, n)| format!(" (shard {k}/{n})")),
        a.seed
    );
    let s = classify::run(&c, stop)?;
    print!("{}", classify::markdown(&[s]));
    eprintln!("s3res-inject: outputs in {}", c.out.display());
    Ok(())
}

fn cmd_storm(a: &StormArgs, stop: &StopSignals) -> anyhow::Result<()> {
    check_rate(a.rate)?;
    check_components(&a.components)?;
    let o = StormOptions {
        state: a.state.clone(),
        faults: a.faults.clone(),
        rate_hz: a.rate,
        seed: a.seed,
        components: a.components.clone().unwrap_or_default(),
        after: seconds("--after", a.after)?,
        settle: seconds("--settle", a.settle)?,
        log: a.log.clone(),
        var: a.var.spec()?,
        reg: a.reg.options(),
    };
    let delivered = storm::run(&o, &|| stop.requested().is_some())?;
    tracing::debug!("storm over: {delivered} injection(s) delivered");
    Ok(())
}

/// `merge` of `classify` folders: the shards of one classification become the whole.
fn merge_classifications(
    a: &MergeArgs,
    parts: Vec<Option<classify::ClassifyOutput>>,
) -> anyhow::Result<()> {
    let parts = parts
        .into_iter()
        .zip(&a.inputs)
        .map(|(p, dir)| match p {
            Some(p) => Ok((dir.clone(), p)),
            None if dir.join("campaign.json").exists() => bail!(
                "{} holds a campaign, the other inputs classifications: the two are merged apart",
                dir.display()
            ),
            None => bail!(
                "{} holds no classification (no classify-run.json: a shard whose golden run \
                 never finished?); leave it out, or run it again with --resume",
                dir.display()
            ),
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    let merged = classify::merge(parts).map_err(anyhow::Error::msg)?;
    if merged.stray > 0 {
        eprintln!(
            "s3res-inject: warning: {} record(s) left out: runs not of their folder's shard",
            merged.stray
        );
    }
    if merged.missing > 0 {
        eprintln!(
            "s3res-inject: warning: the classification has {} of its {} runs (shards missing?)",
            merged.output.info.runs - merged.missing,
            merged.output.info.runs
        );
    }
    std::fs::create_dir_all(&a.out)
        .with_context(|| format!("cannot create the output folder {}", a.out.display()))?;
    let summary = merged.output.write(&a.out)?;
    print!("{}", classify::markdown(&[summary]));
    Ok(())
}

fn cmd_merge(a: &MergeArgs) -> anyhow::Result<()> {
    // Into a new or empty folder only: a campaign's or classification's (running, killed or
    // finished) had its records replaced.
    check_out(&a.out, OutKind::Merge)?;
    let classifications = a
        .inputs
        .iter()
        .map(|d| classify::ClassifyOutput::read(d).map_err(anyhow::Error::msg))
        .collect::<anyhow::Result<Vec<_>>>()?;
    if classifications.iter().any(Option::is_some) {
        return merge_classifications(a, classifications);
    }
    let parts = a
        .inputs
        .iter()
        .map(|d| CampaignOutput::read(d).map_err(anyhow::Error::msg))
        .collect::<anyhow::Result<Vec<_>>>()?;
    let merged = report::merge(parts).map_err(anyhow::Error::msg)?;
    for m in &merged {
        let have = m.runs.len() as u64;
        if have != m.info.runs {
            eprintln!(
                "s3res-inject: warning: campaign {} {} has {have} of its {} runs (shards missing?)",
                m.info.config, m.info.fault, m.info.runs
            );
        }
    }
    let summaries = report::write_outputs(&a.out, &merged)?;
    print!("{}", report::markdown(&summaries));
    Ok(())
}
