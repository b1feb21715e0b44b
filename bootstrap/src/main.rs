//! `s3res-bootstrap [--check] [--events FILE] [--state FILE] [--stop-timeout-ms N] [-v|-q] SYSTEM.json`

#![forbid(unsafe_code)]

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use anyhow::Context as _;
use clap::{ArgAction, Parser};

use s3res_bootstrap::description::{self, HostContext};
use s3res_bootstrap::exec::{self, SearchPath};
use s3res_bootstrap::run::{self, Ending, RunOptions, VOTER_BIN};
use s3res_bootstrap::sched::SystemSched;

/// Overrides where the voter binary is taken from (tests, unusual installs).
const VOTER_ENV: &str = "S3RES_VOTER";

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

Everything is checked before anything starts. On SIGINT/SIGTERM every component gets SIGTERM,
then SIGKILL after --stop-timeout-ms; in every case nothing bootstrap started outlives it.";

const EXIT_STATUSES: &str = "\
Exit status:
  0    every component exited with status 0 (with --check: the description is valid)
  1    a component failed (one line per failure on stderr), or the system could not start
  2    the description is invalid (error: FILE:LINE: what (where)), or bad usage
  130  stopped by SIGINT
  143  stopped by SIGTERM

Environment:
  RUST_LOG     log filter (overrides -v/-q), e.g. RUST_LOG=debug
  S3RES_VOTER  path of the voter binary to use instead of s3res-voter beside bootstrap or on PATH";

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

    /// Append every voter event (one JSON object per line) to FILE, created or truncated at start.
    #[arg(long, value_name = "FILE")]
    events: Option<PathBuf>,

    /// Keep a live view of the running system in FILE (JSON, rewritten atomically on every
    /// replica start, fault and recovery): each component with its pid, or its voter's pid and
    /// the current pid of every replica slot. Fault injectors read it to find their targets
    /// (see docs/campaigns.md).
    #[arg(long, value_name = "FILE")]
    state: Option<PathBuf>,

    /// After SIGTERM to the components, wait this long before SIGKILL.
    #[arg(long, value_name = "N", default_value_t = 2000)]
    stop_timeout_ms: u64,

    /// More log output (-v debug, -vv trace). RUST_LOG, when set, takes precedence.
    #[arg(short, long, action = ArgAction::Count, conflicts_with = "quiet")]
    verbose: u8,

    /// Only warnings and errors.
    #[arg(short, long)]
    quiet: bool,

    /// The system description (JSON).
    #[arg(value_name = "SYSTEM.json")]
    system: PathBuf,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    s3res_bootstrap::logging::init_cli_logging(cli.quiet, cli.verbose);
    match run_cli(&cli) {
        Ok(code) => ExitCode::from(code),
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::from(1)
        }
    }
}

/// The voter binary: `$S3RES_VOTER` if set, else `s3res-voter` beside us or on PATH.
fn find_voter() -> Result<PathBuf, String> {
    let search = SearchPath::from_environment();
    match std::env::var(VOTER_ENV) {
        Ok(path) => {
            let cwd = std::env::current_dir().map_err(|e| format!("no current folder: {e}"))?;
            exec::resolve(&path, &cwd, &search).map_err(|e| format!("{VOTER_ENV}: {e}"))
        }
        Err(_) => search.find(VOTER_BIN),
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
        Some(find_voter().map_err(run::RunError::VoterMissing)?)
    } else {
        None
    };

    if cli.check {
        let sched = SystemSched::for_system(&plan);
        print!("{}", plan.describe(voter.as_deref(), Some(&sched)));
        return Ok(0);
    }

    let opts = RunOptions {
        voter,
        events_file: cli.events.clone(),
        stop_timeout: Duration::from_millis(cli.stop_timeout_ms),
        state_file: cli.state.clone(),
    };
    let report =
        run::run(&plan, &opts).with_context(|| format!("system {} did not run", plan.name))?;

    for f in &report.failures {
        eprintln!(
            "s3res-bootstrap: component {} failed: {}",
            f.component, f.status
        );
    }
    if let Some(events) = &report.events {
        if !cli.quiet {
            eprintln!("s3res-bootstrap: {}", events.line());
        }
    }
    if let Ending::Stopped(sig) = report.ending {
        tracing::info!("stopped by signal {sig}");
    }
    Ok(report.exit_code())
}
