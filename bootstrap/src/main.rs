//! `s3res-bootstrap [--check] [--events FILE] [--state FILE] [--stop-timeout-ms N] [-v|-q] SYSTEM.json`

#![forbid(unsafe_code)]

use std::io::IsTerminal as _;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use anyhow::Context as _;
use clap::{ArgAction, Parser};

use s3res_bootstrap::description::{self, HostContext};
use s3res_bootstrap::exec;
use s3res_bootstrap::run::{self, Ending, RunOptions, VOTER_BIN};
use s3res_bootstrap::sched::SystemSched;
use s3res_bootstrap::status::{read_outcome, ConsoleMode, Verdict};

/// Overrides where the voter binary is taken from (tests, unusual installs).
const VOTER_ENV: &str = "S3RES_VOTER";
/// The injector a description's `inject` runs, and the variable that overrides where it is.
const INJECT_BIN: &str = "s3res-inject";
const INJECT_ENV: &str = "S3RES_INJECT";

const ABOUT: &str = "Start an s3res system from its description, supervise it, stop it cleanly.";

const LONG_ABOUT: &str = "\
Start an s3res system from its description, supervise it, stop it cleanly.

SYSTEM.json names the components and the channels between them:

  {
    \"name\": \"echo-demo\",
    \"components\": {
      \"source\": { \"exec\": \"s3res-source\", \"args\": [\"--count\", \"2000\"] },
      \"echo\":   { \"exec\": \"s3res-echo\", \"redundancy\": \"tmr\", \"timeout_us\": 20000 },
      \"sink\":   { \"exec\": \"s3res-sink\" }
    },
    \"channels\": [
      { \"from\": \"source.out\", \"to\": \"echo.in\" },
      { \"from\": \"echo.out\",   \"to\": \"sink.in\" }
    ]
  }

A component with redundancy smr, dmr or tmr (1, 2 or 3 replicas, or `replicas`: N) runs under
one s3res-voter; with none (the default) it runs directly. Each channel is one pipe of frames
from `component.port` to `component.port`; `stdin` may be a `from` and `stdout` a `to` (then
bootstrap's own stdin/stdout carry the frames, and components' text output goes to stderr).
A bare `exec` name is looked for beside s3res-bootstrap, then on PATH; a name with a `/` is
relative to the description's folder. Every field, default and rule is in
docs/system-description.md.

`priority` (SCHED_RR 1-99), `cpus`, `voter_cpu` and `schedule` (auto, parallel, sequential)
place each process; --check prints the priority and CPU every process will get. Without the
privilege for SCHED_RR (root or CAP_SYS_NICE), bootstrap says so once and keeps the order with
nice values. See docs/real-time.md.

`inject` (faults while the system runs: exec, sdc, cfe at rate_hz, seeded) starts s3res-inject
beside the components; --no-inject leaves it out. `events`, `state` and `outcome` name the
events file, the live view and the file a component writes its verdict to.

While the system runs, a status line (on a terminal; otherwise a line every 5 s) shows the
time, faults/recoveries per protected component and degraded components; at the end a verdict
block shows the outcome, faults by kind, recoveries by method, withheld frames, what the
injector did, false positives and where the files are (-q: neither).

A voter that dies, or stands still past its heartbeat deadline, is replaced by one that adopts
its replicas (every protected component, reactive or stream, replica-rt, C or unmodified; at
most max_restarts within restart_window_ms): no frame is lost or repeated, the replicas keep
their state.

Everything is checked before anything starts. On SIGINT/SIGTERM/SIGHUP/SIGQUIT every component
gets SIGTERM (it may catch it to finish its work), then SIGKILL after --stop-timeout-ms, and
whatever is left below bootstrap is killed; a second stop signal kills at once (one within
250 ms of the first is taken for a copy of it, as a wrapper like timeout(1) forwards it). Components start with SIGHUP, SIGINT and SIGQUIT
blocked: a terminal sends those to bootstrap and everything it started, and bootstrap stops the
system in order. A SIGKILLed bootstrap cannot: the kernel then kills its own children (voters
stop their replicas), and bootstrap's keeper (a second process, s3res-keeper, that waits for
it) kills every process the system started, voters and replicas included, found by the
S3RES_SYSTEM_MARK variable they inherit; a process that cleared or rewrote its environment, or
whose environment it may not read (set-uid), escapes it.";

const EXIT_STATUSES: &str = "\
Exit status:
  0    every component exited with status 0 (with --check: the description is valid)
  1    a component failed (one line per failure on stderr), or the system could not start
  2    the description is invalid (error: FILE:LINE: what (where)), or bad usage
  128+N stopped by signal N: 129 SIGHUP, 130 SIGINT, 131 SIGQUIT, 143 SIGTERM

Environment:
  RUST_LOG      log filter (overrides -v/-q), e.g. RUST_LOG=debug; every process inherits it
  S3RES_VOTER   path of the voter binary to use instead of s3res-voter beside bootstrap or on PATH
  S3RES_INJECT  path of the injector (`inject` in the description) instead of s3res-inject";

#[derive(Debug, Parser)]
#[command(
    name = "s3res-bootstrap",
    version,
    about = ABOUT,
    long_about = LONG_ABOUT,
    after_help = "Run with --help for the description format and exit statuses.",
    after_long_help = EXIT_STATUSES
)]
struct Cli {
    /// Validate the description and print the plan, without starting anything.
    #[arg(long)]
    check: bool,

    /// Write every voter event to FILE, one JSON object per line; FILE is created, or emptied
    /// if it exists, at start. Default: the description's `events`, if it names one.
    #[arg(long, value_name = "FILE")]
    events: Option<PathBuf>,

    /// Keep a live view of the running system in FILE (JSON, rewritten atomically on every
    /// replica start, fault and recovery): each component with its pid, or its voter's pid and
    /// the current pid of every replica slot. Fault injectors read it to find their targets
    /// (see docs/campaigns.md). Default: the description's `state`, if it names one.
    #[arg(long, value_name = "FILE")]
    state: Option<PathBuf>,

    /// Run without the description's injector (`inject`): the same system, fault-free.
    #[arg(long)]
    no_inject: bool,

    /// After SIGTERM to the components, wait this long before SIGKILL.
    #[arg(long, value_name = "N", default_value_t = 2000)]
    stop_timeout_ms: u64,

    /// More log output (-v debug, -vv trace), from bootstrap and every process it starts.
    /// RUST_LOG, when set, takes precedence.
    #[arg(short, long, action = ArgAction::Count, conflicts_with = "quiet")]
    verbose: u8,

    /// Only warnings and errors, from bootstrap and every process it starts; no live status
    /// and no verdict.
    #[arg(short, long)]
    quiet: bool,

    /// The system description (JSON).
    #[arg(value_name = "SYSTEM.json")]
    system: PathBuf,
}

fn main() -> ExitCode {
    // Started by a bootstrap as its keeper (`keeper.rs`), not by a user.
    if let Some(mark) = std::env::var_os(s3res_bootstrap::keeper::ENV_KEEPER_OF) {
        s3res_bootstrap::keeper::keep(&mark.to_string_lossy());
        return ExitCode::SUCCESS;
    }
    let cli = Cli::parse();
    s3res_bootstrap::logging::init_status_logging(cli.quiet, cli.verbose);
    match run_cli(&cli) {
        Ok(code) => ExitCode::from(code),
        Err(e) => {
            eprintln!(
                "error: {}",
                s3res_bootstrap::logging::error_chain(e.as_ref())
            );
            ExitCode::from(1)
        }
    }
}

/// Whether `a` and `b` name one existing file.
fn same_file(a: &std::path::Path, b: &std::path::Path) -> bool {
    use std::os::unix::fs::MetadataExt;
    match (std::fs::metadata(a), std::fs::metadata(b)) {
        (Ok(a), Ok(b)) => (a.dev(), a.ino()) == (b.dev(), b.ino()),
        _ => false,
    }
}

/// `RUST_LOG` for the processes bootstrap starts: its own level, unless `RUST_LOG` is set
/// (then they inherit it) or the level is the default.
fn child_log(quiet: bool, verbose: u8) -> Option<String> {
    if std::env::var_os("RUST_LOG").is_some() {
        return None;
    }
    match (quiet, verbose) {
        (true, _) => Some("warn".to_owned()),
        (false, 0) => None,
        (false, 1) => Some("debug".to_owned()),
        (false, _) => Some("trace".to_owned()),
    }
}

/// Exit code on success paths; `Err` is a failure to start (exit 1).
fn run_cli(cli: &Cli) -> anyhow::Result<u8> {
    let ctx = HostContext::for_file(&cli.system);
    let plan = match description::load(&cli.system, &ctx) {
        Ok(p) => p,
        Err(e) => {
            eprintln!("error: {e}");
            return Ok(2);
        }
    };
    for w in &plan.warnings {
        tracing::warn!("{w}");
    }
    let voter = if plan.has_protected() {
        Some(exec::find_tool(VOTER_BIN, VOTER_ENV).map_err(run::RunError::VoterMissing)?)
    } else {
        None
    };

    if cli.check {
        let sched = SystemSched::for_system(&plan);
        print!("{}", plan.describe(voter.as_deref(), Some(&sched)));
        if let Some(note) = s3res_bootstrap::run::memory_lock_note(&plan) {
            println!("\n{note}");
        }
        return Ok(0);
    }

    let injector = match &plan.inject {
        Some(_) if !cli.no_inject => {
            Some(exec::find_tool(INJECT_BIN, INJECT_ENV).map_err(|e| {
                anyhow::anyhow!(
                    "the description injects faults (`inject`) but `{INJECT_BIN}` was not found \
                 ({e}); build it, or run without faults: --no-inject"
                )
            })?)
        }
        _ => None,
    };
    let console = if cli.quiet {
        ConsoleMode::Off
    } else if std::io::stderr().is_terminal() {
        ConsoleMode::Terminal
    } else {
        ConsoleMode::Plain
    };
    let opts = RunOptions {
        voter,
        events_file: cli.events.clone().or_else(|| plan.events.clone()),
        stop_timeout: Duration::from_millis(cli.stop_timeout_ms),
        state_file: cli.state.clone().or_else(|| plan.state.clone()),
        injector,
        console,
        child_log: child_log(cli.quiet, cli.verbose),
        keeper: std::env::current_exe().ok(),
    };
    // `--events system.json` would empty the description it was read from.
    for (what, path) in [("events", &opts.events_file), ("state", &opts.state_file)] {
        let Some(path) = path.as_deref() else {
            continue;
        };
        if same_file(path, &cli.system) {
            eprintln!(
                "error: the {what} file {} is the description itself; name another",
                cli.system.display()
            );
            return Ok(2);
        }
        // The description's own paths were checked with it; the command line's are here.
        let example = if what == "events" {
            "events.jsonl"
        } else {
            "state.json"
        };
        if let Some(why) = s3res_description::exec::not_a_file_path(path, example) {
            eprintln!("error: the {what} file: {why}");
            return Ok(2);
        }
    }
    let report =
        run::run(&plan, &opts).with_context(|| format!("system {} did not run", plan.name))?;

    for f in &report.failures {
        s3res_bootstrap::logging::say(&format!(
            "component {} failed: {}",
            f.component,
            f.described()
        ));
    }
    if let Some(events) = report.events.as_ref().filter(|e| e.unparsable > 0) {
        tracing::warn!("{} event line(s) could not be read", events.unparsable);
    }
    if let Ending::Stopped(sig) = report.ending {
        tracing::info!("stopped by signal {sig}");
    }
    if !cli.quiet {
        let verdict = Verdict {
            system: plan.name.clone(),
            elapsed: report.elapsed,
            exit_code: report.exit_code(),
            failures: report.failures.iter().map(|f| f.to_string()).collect(),
            outcome: plan.outcome.as_deref().map(read_outcome),
            tally: report.tally.clone(),
            injections: report.injections.clone(),
            files: report.files.clone(),
            protected: plan
                .components
                .iter()
                .filter(|c| c.is_protected())
                .map(|c| (c.name.clone(), c.replicas))
                .collect(),
        };
        eprint!("{}", verdict.render());
    }
    Ok(report.exit_code())
}
