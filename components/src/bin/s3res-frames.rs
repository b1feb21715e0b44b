//! `s3res-frames`: feed frames into a system and watch what comes out. See `--help`.

#![forbid(unsafe_code)]

use std::fs::File;
use std::io::{BufRead, BufReader, Write};
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use clap::{Parser, Subcommand};
use s3res_components::due_at;
use s3res_components::frames::{parse_encoding_name, parse_layout, Encoding, Format, LineCheck};

/// Feeds frames into an s3res system and watches what comes out, without writing code.
///
///   send   reads lines (a file or stdin) and sends each as one frame: text, numbers or JSON
///   show   prints every frame it receives, one line each: hex, text, or the fields of a layout
///   check  compares the frames it receives, as lines, with an expected file
///
/// Started by hand, `send` writes frames to stdout and `show`/`check` read them from stdin (the
/// standalone ports `out` and `in`), so they wrap any frame pipeline. Three samples through
/// the running mean of docs/writing-a-component.md, protected by TMR:
///
///     printf '1\n2\n3\n' | s3res-frames send --as f64 \
///       | s3res-bootstrap examples/running-mean/running-mean.json \
///       | s3res-frames show --format layout:count:u64,mean:f64
///     0 count=1 mean=1.0
///     1 count=2 mean=1.5
///     2 count=3 mean=2.0
///
/// In a system description they are components like any other (ports `out` and `in`; give
/// `send` its lines with --from FILE, since a component's stdin is /dev/null):
///
///     "feed":  { "exec": "s3res-frames", "args": ["send", "--from", "samples.txt", "--as", "f64"] },
///     "check": { "exec": "s3res-frames", "args": ["check", "--expect", "means.txt",
///                                                 "--format", "layout:count:u64,mean:f64"] }
///
/// `s3res-frames <command> --help` says more.
#[derive(Parser)]
#[command(name = "s3res-frames", version, verbatim_doc_comment)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    Send(SendArgs),
    Show(ShowArgs),
    Check(CheckArgs),
}

/// Sends one frame per line of input, then closes the port (the end of the stream).
///
/// Encodings (--as):
///
///   text       the line's bytes as they are, without the line end (the default)
///   u8 ... f64 the line's numbers (separated by spaces or commas), each as that type,
///              little-endian: `--as f64` makes "2.5" an 8-byte frame, "1 2" a 16-byte one
///   json       one JSON value per line, sent as its text; with --layout, laid out as binary:
///              {"seq": 7, "x": 0.5} or [7, 0.5] with --layout seq:u32@0,x:f64@8 is 16 bytes
///
/// With a number or JSON encoding, blank lines are skipped; a line that does not parse stops
/// `send` with its line number and text, and a nonzero exit status.
///
/// Examples:
///
///     seq 1 100 | s3res-frames send --as u32 --rate 50 | ...
///     s3res-frames send --from poses.jsonl --as json --layout 'x:f64,y:f64,heading:f32' | ...
#[derive(Parser)]
#[command(verbatim_doc_comment)]
struct SendArgs {
    /// Read lines from FILE instead of stdin.
    #[arg(long, value_name = "FILE")]
    from: Option<PathBuf>,
    /// How a line becomes a frame: text, json, or a number type (u8 u16 u32 u64 i8 i16 i32 i64
    /// f32 f64).
    #[arg(long = "as", value_name = "ENCODING", default_value = "text")]
    encoding: String,
    /// With --as json: the frame layout (see `show --help` for how to write one).
    #[arg(long, value_name = "SPEC")]
    layout: Option<String>,
    /// With --layout: the frame size in bytes, zero-filled after the fields (default: the end
    /// of the last field).
    #[arg(long, value_name = "BYTES", requires = "layout")]
    size: Option<usize>,
    /// Frames per second (fractions allowed); 0 sends as fast as the port takes them.
    #[arg(long, value_name = "HZ", default_value_t = 0.0)]
    rate: f64,
    /// The output port to send on.
    #[arg(long, value_name = "NAME", default_value = "out")]
    port: String,
}

/// Prints every frame it receives, one line each, until the stream ends.
///
/// Each line is the frame's index (from 0), a space, and the frame in the chosen format.
///
/// Formats (--format):
///
///   hex          every byte as two hex digits: 0 0000000000000040
///   text         the bytes as UTF-8 text; line ends, control characters (tab aside) and
///                bytes that are not UTF-8 are escaped (\n, \r, \x07, \xff): 0 hello
///   layout:SPEC  the fields of a layout, name=value: 0 count=1 mean=1.0
///
/// A layout SPEC is written as the system description's `fields` (the layout the anomaly
/// detectors use): inline JSON, `[{"name": "x", "type": "f64", "offset": 8}, ...]`; a .json file
/// holding it (or a channel entry with `fields`); or the shorthand name:type[@offset],...
/// where a field without @offset follows the one before: `count:u64,mean:f64` is count at
/// byte 0 and mean at byte 8. Types: u8 u16 u32 u64 i8 i16 i32 i64 f32 f64, little-endian.
/// Integers print exactly, floats in their shortest exact form (1.0, 0.1, 1e-7, NaN).
///
/// Example, a capture file of the anomaly detectors:
///
///     s3res-frames show --format layout:nav-cmd.layout.json < capture.bin
#[derive(Parser)]
#[command(verbatim_doc_comment)]
struct ShowArgs {
    /// hex, text, or layout:SPEC.
    #[arg(long, value_name = "FORMAT", default_value = "hex")]
    format: String,
    /// The input port to read.
    #[arg(long, value_name = "NAME", default_value = "in")]
    port: String,
    /// Write the lines to FILE instead of stdout.
    #[arg(long, value_name = "FILE")]
    out: Option<PathBuf>,
    /// Leave the index out: just the frames, as `check --expect` reads them.
    #[arg(long)]
    no_index: bool,
}

/// Compares the frames it receives, as lines, with an expected file.
///
/// Reads frames until the stream ends, renders each as a line (as `show --no-index` would) and
/// compares them with the lines of the file. Exits 0 only if they are exactly the same and as
/// many; otherwise prints the first difference (frame index, expected line, the line it got)
/// and how many lines differ, are missing and are extra, and exits 1.
///
///     check: first difference at frame 2 (line 3):
///       expected: count=3 mean=2.0
///       got:      count=3 mean=2.5
///     check: 4 frames, 4 expected: 1 differing, 0 missing, 0 extra: FAILED
///
/// A broken stream (a cut or oversized frame) also fails the check.
///
/// Example: `show --no-index` once to record the expected file, `check` ever after:
///
///     ... | s3res-frames show --no-index --format text > expected.txt
///     ... | s3res-frames check --format text --expect expected.txt
#[derive(Parser)]
#[command(verbatim_doc_comment)]
struct CheckArgs {
    /// The expected lines, one per frame.
    #[arg(long, value_name = "FILE")]
    expect: PathBuf,
    /// How a frame becomes a line: hex, text, or layout:SPEC (see `show --help`).
    #[arg(long, value_name = "FORMAT", default_value = "text")]
    format: String,
    /// The input port to read.
    #[arg(long, value_name = "NAME", default_value = "in")]
    port: String,
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    replica_rt::init_logging("frames");
    match cli.command {
        Command::Send(s) => send(s),
        Command::Show(s) => show(s),
        Command::Check(c) => check(c),
    }
}

fn send(cli: SendArgs) -> Result<()> {
    let number = parse_encoding_name(&cli.encoding)?;
    let encoding = match (cli.encoding.as_str(), number, &cli.layout) {
        ("json", _, Some(spec)) => {
            let layout = parse_layout(spec)?;
            let size = cli.size.unwrap_or(layout.min_frame());
            if size < layout.min_frame() {
                bail!(
                    "--size {size} is too small for the layout, whose last field ends at byte {}",
                    layout.min_frame()
                );
            }
            Encoding::JsonLayout { layout, size }
        }
        (_, _, Some(_)) => bail!("--layout goes with --as json (a JSON value per line)"),
        ("json", _, None) => Encoding::Json,
        (_, Some(ty), None) => Encoding::Numbers(ty),
        _ => Encoding::Text,
    };
    if !cli.rate.is_finite() || cli.rate < 0.0 {
        bail!(
            "--rate {} is not a rate: give frames per second, or 0 for no pacing",
            cli.rate
        );
    }
    let period = match cli.rate {
        0.0 => None,
        hz => Some(
            Duration::try_from_secs_f64(1.0 / hz)
                .with_context(|| format!("--rate {hz} is too slow to pace"))?,
        ),
    };
    let (reader, source): (Box<dyn BufRead>, String) = match &cli.from {
        Some(path) => (
            Box::new(BufReader::new(File::open(path).with_context(|| {
                format!("cannot open --from {}", path.display())
            })?)),
            path.display().to_string(),
        ),
        None => (Box::new(std::io::stdin().lock()), "stdin".to_owned()),
    };
    let mut rt = replica_rt::init().context("starting the s3res runtime")?;
    if cli.from.is_none() && rt.mode() != replica_rt::Mode::Standalone {
        tracing::warn!(
            "reading lines from stdin, which s3res-bootstrap connects to /dev/null: \
             give the lines with --from FILE"
        );
    }
    let mut out = rt
        .output(&cli.port)
        .with_context(|| format!("opening output port `{}`", cli.port))?;
    if let Encoding::JsonLayout { layout, size } = &encoding {
        if *size > out.max_frame() {
            bail!(
                "frames of the layout are {size} bytes, more than port `{}` allows ({})",
                cli.port,
                out.max_frame()
            );
        }
        tracing::debug!(fields = layout.len(), size, "laying out JSON values");
    }
    tracing::debug!(from = %source, encoding = %cli.encoding, rate = cli.rate, port = %cli.port, "sending");
    let start = Instant::now();
    let (mut sent, mut line_no) = (0u64, 0u64);
    let mut reader = reader;
    let (mut line, mut frame) = (Vec::new(), Vec::new());
    loop {
        line.clear();
        let n = reader
            .read_until(b'\n', &mut line)
            .with_context(|| format!("reading {source} after line {line_no}"))?;
        if n == 0 {
            break;
        }
        line_no += 1;
        if line.last() == Some(&b'\n') {
            line.pop();
            if line.last() == Some(&b'\r') {
                line.pop();
            }
        }
        let send_it = encoding.encode(&line, &mut frame).map_err(|e| {
            anyhow::anyhow!(
                "{source}:{line_no}: {e}\n  the line: {}",
                String::from_utf8_lossy(&line)
            )
        })?;
        if !send_it {
            continue;
        }
        if frame.len() > out.max_frame() {
            bail!(
                "{source}:{line_no}: the frame is {} bytes, more than port `{}` allows ({})",
                frame.len(),
                cli.port,
                out.max_frame()
            );
        }
        if let Some(period) = period {
            let due = due_at(start, period, sent)
                .with_context(|| format!("frame {sent} is due beyond the clock's range"))?;
            let now = Instant::now();
            if due > now {
                std::thread::sleep(due - now);
            }
        }
        out.send(&frame)
            .with_context(|| format!("sending frame {sent} ({source}:{line_no})"))?;
        sent += 1;
    }
    // Dropping the port closes it: the reader sees the end of the stream.
    drop(out);
    tracing::debug!(frames = sent, lines = line_no, elapsed = ?start.elapsed(), "end of input; port closed");
    Ok(())
}

/// Receives every frame of `port` and hands it, rendered by `format`, to `each` with its index.
/// Returns the number of frames, or the stream's error after handing over what arrived.
fn receive(
    port: &str,
    format: &Format,
    mut each: impl FnMut(u64, &str) -> Result<bool>,
) -> Result<u64> {
    let mut rt = replica_rt::init().context("starting the s3res runtime")?;
    let mut input = rt
        .input(port)
        .with_context(|| format!("opening input port `{port}`"))?;
    let mut line = String::new();
    let mut index = 0u64;
    let mut short = 0u64;
    loop {
        let frame = match input.recv() {
            Ok(Some(frame)) => frame,
            Ok(None) => break,
            Err(e) => {
                return Err(anyhow::Error::from(e)
                    .context(format!("port `{port}` broke after {index} frames")))
            }
        };
        if !format.render(frame, &mut line) {
            short += 1;
            if short == 1 {
                tracing::warn!(index, len = frame.len(), "a frame too short for the layout");
            }
        }
        if !each(index, &line)? {
            break;
        }
        index += 1;
    }
    if short > 0 {
        tracing::warn!(short, "frames too short for the layout");
    }
    tracing::debug!(frames = index, "end of stream");
    Ok(index)
}

fn show(cli: ShowArgs) -> Result<()> {
    let format = Format::parse(&cli.format)?;
    let (mut sink, dest): (Box<dyn Write>, String) = match &cli.out {
        Some(path) => (
            Box::new(
                File::create(path).with_context(|| format!("cannot create {}", path.display()))?,
            ),
            path.display().to_string(),
        ),
        None => (Box::new(std::io::stdout().lock()), "stdout".to_owned()),
    };
    let mut text = String::new();
    receive(&cli.port, &format, |index, line| {
        text.clear();
        if !cli.no_index {
            text.push_str(&index.to_string());
            if !line.is_empty() {
                text.push(' ');
            }
        }
        text.push_str(line);
        text.push('\n');
        // One write and a flush per frame: whoever watches sees each frame as it comes.
        match sink.write_all(text.as_bytes()).and_then(|()| sink.flush()) {
            Ok(()) => Ok(true),
            // Whoever read the lines has gone (`| head`): stop quietly.
            Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => {
                tracing::debug!("{dest} closed; stopping");
                Ok(false)
            }
            Err(e) => Err(anyhow::Error::from(e).context(format!("writing to {dest}"))),
        }
    })?;
    Ok(())
}

fn check(cli: CheckArgs) -> Result<()> {
    let format = Format::parse(&cli.format)?;
    let text = std::fs::read(&cli.expect)
        .with_context(|| format!("cannot read --expect {}", cli.expect.display()))?;
    let text = String::from_utf8(text).with_context(|| {
        format!(
            "--expect {} is not UTF-8 text (use --format hex for binary frames)",
            cli.expect.display()
        )
    })?;
    let mut lines = LineCheck::new(&text);
    let received = receive(&cli.port, &format, |_, line| {
        lines.frame(line);
        Ok(true)
    });
    let report = lines.finish();
    match received {
        Ok(_) if report.ok() => {
            println!("{report}");
            Ok(())
        }
        Ok(_) => {
            println!("{report}");
            std::process::exit(1);
        }
        Err(e) => {
            if !report.ok() {
                println!("{report}");
            }
            println!("check: the stream broke: {e:#}: FAILED");
            std::process::exit(1);
        }
    }
}
