//! `docs/writing-a-component.md` is true: it shows the example component's source verbatim, its
//! system description runs (TMR, stdin → running-mean → stdout) and gives exactly the documented
//! answers, the by-hand `S3RES_PORTS` command works, and the component keeps its state through a
//! recovery by fork.

use std::fs::{File, OpenOptions};
use std::io::{Read, Write};
use std::os::unix::fs::OpenOptionsExt;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use s3res_testkit::{signals, EventKind, RecoveryMethod, Rng, RunningSystem, System};

const DOC: &str = include_str!("../../docs/writing-a-component.md");
const MAIN_RS: &str = include_str!("../../examples/running-mean/src/main.rs");
const CARGO_TOML: &str = include_str!("../../examples/running-mean/Cargo.toml");
const EXAMPLE_JSON: &str = include_str!("../../examples/running-mean/running-mean.json");

const COMPONENT: &str = "running-mean";
/// Bytes of one answer frame on the wire: 4 of header, 8 of count, 8 of mean.
const ANSWER_WIRE: usize = 20;
const LIMIT: Duration = Duration::from_secs(120);

/// The fenced code block of language `lang` in the doc that contains `needle`.
fn doc_block(lang: &str, needle: &str) -> &'static str {
    let fence = format!("```{lang}\n");
    let mut rest = DOC;
    while let Some(start) = rest.find(&fence) {
        let body = &rest[start + fence.len()..];
        let end = body
            .find("\n```")
            .expect("unterminated code block in the doc");
        let block = &body[..end + 1];
        if block.contains(needle) {
            return block;
        }
        rest = &body[end + 4..];
    }
    panic!("docs/writing-a-component.md has no ```{lang} block containing {needle:?}");
}

/// Sample frames: a 4-byte little-endian length (8), then the f64, little-endian.
fn sample_frames(samples: &[f64]) -> Vec<u8> {
    let mut out = Vec::with_capacity(samples.len() * 12);
    for x in samples {
        out.extend_from_slice(&8u32.to_le_bytes());
        out.extend_from_slice(&x.to_le_bytes());
    }
    out
}

/// Samples of mixed sign and magnitude, some with fractions, so the running mean rounds.
fn random_samples(rng: &mut Rng, n: usize) -> Vec<f64> {
    (0..n)
        .map(|_| {
            let mantissa = rng.next_u64() as i64 as f64;
            mantissa / (1u64 << rng.range(20, 60)) as f64
        })
        .collect()
}

/// What the component must answer, computed in the same order: sum += x; count += 1;
/// mean = sum / count.
fn reference(samples: &[f64]) -> Vec<(u64, f64)> {
    let (mut count, mut sum) = (0u64, 0.0f64);
    samples
        .iter()
        .map(|x| {
            sum += x;
            count += 1;
            (count, sum / count as f64)
        })
        .collect()
}

/// Parses answer frames; panics on anything that is not a whole 16-byte answer.
fn parse_answers(mut bytes: &[u8]) -> Vec<(u64, f64)> {
    let mut out = Vec::new();
    while !bytes.is_empty() {
        assert!(bytes.len() >= 4, "a partial frame header at the end");
        let len = u32::from_le_bytes(bytes[..4].try_into().unwrap()) as usize;
        assert_eq!(len, 16, "answer {} has {len} bytes, not 16", out.len() + 1);
        assert!(bytes.len() >= 4 + len, "a partial answer at the end");
        let count = u64::from_le_bytes(bytes[4..12].try_into().unwrap());
        let mean = f64::from_le_bytes(bytes[12..20].try_into().unwrap());
        out.push((count, mean));
        bytes = &bytes[4 + len..];
    }
    out
}

/// Every answer equal to the reference, bit for bit.
fn assert_exact(got: &[(u64, f64)], samples: &[f64]) {
    let want = reference(samples);
    assert_eq!(got.len(), want.len(), "number of answers");
    for (i, (g, w)) in got.iter().zip(&want).enumerate() {
        assert!(
            g.0 == w.0 && g.1.to_bits() == w.1.to_bits(),
            "answer {i}: got {g:?}, want {w:?}"
        );
    }
}

fn stdout_bytes(run: &RunningSystem) -> Vec<u8> {
    std::fs::read(run.path("stdout.txt")).expect("reading bootstrap's stdout")
}

#[test]
fn the_doc_shows_the_example_verbatim() {
    let main_block = format!("```rust\n{MAIN_RS}```\n");
    assert!(
        DOC.contains(&main_block),
        "docs/writing-a-component.md must show examples/running-mean/src/main.rs verbatim, \
         in a ```rust block; copy the file into the doc again"
    );
    let json_block = format!("```json\n{EXAMPLE_JSON}```\n");
    assert!(
        DOC.contains(&json_block),
        "docs/writing-a-component.md must show examples/running-mean/running-mean.json \
         verbatim, in a ```json block; copy the file into the doc again"
    );
    let toml_block = format!("```toml\n{CARGO_TOML}```\n");
    assert!(
        DOC.contains(&toml_block),
        "docs/writing-a-component.md must show examples/running-mean/Cargo.toml verbatim, \
         in a ```toml block; copy the file into the doc again"
    );
}

/// The description in the doc, run as the doc says: samples on bootstrap's stdin, answers on
/// its stdout, every answer exact.
#[test]
fn the_documented_tmr_system_gives_every_running_mean_exactly() {
    let description = doc_block("json", "\"redundancy\": \"tmr\"");
    assert!(description.contains(r#""from": "stdin""#), "{description}");
    assert!(description.contains(r#""to": "stdout""#), "{description}");
    assert!(
        description.contains(r#""exec": "s3res-running-mean""#),
        "{description}"
    );

    let mut rng = Rng::from_env();
    let samples = random_samples(&mut rng, 500);
    let mut run = System::new()
        .stdin(sample_frames(&samples))
        .start(description);
    let out = run.wait(LIMIT);
    assert!(
        out.status.success(),
        "bootstrap failed ({}):\n{}",
        out.status,
        s3res_testkit::tail(&out.stderr, 30)
    );
    run.assert_nothing_left();

    let starts = out
        .events
        .iter()
        .filter(|e| e.component == COMPONENT && e.kind == EventKind::Start)
        .count();
    assert_eq!(starts, 3, "TMR starts three replicas: {:?}", out.events);
    let faults: Vec<_> = out
        .events
        .iter()
        .filter(|e| e.kind != EventKind::Start)
        .collect();
    assert!(faults.is_empty(), "no fault was injected: {faults:?}");
    assert_exact(&parse_answers(&stdout_bytes(&run)), &samples);
}

/// The doc's by-hand command line (section "Running it by hand"): the port map it exports
/// makes stdin the port `samples` and stdout the port `mean`.
const BY_HAND_PORTS: &str = r#"{"ports":[{"name":"samples","dir":"in","fd":0,"max_frame":65536},{"name":"mean","dir":"out","fd":1,"max_frame":65536}]}"#;

fn run_by_hand(ports: Option<&str>, stdin: Vec<u8>) -> std::process::Output {
    run_tool("s3res-running-mean", &[], ports, stdin)
}

/// A child killed and reaped when dropped (a test that fails midway leaves nothing behind).
struct Reaped(std::process::Child);

impl Drop for Reaped {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Runs the workspace executable `name` with `args`, the port map `ports` (standalone without
/// one) and `stdin`, as a user would by hand; bounded in time.
fn run_tool(
    name: &str,
    args: &[&str],
    ports: Option<&str>,
    stdin: Vec<u8>,
) -> std::process::Output {
    let mut cmd = Command::new(s3res_testkit::bin_path(name));
    cmd.args(args)
        .env_remove("S3RES_PORTS")
        .env_remove("S3RES_VOTER_SOCKET")
        .env_remove("S3RES_REPLICA")
        .env_remove("S3RES_COMPONENT")
        .env("RUST_BACKTRACE", "0")
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    if let Some(p) = ports {
        cmd.env("S3RES_PORTS", p);
    }
    let mut child = Reaped(
        cmd.spawn()
            .unwrap_or_else(|e| panic!("starting {name}: {e}")),
    );
    let mut input = child.0.stdin.take().unwrap();
    let writer = std::thread::spawn(move || {
        // The component may stop reading (bad frame): a broken pipe is expected then.
        let _ = input.write_all(&stdin);
    });
    let drain = |mut r: Box<dyn Read + Send>| {
        std::thread::spawn(move || {
            let mut v = Vec::new();
            let _ = r.read_to_end(&mut v);
            v
        })
    };
    let stdout = drain(Box::new(child.0.stdout.take().unwrap()));
    let stderr = drain(Box::new(child.0.stderr.take().unwrap()));
    let deadline = Instant::now() + LIMIT;
    let status = loop {
        if let Some(st) = child.0.try_wait().expect("waitpid") {
            break st;
        }
        assert!(
            Instant::now() < deadline,
            "{name} did not end within {LIMIT:?}"
        );
        std::thread::sleep(Duration::from_millis(5));
    };
    writer.join().unwrap();
    std::process::Output {
        status,
        stdout: stdout.join().unwrap(),
        stderr: stderr.join().unwrap(),
    }
}

/// The doc's lines of `s3res-frames`: the samples it sends, and how it shows the answers.
const DOC_SEND: &str =
    "printf '1\\n2\\n3\\n10\\n' | target/release/s3res-frames send --as f64 \\\n";
const DOC_SHOW: &str = "  | target/release/s3res-frames show --format layout:count:u64,mean:f64\n";
const DOC_SAMPLES: &str = "1\n2\n3\n10\n";
const DOC_SHOWN: &str =
    "0 count=1 mean=1.0\n1 count=2 mean=1.5\n2 count=3 mean=2.0\n3 count=4 mean=4.0\n";

/// `s3res-frames send --as f64` of the doc's samples: the frames bootstrap gets on stdin.
fn doc_sample_frames() -> Vec<u8> {
    let out = run_tool(
        "s3res-frames",
        &["send", "--as", "f64"],
        None,
        DOC_SAMPLES.as_bytes().to_vec(),
    );
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(out.stdout, sample_frames(&[1.0, 2.0, 3.0, 10.0]));
    out.stdout
}

/// `s3res-frames show --format layout:count:u64,mean:f64` of answer frames.
fn show_answers(frames: Vec<u8>) -> String {
    let out = run_tool(
        "s3res-frames",
        &["show", "--format", "layout:count:u64,mean:f64"],
        None,
        frames,
    );
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).unwrap()
}

/// Section 5's pipeline, `s3res-frames send | s3res-bootstrap | s3res-frames show`, prints
/// exactly the lines the doc says (bootstrap run by the harness, its stdin and stdout the
/// pipeline's middle).
#[test]
fn the_documented_pipeline_prints_the_documented_lines() {
    assert!(
        DOC.contains(&format!(
            "{DOC_SEND}  | target/release/s3res-bootstrap --events events.jsonl \
             examples/running-mean/running-mean.json \\\n{DOC_SHOW}"
        )),
        "the doc's pipeline changed; update DOC_SEND/DOC_SHOW"
    );
    assert!(
        DOC.contains(&format!("```\n{DOC_SHOWN}```\n")),
        "the doc's output changed; update DOC_SHOWN"
    );
    let mut run = System::new().stdin(doc_sample_frames()).start(EXAMPLE_JSON);
    run.wait_success(LIMIT);
    assert_eq!(show_answers(stdout_bytes(&run)), DOC_SHOWN);
}

#[test]
fn the_by_hand_command_works_and_a_bad_frame_ends_it_cleanly() {
    assert!(
        DOC.contains(&format!("ports='{BY_HAND_PORTS}'")),
        "the doc's by-hand port map changed; update BY_HAND_PORTS"
    );
    assert!(
        DOC.contains(&format!(
            "{DOC_SEND}  | S3RES_PORTS=\"$ports\" target/release/s3res-running-mean \\\n{DOC_SHOW}"
        )),
        "the doc's by-hand pipeline changed"
    );
    // The doc's pipeline, stage by stage: the same four lines as through bootstrap.
    let out = run_by_hand(Some(BY_HAND_PORTS), doc_sample_frames());
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(show_answers(out.stdout), DOC_SHOWN);
    // The doc's bad frame: `echo abc | s3res-frames send` is the 3-byte frame below.
    let abc = run_tool("s3res-frames", &["send"], None, b"abc\n".to_vec());
    assert_eq!(abc.stdout, [3, 0, 0, 0, b'a', b'b', b'c']);
    let samples = [1.0, 2.0, 3.0, 10.0];
    let out = run_by_hand(Some(BY_HAND_PORTS), sample_frames(&samples));
    assert!(
        out.status.success(),
        "{}: {}",
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    assert_exact(&parse_answers(&out.stdout), &samples);

    // Two good samples, then a 3-byte frame: two answers, then a clear error and status 1.
    let mut bytes = sample_frames(&samples[..2]);
    bytes.extend_from_slice(&[3, 0, 0, 0, b'a', b'b', b'c']);
    bytes.extend_from_slice(&sample_frames(&[5.0]));
    let out = run_by_hand(Some(BY_HAND_PORTS), bytes);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains("a sample frame must be 8 bytes (one f64), got 3"),
        "{stderr}"
    );
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert_exact(&parse_answers(&out.stdout), &samples[..2]);

    // Without S3RES_PORTS only `in`/`out` exist, as the doc says: a clear error, status 1.
    let out = run_by_hand(None, sample_frames(&samples));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains("no input port named \"samples\""),
        "{stderr}"
    );
    assert!(out.stdout.is_empty());
}

/// Opens the FIFO for writing once its reader (the feeder) has opened it, without blocking
/// forever if the system never gets that far; the returned file blocks on writes.
fn open_fifo_writer(path: &Path, run: &mut RunningSystem) -> File {
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        match OpenOptions::new()
            .write(true)
            .custom_flags(libc::O_NONBLOCK)
            .open(path)
        {
            Ok(f) => {
                use std::os::fd::AsRawFd;
                // SAFETY: fcntl on an fd we own; only changes its status flags.
                let rc = unsafe { libc::fcntl(f.as_raw_fd(), libc::F_SETFL, 0) };
                assert_eq!(rc, 0, "clearing O_NONBLOCK");
                return f;
            }
            Err(e) if e.raw_os_error() == Some(libc::ENXIO) => {}
            Err(e) => panic!("opening {}: {e}", path.display()),
        }
        assert!(
            run.try_status().is_none(),
            "bootstrap exited before the feeder opened the FIFO:\n{}",
            run.stderr()
        );
        assert!(
            Instant::now() < deadline,
            "the feeder never opened the FIFO"
        );
        std::thread::sleep(Duration::from_millis(10));
    }
}

/// Waits until bootstrap's stdout holds `n` answers.
fn wait_for_answers(run: &mut RunningSystem, n: usize) {
    let deadline = Instant::now() + Duration::from_secs(30);
    while stdout_bytes(run).len() < n * ANSWER_WIRE {
        assert!(
            run.try_status().is_none(),
            "bootstrap exited early:\n{}",
            run.stderr()
        );
        assert!(
            Instant::now() < deadline,
            "{n} answers did not arrive; have {} bytes",
            stdout_bytes(run).len()
        );
        std::thread::sleep(Duration::from_millis(10));
    }
}

/// A corrupted answer from one replica is outvoted, the replica is replaced by a fork of a
/// healthy one, and the new replica carries on with the same count and sum: bootstrap's stdout
/// is still exact, and no further disagreement follows the recovery.
///
/// The harness feeds stdin from a file, which is read to the end before a test could inject
/// anything, so the samples come from a FIFO this test writes, through a small unprotected
/// feeder (`cat FIFO` onto its output port, fd 3) instead of bootstrap's stdin.
#[test]
fn a_corrupted_replica_is_outvoted_and_replaced_without_losing_the_mean() {
    let mut rng = Rng::from_env();
    let samples = random_samples(&mut rng, 600);
    let (first, rest) = samples.split_at(200);
    let (second, third) = rest.split_at(200);

    let sys = System::new();
    let fifo = sys.path("samples.fifo");
    let c_path = std::ffi::CString::new(fifo.to_str().unwrap()).unwrap();
    // SAFETY: a valid NUL-terminated path.
    assert_eq!(unsafe { libc::mkfifo(c_path.as_ptr(), 0o600) }, 0, "mkfifo");
    let feeder = format!("exec cat '{}' >&3", fifo.display());
    let description = serde_json::json!({
        "name": "running-mean-sdc",
        "components": {
            "feeder": { "exec": "/bin/sh", "args": ["-c", feeder], "outputs": ["out"] },
            COMPONENT: {
                "exec": "s3res-running-mean",
                "redundancy": "tmr",
                "timeout_us": 250000,
                "inputs": ["samples"],
                "outputs": ["mean"]
            }
        },
        "channels": [
            { "from": "feeder.out", "to": "running-mean.samples" },
            { "from": "running-mean.mean", "to": "stdout" }
        ]
    });
    let mut run = sys.start_json(&description);
    let mut writer = open_fifo_writer(&fifo, &mut run);

    writer.write_all(&sample_frames(first)).unwrap();
    wait_for_answers(&mut run, first.len());
    let pids = run.replica_pids(COMPONENT);
    assert_eq!(pids.len(), 3, "{pids:?}");
    let slot = 1;
    let pid = pids[&slot];
    // Bit 7 of the first payload byte: the low byte of the count in the next answer.
    s3res_testkit::sigqueue(pid, signals::INJECT_SDC, 7).expect("sigqueue");

    writer.write_all(&sample_frames(second)).unwrap();
    let sdc = run.wait_for_event(|e| e.kind == EventKind::Sdc, Duration::from_secs(30));
    assert_eq!(sdc.replica, Some(slot), "{sdc:?}");
    assert_eq!(sdc.pid, Some(pid), "{sdc:?}");
    let rec = run.wait_for_event(
        |e| e.kind == EventKind::Recovery && e.pid == Some(pid),
        Duration::from_secs(30),
    );
    assert_eq!(rec.replica, Some(slot), "{rec:?}");
    assert_eq!(rec.method, Some(RecoveryMethod::Fork), "{rec:?}");
    assert_eq!(rec.state_lost, Some(false), "{rec:?}");

    // After the recovery: a replica that had lost count and sum would disagree from here on.
    writer.write_all(&sample_frames(third)).unwrap();
    drop(writer);
    let out = run.wait(LIMIT);
    assert!(
        out.status.success(),
        "bootstrap failed ({}):\n{}",
        out.status,
        s3res_testkit::tail(&out.stderr, 30)
    );
    run.assert_nothing_left();
    let faults: Vec<_> = out
        .events
        .iter()
        .filter(|e| !matches!(e.kind, EventKind::Start | EventKind::Recovery))
        .collect();
    assert_eq!(faults.len(), 1, "exactly the injected fault: {faults:?}");
    let mut bytes = Vec::new();
    File::open(run.path("stdout.txt"))
        .unwrap()
        .read_to_end(&mut bytes)
        .unwrap();
    assert_exact(&parse_answers(&bytes), &samples);
}

/// The documented system with its stdout on a full device (`> /dev/full`): none of the
/// answers can be written, and the run fails in one line that says so. Before, the voter took
/// the write error for a reader gone away ("downstream is gone"), and the run "ran clean",
/// exit 0, with none of 2000 answers written.
#[test]
fn a_stdout_that_cannot_be_written_fails_the_run() {
    let description = doc_block("json", "\"redundancy\": \"tmr\"");
    let mut rng = Rng::from_env();
    let samples = random_samples(&mut rng, 200);
    let full = std::fs::OpenOptions::new()
        .write(true)
        .open("/dev/full")
        .expect("opening /dev/full");
    let mut run = System::new()
        .stdin(sample_frames(&samples))
        .stdout_file(full)
        .start(description);
    let out = run.wait(LIMIT);
    assert_eq!(
        out.status.code(),
        Some(1),
        "{}",
        s3res_testkit::tail(&out.stderr, 30)
    );
    assert!(
        out.stderr
            .contains("s3res-voter: output `mean` could not be written: No space left on device"),
        "{}",
        s3res_testkit::tail(&out.stderr, 30)
    );
    assert!(!out.stderr.contains("ran clean"), "{}", out.stderr);
    // Every replica answered: no frame is a `lost` one (which the verdict counts as such).
    assert!(
        !out.stderr.contains("lost (no replica answered)"),
        "{}",
        out.stderr
    );
    run.assert_nothing_left();
}
