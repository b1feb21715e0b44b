//! `s3res-bench`: what redundancy costs. See `--help` and docs/benchmarks.md.

mod detect;
mod echo;
mod elf;
mod frames;
mod memory;
mod plot;
mod report;
mod restart;
mod sys;
mod system;

use std::io::IsTerminal;
use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{bail, Context, Result};
use clap::{Args, Parser, Subcommand};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use s3res_protocol::plan::{CpuIdle, LockMemory, CPU_LATENCY_QOS};

use crate::system::{Bins, Setup};

const LONG_ABOUT: &str = "\
Measure what s3res redundancy costs, side by side with the no-voter baseline, in one run.

  echo     round trip of a frame through s3res-echo: no voter (0) and under s3res-voter with
           1 (SMR), 2 (DMR) or 3 (TMR) replicas, for each frame size (the S³RES paper's Fig. 3)
  restart  a TMR ballast component of each state size loses a replica; time from the voter's
           detection to the new replica ready, next to the floor: fork + touching every page
           of the same size in the bench itself (Fig. 4)
  detect   death → `crash` event and deadline → `hang` event, at 2 ms and 20 ms round timeouts;
           fault events in fault-free TMR rounds at 2 ms (false positives)
  memory   resident size of an idle voter and of replica-rt components beyond their state

The bench starts s3res-voter the way s3res-bootstrap does and holds the voter's input and
output pipes itself (no relay). Executables are taken from the bench's own folder (build with
`cargo build --release` and run target/release/s3res-bench) or from --bin-dir.

Each subcommand prints a table, or with --json one JSON object per configuration per line
(keys: bench, replicas, size, count, median_us, p99_us, p999_us, max_us, setup, and where
they apply what, timeout_us, floor_us, ratio, faults, extra). --plot DIR writes SVG plots.
Everything the bench starts runs in its own process group and is killed and reaped on exit,
on error, and on Ctrl-C.

Benchmarks measure wall-clock time: run them on a quiet machine (check `uptime`).";

#[derive(Parser)]
#[command(name = "s3res-bench", version, about = "Measure what s3res redundancy costs", long_about = LONG_ABOUT)]
struct Cli {
    #[command(subcommand)]
    command: Command,
    #[command(flatten)]
    common: CommonArgs,
}

#[derive(Args)]
struct CommonArgs {
    /// One JSON object per configuration per line on stdout, instead of a table.
    #[arg(long, global = true)]
    json: bool,
    /// Write SVG plots into DIR (created if missing): echo writes fig3-round-trip.svg,
    /// restart fig4-restart.svg.
    #[arg(long, value_name = "DIR", global = true)]
    plot: Option<PathBuf>,
    /// Folder of the s3res executables (default: the folder of s3res-bench).
    #[arg(long, value_name = "DIR", global = true)]
    bin_dir: Option<PathBuf>,
    /// Folder of the measured components, s3res-echo and s3res-ballast (default: the
    /// --bin-dir folder): to measure another build of them, such as a statically linked one
    /// (docs/writing-a-component.md, "Statically linked"). Rows measured with statically
    /// linked components carry `"linking": "static"`.
    #[arg(long, value_name = "DIR", global = true)]
    component_dir: Option<PathBuf>,
    /// No progress bar.
    #[arg(long, short, global = true)]
    quiet: bool,
    /// Run the voter without its journal (what a successor needs when the voter dies; on by
    /// default, as s3res-bootstrap runs a reactive component): to measure what it costs.
    #[arg(long, global = true)]
    no_journal: bool,
    /// How much of its memory each replica locks: `all` (every page of the binary and its
    /// libraries, populated at start: the default, as in a system description) or `used` (the
    /// pages it touches, locked on fault): to measure what either costs.
    #[arg(long, global = true, value_name = "all|used", default_value = "all", value_parser = parse_lock_memory)]
    lock_memory: LockMemory,
    /// What idle CPUs do while a voter runs: `halt` (the kernel's choice: the default, as in a
    /// system description) or `poll` (the voters keep every CPU polling when idle, as a
    /// component's `cpu_idle: poll` does; needs root): to measure what a wake-up from idle
    /// costs. Rows without a voter (`--replicas 0`) run without the request either way.
    #[arg(long, global = true, value_name = "halt|poll", default_value = "halt", value_parser = parse_cpu_idle)]
    cpu_idle: CpuIdle,
    /// How long a voter pinned apart from its replicas (`--setup rr-pinned`) may spin for an
    /// answer before it sleeps, µs, as a component's `spin_us` (0: never; the default is a
    /// system description's). Other setups never spin.
    #[arg(long, global = true, value_name = "US", default_value_t = s3res_protocol::plan::DEFAULT_SPIN_US,
          value_parser = clap::value_parser!(u32).range(0..=i64::from(s3res_protocol::plan::MAX_SPIN_US)))]
    spin_us: u32,
}

fn parse_cpu_idle(s: &str) -> Result<CpuIdle, String> {
    CpuIdle::parse(s).ok_or_else(|| format!("`{s}` is neither `halt` nor `poll`"))
}

/// `--timeout-us`: a voter's round deadline, within the bounds of a description's
/// `timeout_us` (0 was passed on, and the run failed on 'the voter's events pipe closed').
fn timeout_us() -> clap::builder::RangedU64ValueParser<u64> {
    let max = s3res_description::description::MAX_DURATION_MS * 1000;
    clap::value_parser!(u64).range(1..=max)
}

fn parse_lock_memory(s: &str) -> Result<LockMemory, String> {
    LockMemory::parse(s).ok_or_else(|| format!("`{s}` is neither `all` nor `used`"))
}

#[derive(Subcommand)]
enum Command {
    /// Round trip by replication level and frame size (Figure 3).
    Echo {
        /// The echo measured: `linked` (s3res-echo, linked to replica-rt), `preload-frames`
        /// (`cat`, unmodified, preloaded, s3res frames on stdin/stdout) or `preload-lines`
        /// (`cat`, preloaded, one line per frame: payloads are printable, no newline).
        #[arg(long, value_enum, default_value = "linked")]
        program: echo::Program,
        /// Replication levels: 0 = no voter, 1 SMR, 2 DMR, 3 TMR (or more).
        #[arg(long, value_delimiter = ',', default_value = "0,1,2,3")]
        replicas: Vec<usize>,
        /// Frame payload sizes in bytes (suffixes k, m allowed: 4k = 4096).
        #[arg(long, value_delimiter = ',', value_parser = parse_frame_size,
              default_value = "8,64,512,1024,2048,4096,65536")]
        size: Vec<u64>,
        /// Round trips measured per configuration.
        #[arg(long, default_value_t = 20_000)]
        count: u64,
        /// Round trips before measuring (caches, page faults, scheduler).
        #[arg(long, default_value_t = 2_000)]
        warmup: u64,
        /// Round deadline of the voter, µs (1 to 60,000,000, as a description's `timeout_us`).
        #[arg(long, default_value_t = 20_000, value_parser = timeout_us())]
        timeout_us: u64,
        /// How processes are scheduled: plain (default scheduler), rr (SCHED_RR: bench and voter
        /// 60, replicas below), rr-pinned (rr, bench and voter on CPU 0, the rest on CPU 1),
        /// one-cpu (default scheduler, everything on CPU 0), rr-one-cpu (rr, everything on CPU
        /// 0, the replicas taking turns). The rr setups need root or CAP_SYS_NICE.
        #[arg(long, value_delimiter = ',', value_parser = Setup::parse, default_value = "plain")]
        setup: Vec<Setup>,
    },
    /// Replica restart time by component state size, and the fork+touch floor (Figure 4).
    Restart {
        /// Resident state of the ballast component (suffixes k, m: 256k, 64m).
        #[arg(long, value_delimiter = ',', value_parser = parse_size,
              default_value = "256k,1m,8m,32m,64m")]
        size: Vec<u64>,
        /// Restarts measured per size (and floor samples).
        #[arg(long, default_value_t = 30)]
        count: u64,
        /// Round deadline of the voter, µs (generous by default: a replica with a large state
        /// takes a while to start, and hangs are not what this measures).
        #[arg(long, default_value_t = 2_000_000, value_parser = timeout_us())]
        timeout_us: u64,
        /// How processes are scheduled (plain, rr, rr-pinned, one-cpu, rr-one-cpu; see `echo
        /// --help`). The floor's fork runs at the bench's own scheduling of that setup.
        #[arg(long, value_parser = Setup::parse, default_value = "plain")]
        setup: Setup,
        /// Idle time before each kill, and before each fork of the floor, ms. 0 (the default):
        /// back to back, so caches and the kernel's free page lists are warm from the last
        /// restart. A fault in a real system comes after a while of other work: measured on
        /// the project's VM under s3res-bootstrap, a 256 KiB restart took about 220 µs with
        /// 2–5 ms between kills, 350 with 20–50 ms and 455 with 200–500 ms (docs/results.md,
        /// stop 36).
        #[arg(long, default_value_t = 0)]
        gap_ms: u64,
    },
    /// Crash and hang detection latency; false positives in fault-free rounds.
    Detect {
        /// Round timeouts, µs (each 1 to 60,000,000).
        #[arg(long, value_delimiter = ',', default_value = "2000,20000", value_parser = timeout_us())]
        timeout_us: Vec<u64>,
        /// Injected crashes and hangs per timeout (0 skips the detection latencies: only the
        /// fault-free rounds of --rounds are run).
        #[arg(long, default_value_t = 1000)]
        count: u64,
        /// Fault-free TMR rounds for the false-positive count (at the smallest timeout; 0 skips).
        #[arg(long, default_value_t = 1_000_000)]
        rounds: u64,
        /// Seed of the choice of victim replicas (printed; random if not given).
        #[arg(long)]
        seed: Option<u64>,
        /// How processes are scheduled (plain, rr, rr-pinned, one-cpu, rr-one-cpu; see `echo
        /// --help`).
        #[arg(long, value_parser = Setup::parse, default_value = "plain")]
        setup: Setup,
    },
    /// Draw the plots again from saved JSON lines (echo and restart rows) into --plot DIR.
    Plot {
        /// Files of JSON lines written with --json.
        #[arg(required = true)]
        files: Vec<PathBuf>,
    },
    /// Resident memory of an idle voter and of replica-rt components beyond their state.
    Memory {
        /// Ballast states to measure the runtime's overhead against (suffixes k, m).
        #[arg(long, value_delimiter = ',', value_parser = parse_size, default_value = "0,8m")]
        size: Vec<u64>,
    },
}

/// What every subcommand needs.
pub struct Common {
    pub bins: Bins,
    pub quiet: bool,
    /// Whether the voter keeps its journal (see `--no-journal`).
    pub journal: bool,
    /// What the replicas lock (see `--lock-memory`).
    pub lock_memory: LockMemory,
    /// What idle CPUs do while a voter runs (see `--cpu-idle`).
    pub cpu_idle: CpuIdle,
    /// How long a voter pinned apart from its replicas may spin (see `--spin-us`).
    pub spin_us: u32,
    /// `Some("static")` when the measured components are statically linked (read once from
    /// their ELF headers: `Bins::component_linking`).
    pub linking: Option<&'static str>,
}

impl Common {
    /// A progress bar on stderr (hidden with --quiet or when stderr is not a terminal).
    pub fn progress(&self, total: u64, what: &str) -> ProgressBar {
        if self.quiet || !std::io::stderr().is_terminal() {
            return ProgressBar::hidden();
        }
        let bar = ProgressBar::with_draw_target(Some(total), ProgressDrawTarget::stderr());
        bar.set_style(
            ProgressStyle::with_template(
                "{prefix} [{elapsed_precise}] {wide_bar} {pos}/{len} {msg}",
            )
            .expect("valid template"),
        );
        bar.set_prefix(what.to_owned());
        bar
    }
}

/// `8`, `4096`, `4k`, `4KiB`, `64m`, `64MiB`.
fn parse_size(s: &str) -> Result<u64, String> {
    let t = s.trim().to_ascii_lowercase();
    let (num, mult) = if let Some(n) = t.strip_suffix("kib").or(t.strip_suffix('k')) {
        (n, 1u64 << 10)
    } else if let Some(n) = t.strip_suffix("mib").or(t.strip_suffix('m')) {
        (n, 1 << 20)
    } else if let Some(n) = t.strip_suffix('b') {
        (n, 1)
    } else {
        (t.as_str(), 1)
    };
    let n = num
        .trim()
        .parse::<u64>()
        .map_err(|_| format!("`{s}` is not a size (examples: 8, 4096, 4k, 64m)"))?;
    // Checked: a size that wrapped around was measured as another (17592186044416m as 0 B).
    match n.checked_mul(mult) {
        Some(bytes) if bytes <= MAX_STATE => Ok(bytes),
        _ => Err(format!("`{s}`: at most {} GiB", MAX_STATE >> 30)),
    }
}

/// The largest state size (`restart`, `memory`): a few times what the figures go to (64 MiB).
const MAX_STATE: u64 = 16 << 30;

/// A frame payload size (`echo`): a [`parse_size`] no larger than a channel's largest frame.
fn parse_frame_size(s: &str) -> Result<u64, String> {
    let n = parse_size(s)?;
    let max = s3res_description::description::MAX_FRAME_LIMIT as u64;
    if n > max {
        return Err(format!(
            "`{s}`: a frame holds at most {max} bytes (16 MiB, a channel's largest max_frame)"
        ));
    }
    Ok(n)
}

fn main() -> ExitCode {
    replica_rt::init_logging("bench");
    match run() {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("s3res-bench: {e:#}");
            ExitCode::FAILURE
        }
    }
}

fn run() -> Result<()> {
    let cli = Cli::parse();
    sys::install_interrupt_handler().context("installing the Ctrl-C handler")?;
    // Replicas whose voter died come to us, so they are reaped here.
    replica_rt::sys::set_child_subreaper().context("becoming a child subreaper")?;
    let bins = Bins::locate(cli.common.bin_dir.clone(), cli.common.component_dir.clone())?;
    let linking = bins.component_linking()?;
    if linking.is_some() {
        eprintln!("s3res-bench: the components measured are statically linked");
    }
    let common = Common {
        bins,
        linking,
        quiet: cli.common.quiet,
        journal: !cli.common.no_journal,
        lock_memory: cli.common.lock_memory,
        cpu_idle: cli.common.cpu_idle,
        spin_us: cli.common.spin_us,
    };
    let json = cli.common.json;
    // Taken before measuring: the load then is what the measurement competed with.
    let machine = replica_rt::machine::Machine::probe().one_line();
    if common.cpu_idle == CpuIdle::Poll {
        // What the voters will open; opening it without writing asks for nothing. Refused
        // here, every voter would run on sleeping CPUs and the rows would say otherwise.
        std::fs::File::options()
            .write(true)
            .open(CPU_LATENCY_QOS)
            .with_context(|| {
                format!(
                    "--cpu-idle poll: the voters could not open {CPU_LATENCY_QOS} (run as root)"
                )
            })?;
    }
    let cpu_idle = (common.cpu_idle == CpuIdle::Poll).then_some(common.cpu_idle.as_str());
    let stamp = |mut rows: Vec<report::Row>| {
        for r in &mut rows {
            r.machine = Some(machine.clone());
            // Only a voter holds the request: a row without one (the no-voter baseline) ran
            // on CPUs that sleep when idle.
            r.cpu_idle = cpu_idle.filter(|_| r.replicas > 0);
            // Only a voter pinned apart from its replicas spins.
            let apart = Setup::parse(r.setup).is_ok_and(|s| {
                let placed = s.plan_fields(r.replicas);
                s3res_protocol::sched::voter_apart(&placed.cpus, placed.voter_cpu)
            });
            r.spin_us = (apart && r.replicas > 0).then_some(common.spin_us);
            // An unmodified program's rows ran `cat`, not a component of the folder.
            let preloaded = r.what.as_deref().is_some_and(|w| w.starts_with("preload"));
            r.linking = linking.filter(|_| !preloaded);
        }
        rows
    };
    let plot_dir = cli.common.plot.clone();
    if let Some(dir) = &plot_dir {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    match cli.command {
        Command::Echo {
            program,
            replicas,
            size,
            count,
            warmup,
            timeout_us,
            setup,
        } => {
            if count == 0 {
                bail!("--count must be at least 1");
            }
            if setup.iter().any(|s| s.realtime()) && !sys::is_root() {
                let realtime: Vec<&str> = Setup::ALL
                    .iter()
                    .filter(|s| s.realtime())
                    .map(|s| s.name())
                    .collect();
                tracing::warn!(
                    "setups {} need root or CAP_SYS_NICE; they may fail",
                    realtime.join(", ")
                );
            }
            let opts = echo::EchoOptions {
                program,
                replicas,
                sizes: size.into_iter().map(|s| s as usize).collect(),
                count,
                warmup,
                timeout_us,
                setups: setup,
            };
            let rows = stamp(echo::run(&common, &opts)?);
            report::emit(&rows, json, echo::render);
            write_plot(plot_dir, "fig3-round-trip.svg", |p| {
                plot::round_trip(&rows, p)
            })?;
        }
        Command::Restart {
            size,
            count,
            timeout_us,
            setup,
            gap_ms,
        } => {
            if count == 0 {
                bail!("--count must be at least 1");
            }
            let gap = std::time::Duration::from_millis(gap_ms);
            let rows = stamp(restart::run(&common, &size, count, timeout_us, setup, gap)?);
            report::emit(&rows, json, restart::render);
            write_plot(plot_dir, "fig4-restart.svg", |p| plot::restart(&rows, p))?;
        }
        Command::Detect {
            timeout_us,
            count,
            rounds,
            seed,
            setup,
        } => {
            let seed = seed.unwrap_or_else(replica_rt::sys::monotonic_ns);
            eprintln!("s3res-bench detect: seed = {seed}");
            let opts = detect::DetectOptions {
                setup,
                timeouts_us: timeout_us,
                count,
                rounds,
                seed,
            };
            let rows = stamp(detect::run(&common, &opts)?);
            report::emit(&rows, json, detect::render);
        }
        Command::Plot { files } => {
            let Some(dir) = plot_dir else {
                bail!("plot needs --plot DIR");
            };
            let mut rows = Vec::new();
            for f in &files {
                let text = std::fs::read_to_string(f)
                    .with_context(|| format!("reading {}", f.display()))?;
                for (n, line) in text
                    .lines()
                    .enumerate()
                    .filter(|(_, l)| !l.trim().is_empty())
                {
                    let v: serde_json::Value = serde_json::from_str(line)
                        .with_context(|| format!("{}:{}: not JSON", f.display(), n + 1))?;
                    rows.extend(report::Row::from_json(&v));
                }
            }
            let (echo, restart): (Vec<_>, Vec<_>) =
                rows.into_iter().partition(|r| r.bench == "echo");
            if echo.is_empty() && restart.is_empty() {
                bail!("no echo or restart rows in the given files");
            }
            if !echo.is_empty() {
                write_plot(Some(dir.clone()), "fig3-round-trip.svg", |p| {
                    plot::round_trip(&echo, p)
                })?;
            }
            if !restart.is_empty() {
                write_plot(Some(dir), "fig4-restart.svg", |p| {
                    plot::restart(&restart, p)
                })?;
            }
        }
        Command::Memory { size } => {
            let rows = memory::run(&common, &size)?;
            memory::emit(&rows, json);
        }
    }
    Ok(())
}

/// Writes plot `name` into `dir` with `draw`, if a plot folder was asked for.
fn write_plot(
    dir: Option<PathBuf>,
    name: &str,
    draw: impl FnOnce(&std::path::Path) -> Result<()>,
) -> Result<()> {
    if let Some(dir) = dir {
        let path = dir.join(name);
        draw(&path)?;
        eprintln!("wrote {}", path.display());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_parse_with_suffixes() {
        assert_eq!(parse_size("8"), Ok(8));
        assert_eq!(parse_size("4k"), Ok(4096));
        assert_eq!(parse_size("256KiB"), Ok(256 << 10));
        assert_eq!(parse_size("64m"), Ok(64 << 20));
        assert_eq!(parse_size("64MiB"), Ok(64 << 20));
        assert!(parse_size("lots").unwrap_err().contains("lots"));
        // Too large, or wrapping around u64, is refused, not measured as another size.
        assert!(parse_size("17592186044416m")
            .unwrap_err()
            .contains("at most 16 GiB"));
        assert!(parse_size("99999999999999")
            .unwrap_err()
            .contains("at most"));
        assert_eq!(parse_frame_size("16m"), Ok(16 << 20));
        assert!(parse_frame_size("17m")
            .unwrap_err()
            .contains("at most 16777216"));
    }

    #[test]
    fn every_setup_is_named_in_the_help_of_every_subcommand_that_takes_one() {
        use clap::CommandFactory;
        let mut cli = Cli::command();
        for sub in ["echo", "restart", "detect"] {
            let help = cli
                .find_subcommand_mut(sub)
                .unwrap()
                .render_long_help()
                .to_string();
            // Whole words: `one-cpu` is not named by `rr-one-cpu`.
            let words: Vec<&str> = help
                .split(|c: char| !(c.is_ascii_alphanumeric() || c == '-'))
                .collect();
            for setup in Setup::ALL {
                let name = setup.name();
                assert!(
                    words.contains(&name),
                    "`{sub} --help` does not name the setup {name}:\n{help}"
                );
                assert_eq!(Setup::parse(name), Ok(setup));
            }
        }
        // Every setup is in `Setup::ALL`, in its place: a new one does not compile here until
        // it is given one (and put there).
        let place = |setup: Setup| match setup {
            Setup::Plain => 0,
            Setup::Rr => 1,
            Setup::RrPinned => 2,
            Setup::OneCpu => 3,
            Setup::RrOneCpu => 4,
        };
        for (i, setup) in Setup::ALL.into_iter().enumerate() {
            assert_eq!(place(setup), i, "{setup:?}");
        }
    }

    /// A deadline of 0 reached the voter, which refused its plan, and the bench said first
    /// that the voter's events pipe closed; one beyond a minute is beyond any description's.
    #[test]
    fn timeouts_outside_a_descriptions_bounds_are_refused_by_every_subcommand() {
        use clap::Parser;
        let cases = [
            ("echo", "0"),
            ("echo", "60000001"),
            ("restart", "0"),
            ("detect", "0"),
            ("detect", "1000,0"),
        ];
        for (sub, bad) in cases {
            let e = Cli::try_parse_from(["s3res-bench", sub, "--timeout-us", bad])
                .err()
                .unwrap_or_else(|| panic!("{sub} --timeout-us {bad} was taken"));
            assert!(
                e.to_string().contains("is not in 1..=60000000"),
                "{sub}: {e}"
            );
            assert!(Cli::try_parse_from(["s3res-bench", sub, "--timeout-us", "60000000"]).is_ok());
        }
    }

    #[test]
    fn cli_is_well_formed() {
        use clap::CommandFactory;
        Cli::command().debug_assert();
    }
}
