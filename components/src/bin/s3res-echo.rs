//! `s3res-echo`: answers every frame with itself. See `--help`.

#![forbid(unsafe_code)]

use anyhow::{Context, Result};
use clap::Parser;
use replica_rt::TryRecv;
use s3res_components::Echo;

/// Answers every frame on input `in` with the same bytes on output `out`; exits at the end of
/// the input.
///
/// With --stateful each answer starts with a little-endian u64: how many frames were answered
/// before this one (0 for the first). That counter is state a replica must not lose: a replica
/// restarted by fork from a healthy one carries on counting, one restarted afresh starts at 0
/// again, and `s3res-sink --stateful` reports it as a state break.
///
/// Started by hand (not by s3res-bootstrap), `in` is stdin and `out` is stdout:
///
///     s3res-source --count 5 --hz 0 | s3res-echo --stateful | s3res-sink --stateful --expect 5
#[derive(Parser)]
#[command(name = "s3res-echo", version, verbatim_doc_comment)]
struct Cli {
    /// Prefix each answer with the number of frames answered before it.
    #[arg(long)]
    stateful: bool,
    /// Hold this many MiB of private heap, every page written (for tests that look at the
    /// replicas' memory, such as the copy-on-write break after a fork).
    #[arg(long, value_name = "MIB", default_value_t = 0)]
    heap_mib: usize,
    /// Compute for this many microseconds (spinning on the CPU) before each answer, like a
    /// component with real work to do (for tests that need rounds to take a while).
    #[arg(long, value_name = "US", default_value_t = 0)]
    work_us: u64,
    /// Never block for input: look for a frame with `try_recv` and, when none has come, sleep
    /// this many microseconds and look again (a component that polls, for the tests that
    /// check such a one is looked after as well as one that waits).
    #[arg(long, value_name = "US")]
    poll_us: Option<u64>,
}

fn main() -> Result<()> {
    replica_rt::init_logging("echo");
    let cli = Cli::parse();
    let mut rt = replica_rt::init().context("starting the s3res runtime")?;
    let mut input = rt.input("in").context("opening the input port")?;
    let mut output = rt.output("out").context("opening the output port")?;
    let mut echo = Echo::new(cli.stateful);
    // Filled with a non-zero byte, so every page is a private page of its own (not the zero page).
    let heap_bytes = cli.heap_mib.checked_mul(1 << 20).with_context(|| {
        format!(
            "--heap-mib {} is more than this machine can address",
            cli.heap_mib
        )
    })?;
    let ballast = vec![0xa5u8; heap_bytes];
    let mut frames: u64 = 0;
    let work = std::time::Duration::from_micros(cli.work_us);
    let poll = cli.poll_us.map(std::time::Duration::from_micros);
    loop {
        let frame = match poll {
            None => match input.recv().context("receiving")? {
                Some(frame) => frame,
                None => break,
            },
            Some(pause) => match input.try_recv().context("receiving")? {
                TryRecv::Frame(frame) => frame,
                TryRecv::Empty => {
                    std::thread::sleep(pause);
                    continue;
                }
                TryRecv::Closed => break,
            },
        };
        // No clock read without work: the round-trip benchmarks measure the runtime, not two
        // clock reads a frame.
        if !work.is_zero() {
            let started = std::time::Instant::now();
            while started.elapsed() < work {
                std::hint::spin_loop();
            }
        }
        output.send(echo.answer(frame)).context("answering")?;
        frames += 1;
    }
    tracing::info!(
        frames,
        heap_bytes = std::hint::black_box(&ballast).len(),
        "end of input"
    );
    Ok(())
}
