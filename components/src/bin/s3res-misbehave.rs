//! `s3res-misbehave`: an echo that breaks the frame protocol once, on purpose. See `--help`.

#![forbid(unsafe_code)]

use anyhow::{Context, Result};
use clap::{Parser, ValueEnum};
use replica_rt::frame::header;
use replica_rt::OutPort;
use s3res_components::Echo;

/// TEST AID: behaves exactly like `s3res-echo`, except that the replica(s) with index R, when
/// answering frame K (0-based), break the frame protocol (or the answer) in the chosen way, so
/// tests can check that the voter detects it and recovers. Never use it as a real component.
///
/// Modes:
///   oversize  instead of the answer: a header announcing 0x7fff_fff0 bytes and 4 bytes; then
///             normal answers again from frame K+1
///   truncate  instead of the answer: a header announcing 100 bytes and only 10 bytes; then it
///             closes its output and reads its input to the end without answering
///   extra     the correct answer, then a second, unasked-for frame
///   garbage   instead of the answer: 7 bytes, a header announcing 200 bytes and 3 bytes of
///             junk; then normal answers again from frame K+1
///   corrupt   a well-formed answer with the last byte inverted (a silent data corruption);
///             then normal answers again from frame K+1
///   panic     panic at start, before answering anything (a replacement started by exec has
///             the same index and panics again: a component that always fails)
///   spin      the correct answer, then spin forever (a control-flow error that strikes just
///             after the replica answered, while its siblings are still working on the round)
///   die-slowly  instead of the answer: closes its output, computes for 150 ms (as a program
///             that reports an error with a backtrace on its way out), then exits with status 1
///   last-words  at frame K, a line `Error: misbehaving on purpose: last words` on stderr, and
///             the answer; at frame K+100 the process it started as exits with status 1 without
///             another word, at frame K+200 every replacement forked from it (as a program forked
///             while it reported an error on its way out, whose child writes nothing of it)
///   silent    from frame K on, no answer at all (a component that forgets to send its
///             output); with K = 0 on every replica, a stream component that never sends
///   worker    from frame K on, every answer passes through a worker thread (handed over a
///             channel and back): correct answers, but a second thread, which a fork does not
///             copy (the rule a component breaks by starting one)
///
/// The replica index is S3RES_REPLICA, read once at start. A replacement forked from a healthy
/// donor inherits the donor's memory, including the donor's index, so it does not misbehave
/// again. Without S3RES_REPLICA (started by hand) it never misbehaves.
#[derive(Parser)]
#[command(name = "s3res-misbehave", version, verbatim_doc_comment)]
struct Cli {
    /// How to break the protocol.
    #[arg(long, value_enum)]
    mode: Mode,
    /// Index of the replica that misbehaves (S3RES_REPLICA); several as `1,3`.
    #[arg(long, value_name = "R", value_delimiter = ',', required = true)]
    replica: Vec<usize>,
    /// 0-based number of the frame whose answer is broken.
    #[arg(long, value_name = "K")]
    at: u64,
    /// Prefix answers with a counter, as `s3res-echo --stateful`.
    #[arg(long)]
    stateful: bool,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum Mode {
    Oversize,
    Truncate,
    Extra,
    Garbage,
    Corrupt,
    Spin,
    Panic,
    Worker,
    DieSlowly,
    LastWords,
    Silent,
}

fn main() -> Result<()> {
    replica_rt::init_logging("misbehave");
    let cli = Cli::parse();
    let mut rt = replica_rt::init().context("starting the s3res runtime")?;
    // Read once, here: a forked replacement keeps this value (see --help).
    let me = rt.replica_index();
    let armed = me.is_some_and(|r| cli.replica.contains(&r));
    if armed {
        tracing::info!(mode = ?cli.mode, at = cli.at, "this replica will misbehave");
        if matches!(cli.mode, Mode::Panic) {
            panic!("misbehaving on purpose: a replica that fails at every start");
        }
    }
    let mut input = rt.input("in").context("opening the input port")?;
    let mut output = Some(rt.output("out").context("opening the output port")?);
    let mut echo = Echo::new(cli.stateful);
    let mut worker = None;
    // The process this replica started as (a forked replacement has another pid).
    let started_as = std::process::id();
    let mut k: u64 = 0;
    while let Some(frame) = input.recv().context("receiving")? {
        let answer = echo.answer(frame);
        if armed && matches!(cli.mode, Mode::LastWords) {
            if k == cli.at {
                eprintln!("Error: misbehaving on purpose: last words");
            }
            let end = if std::process::id() == started_as {
                cli.at + 100
            } else {
                cli.at + 200
            };
            if k >= end {
                std::process::exit(1);
            }
        }
        if armed && matches!(cli.mode, Mode::Silent) && k >= cli.at {
            k += 1;
            continue;
        }
        if let Some(out) = output.as_mut() {
            if armed && matches!(cli.mode, Mode::Worker) && k >= cli.at {
                let worker = worker.get_or_insert_with(Worker::start);
                out.send(&worker.round_trip(answer)?).context("answering")?;
            } else if armed && k == cli.at && !matches!(cli.mode, Mode::LastWords) {
                tracing::warn!(mode = ?cli.mode, frame = k, "misbehaving now, on purpose");
                if misbehave(cli.mode, out, answer)? == After::Close {
                    // Dropping the port closes the fd: the voter sees the pipe closed.
                    output = None;
                    if matches!(cli.mode, Mode::DieSlowly) {
                        let started = std::time::Instant::now();
                        while started.elapsed() < std::time::Duration::from_millis(150) {
                            std::hint::spin_loop();
                        }
                        eprintln!("Error: misbehaving on purpose: exiting slowly with status 1");
                        std::process::exit(1);
                    }
                }
            } else {
                out.send(answer).context("answering")?;
            }
        }
        k += 1;
    }
    Ok(())
}

#[derive(PartialEq, Eq)]
enum After {
    CarryOn,
    Close,
}

fn misbehave(mode: Mode, out: &mut OutPort, answer: &[u8]) -> Result<After> {
    let mut bytes = Vec::new();
    let after = match mode {
        Mode::Oversize => {
            bytes.extend_from_slice(&header(0x7fff_fff0));
            bytes.extend_from_slice(&[1, 2, 3, 4]);
            After::CarryOn
        }
        Mode::Truncate => {
            bytes.extend_from_slice(&header(100));
            bytes.extend_from_slice(&[0xab; 10]);
            After::Close
        }
        Mode::Extra => {
            out.send(answer).context("answering")?;
            out.send(b"extra frame from s3res-misbehave")
                .context("sending the extra frame")?;
            return Ok(After::CarryOn);
        }
        Mode::Garbage => {
            bytes.extend_from_slice(&header(200));
            bytes.extend_from_slice(&[0xde, 0xad, 0xbe]);
            After::CarryOn
        }
        Mode::Corrupt => {
            let mut wrong = answer.to_vec();
            if let Some(last) = wrong.last_mut() {
                *last = !*last;
            }
            out.send(&wrong).context("sending the corrupted answer")?;
            return Ok(After::CarryOn);
        }
        Mode::Spin => {
            out.send(answer).context("answering")?;
            loop {
                std::hint::spin_loop();
            }
        }
        Mode::Panic => unreachable!("panics at start"),
        Mode::Worker => unreachable!("answers through the worker"),
        Mode::LastWords => unreachable!("answers until it exits"),
        Mode::Silent => unreachable!("answers nothing"),
        Mode::DieSlowly => After::Close,
    };
    out.write_raw(&bytes).context("writing the broken frame")?;
    Ok(after)
}

/// A second thread that hands back what it is given.
struct Worker {
    to: std::sync::mpsc::Sender<Vec<u8>>,
    from: std::sync::mpsc::Receiver<Vec<u8>>,
}

impl Worker {
    fn start() -> Worker {
        let (to, inbox) = std::sync::mpsc::channel::<Vec<u8>>();
        let (outbox, from) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            for frame in inbox {
                if outbox.send(frame).is_err() {
                    break;
                }
            }
        });
        tracing::info!("a worker thread answers from now on");
        Worker { to, from }
    }

    fn round_trip(&self, answer: &[u8]) -> Result<Vec<u8>> {
        self.to
            .send(answer.to_vec())
            .context("handing the answer to the worker")?;
        self.from.recv().context("the worker's answer")
    }
}
