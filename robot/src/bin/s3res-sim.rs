//! `s3res-sim`: the maze-robot simulator and benchmarker. See `--help`.

#![forbid(unsafe_code)]

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use clap::{Args, Parser, Subcommand};
use replica_rt::TryRecv;
use s3res_robot::component::{optional_output, Downstream};
use s3res_robot::mission::{run_in_process, Controllers};
use s3res_robot::msg::{Cmd, Tick};
use s3res_robot::sim::{Sim, SimConfig, Summary};
use s3res_robot::svg;

/// The maze-robot simulator: a seeded maze, a differential-drive robot with 16 range sensors,
/// and the mission verdict. It is the top-priority, unprotected component of the robot system
/// (the benchmarker of the S³RES evaluation).
///
/// Each period (--hz per wall-clock second, --dt simulated seconds each) it sends a scan on
/// output `sensors` (and, if connected, the pose on `telemetry` and a work unit on `tick`),
/// then waits until the period ends for the command answering that scan on input `cmd`. A
/// command that is late leaves the previous one in force, and the period is counted late (a
/// late answer to an earlier scan, when it comes, replaces an older command in force).
///
/// The mission succeeds when the robot reaches the goal (the far corner) before --time-limit
/// simulated seconds without touching a wall; a contact ends it at once. Then the sim closes
/// its outputs (so the whole system finishes), waits for `cmd` to close, prints a one-line
/// summary on stderr, writes --summary, and exits 0 on success, 1 on failure.
///
/// Other uses:
///
///     s3res-sim golden --seed 3 --summary golden.json    # the mission in one process, ideal timing
///     s3res-sim render golden.json --overlay faulted.json --out maze.svg
#[derive(Parser)]
#[command(
    name = "s3res-sim",
    version,
    verbatim_doc_comment,
    args_conflicts_with_subcommands = true
)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
    #[command(flatten)]
    run: RunArgs,
}

#[derive(Subcommand)]
enum Command {
    /// Runs the mission with every control algorithm in this process, with ideal timing: the
    /// golden run of a seed (deterministic).
    Golden(GoldenArgs),
    /// Draws a mission summary as SVG: the maze and the trajectory, optionally a second one.
    Render(RenderArgs),
}

#[derive(Args)]
struct WorldArgs {
    /// Seed of the maze and of the sensor noise.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Maze cells per side.
    #[arg(long, default_value_t = 8, value_parser = clap::value_parser!(u64).range(2..=32))]
    cells: u64,
    /// Simulated seconds per period.
    #[arg(long, default_value_t = 0.05)]
    dt: f64,
    /// Simulated seconds before the mission fails.
    #[arg(long, default_value_t = 120.0)]
    time_limit: f64,
    /// Outlier readings per thousand (spurious or missed echoes the filter must remove).
    #[arg(long, default_value_t = 20, value_parser = clap::value_parser!(u32).range(0..=1000))]
    outliers: u32,
    /// Write the mission summary (JSON, with the trajectory) here.
    #[arg(long)]
    summary: Option<PathBuf>,
}

impl WorldArgs {
    fn config(&self) -> Result<SimConfig> {
        if !(self.dt > 0.0 && self.dt <= 1.0) {
            bail!("--dt must be in (0, 1] seconds, got {}", self.dt);
        }
        if !(self.time_limit > 0.0 && self.time_limit.is_finite()) {
            bail!("--time-limit must be positive, got {}", self.time_limit);
        }
        let mut cfg = SimConfig::new(self.seed);
        cfg.maze.cells = self.cells as usize;
        cfg.dt = self.dt;
        cfg.time_limit_s = self.time_limit;
        cfg.outlier_per_mille = self.outliers;
        Ok(cfg)
    }
}

#[derive(Args)]
struct RunArgs {
    #[command(flatten)]
    world: WorldArgs,
    /// Control periods per wall-clock second. With the default --dt of 0.05 s, 50 Hz runs the
    /// simulated world 2.5 times faster than real time.
    #[arg(long, default_value_t = 50.0)]
    hz: f64,
    /// How long to wait, after the mission, for the controllers to close `cmd`, milliseconds.
    #[arg(long, default_value_t = 10_000)]
    drain_ms: u64,
}

#[derive(Args)]
struct GoldenArgs {
    #[command(flatten)]
    world: WorldArgs,
}

#[derive(Args)]
struct RenderArgs {
    /// The summary to draw (blue).
    summary: PathBuf,
    /// A second summary of the same maze to draw over it (red, dashed), e.g. a faulted run.
    #[arg(long)]
    overlay: Option<PathBuf>,
    /// Where to write the SVG.
    #[arg(long)]
    out: PathBuf,
}

fn main() {
    replica_rt::init_logging("sim");
    let cli = Cli::parse();
    let result = match cli.command {
        Some(Command::Golden(g)) => golden(g),
        Some(Command::Render(r)) => render(r).map(|()| true),
        None => run(cli.run),
    };
    match result {
        Ok(true) => {}
        Ok(false) => std::process::exit(1),
        Err(e) => {
            eprintln!("s3res-sim: error: {e:#}");
            std::process::exit(2);
        }
    }
}

fn write_summary(path: Option<&Path>, summary: &Summary) -> Result<()> {
    // One write: the other processes of the system share this stderr, and a verdict written
    // in pieces could be interleaved with their lines.
    let verdict = format!("s3res-sim: {}\n", summary.line());
    let _ = std::io::Write::write_all(&mut std::io::stderr().lock(), verdict.as_bytes());
    if let Some(path) = path {
        let json = serde_json::to_string(summary).context("encoding the summary")?;
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir)
                .with_context(|| format!("creating the folder {}", dir.display()))?;
        }
        std::fs::write(path, json + "\n")
            .with_context(|| format!("writing the summary to {}", path.display()))?;
    }
    Ok(())
}

fn golden(args: GoldenArgs) -> Result<bool> {
    let summary = run_in_process(args.world.config()?, Controllers::default());
    write_summary(args.world.summary.as_deref(), &summary)?;
    Ok(summary.success)
}

fn render(args: RenderArgs) -> Result<()> {
    let read = |p: &Path| -> Result<Summary> {
        let text =
            std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?;
        serde_json::from_str(&text)
            .with_context(|| format!("{} is not a mission summary", p.display()))
    };
    let first = read(&args.summary)?;
    let second = args.overlay.as_deref().map(read).transpose()?;
    if let Some(s) = &second {
        if s.config.maze != first.config.maze {
            bail!(
                "{} is a mission in another maze than {} (seed or size differ)",
                args.overlay
                    .as_ref()
                    .map_or(String::new(), |p| p.display().to_string()),
                args.summary.display()
            );
        }
    }
    std::fs::write(&args.out, svg::render(&first, second.as_ref()))
        .with_context(|| format!("writing {}", args.out.display()))?;
    Ok(())
}

/// Whether `c` answers a later scan than `than` (or there is none).
fn fresher(c: &Cmd, than: &Option<Cmd>) -> bool {
    !matches!(than, Some(t) if t.seq >= c.seq)
}

fn run(args: RunArgs) -> Result<bool> {
    let cfg = args.world.config()?;
    if !(args.hz > 0.0 && args.hz <= 10_000.0) {
        bail!("--hz must be in (0, 10000], got {}", args.hz);
    }
    let mut rt = replica_rt::init().context("starting the s3res runtime")?;
    // A reader that dies (an unprotected component killed) must not end the mission early:
    // the robot carries on with its last command, and the verdict says what came of it.
    let mut sensors = Downstream::new(Some(
        rt.output("sensors").context("opening output sensors")?,
    ));
    let mut cmd_in = rt.input("cmd").context("opening input cmd")?;
    let mut telemetry = Downstream::new(optional_output(&mut rt, "telemetry")?);
    let mut tick = Downstream::new(optional_output(&mut rt, "tick")?);

    let mut sim = Sim::new(cfg);
    let period = Duration::from_secs_f64(1.0 / args.hz);
    let mut buf = Vec::with_capacity(256);
    let mut bad_frames = 0u64;
    let mut controller_gone = false;
    let started = Instant::now();
    let mut next = started;
    let mut applied: Option<Cmd> = None;
    tracing::info!(
        seed = cfg.maze.seed,
        hz = args.hz,
        dt = cfg.dt,
        "mission starts"
    );
    while sim.is_running() {
        let seq = sim.seq();
        sim.scan().encode(&mut buf);
        sensors.send(&buf).context("sending the scan")?;
        sim.telemetry().encode(&mut buf);
        telemetry.send(&buf).context("sending telemetry")?;
        Tick { seq }.encode(&mut buf);
        tick.send(&buf).context("sending the tick")?;
        let deadline = next + period;
        let mut answer = None;
        loop {
            let now = Instant::now();
            if now >= deadline {
                break;
            }
            if controller_gone {
                std::thread::sleep(deadline - now);
                break;
            }
            match cmd_in
                .recv_timeout(deadline - now)
                .context("receiving a command")?
            {
                TryRecv::Frame(bytes) => match Cmd::decode(bytes) {
                    // The freshest command wins, even one answering an earlier scan that came
                    // late (the period still counts late); an older one than in force is dropped.
                    Ok(c) if c.seq <= seq && fresher(&c, &applied) && fresher(&c, &answer) => {
                        answer = Some(c)
                    }
                    Ok(_) => {}
                    Err(e) => {
                        bad_frames += 1;
                        tracing::warn!(error = %e, seq, "bad command frame ignored");
                    }
                },
                TryRecv::Empty => break,
                TryRecv::Closed => {
                    tracing::warn!(
                        seq,
                        "the command channel closed: the robot keeps its last command"
                    );
                    controller_gone = true;
                }
            }
        }
        if let Some(c) = answer {
            applied = Some(c);
        }
        sim.step(answer);
        next = deadline;
        let now = Instant::now();
        if now > next + period {
            // The sim itself fell behind (descheduled): do not burst to catch up.
            next = now;
        }
    }
    let wall = started.elapsed().as_secs_f64();
    // Close every output: the whole system sees end of input and finishes.
    sensors.close();
    telemetry.close();
    tick.close();
    // Keep reading commands until the controllers close them, so none of them writes into a
    // closed pipe on the way out.
    let drain_until = Instant::now() + Duration::from_millis(args.drain_ms);
    while !controller_gone {
        let left = drain_until.saturating_duration_since(Instant::now());
        controller_gone = left.is_zero();
        if controller_gone {
            tracing::warn!(
                "the command channel is still open after the mission; not waiting longer"
            );
        } else if let Ok(TryRecv::Closed) | Err(_) = cmd_in.recv_timeout(left) {
            controller_gone = true;
        }
    }
    let summary = sim.summary(args.hz, wall);
    if bad_frames > 0 {
        tracing::warn!(bad_frames, "bad command frames were ignored");
    }
    write_summary(args.world.summary.as_deref(), &summary)?;
    Ok(summary.success)
}
