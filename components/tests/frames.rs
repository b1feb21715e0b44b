//! `s3res-frames` by hand, in standalone mode (send writes frames to stdout, show and check read
//! them from stdin), as the docs use it in shell pipelines. Every process is bounded in time and
//! killed and reaped on drop, also when a test fails.

use std::io::{Read, Write};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

const LIMIT: Duration = Duration::from_secs(30);

fn frames() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_s3res-frames"));
    c.env_remove("S3RES_PORTS")
        .env_remove("S3RES_VOTER_SOCKET")
        .env_remove("S3RES_REPLICA")
        .env_remove("S3RES_COMPONENT")
        .env("RUST_BACKTRACE", "0")
        .env("RUST_LOG", "warn");
    c
}

/// A child that is killed and reaped when dropped.
struct Guard(Child);

impl Drop for Guard {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// What a finished process left.
struct Out {
    code: Option<i32>,
    stdout: String,
    stderr: String,
}

/// Reads a pipe to its end on a thread of its own (`None`: an empty pipe).
fn drain(pipe: Option<impl Read + Send + 'static>) -> std::thread::JoinHandle<String> {
    std::thread::spawn(move || {
        let mut s = Vec::new();
        if let Some(mut p) = pipe {
            let _ = p.read_to_end(&mut s);
        }
        String::from_utf8_lossy(&s).into_owned()
    })
}

/// Waits for `child` within [`LIMIT`], reading its stderr and its stdout (when still piped
/// here: a sender's stdout may have gone to the receiver).
fn finish(mut g: Guard) -> Out {
    let stdout = drain(g.0.stdout.take());
    let stderr = drain(g.0.stderr.take());
    let deadline = Instant::now() + LIMIT;
    let status = loop {
        if let Some(st) = g.0.try_wait().unwrap() {
            break st;
        }
        assert!(
            Instant::now() < deadline,
            "s3res-frames did not end within {LIMIT:?}"
        );
        std::thread::sleep(Duration::from_millis(5));
    };
    Out {
        code: status.code(),
        stdout: stdout.join().unwrap(),
        stderr: stderr.join().unwrap(),
    }
}

/// `s3res-frames ARGS` with `input` on stdin.
fn run(args: &[&str], input: &[u8]) -> Out {
    let mut g = Guard(
        frames()
            .args(args)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap(),
    );
    let mut stdin = g.0.stdin.take().unwrap();
    let input = input.to_vec();
    // The process may stop reading (a bad line): a broken pipe is expected then.
    let writer = std::thread::spawn(move || {
        let _ = stdin.write_all(&input);
    });
    let out = finish(g);
    writer.join().unwrap();
    out
}

/// `printf LINES | s3res-frames send SEND | s3res-frames RECV`: the receiver's output, and the
/// sender's.
fn pipeline(lines: &str, send: &[&str], recv: &[&str]) -> (Out, Out) {
    let mut sender = Guard(
        frames()
            .arg("send")
            .args(send)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap(),
    );
    let receiver = Guard(
        frames()
            .args(recv)
            .stdin(sender.0.stdout.take().unwrap())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap(),
    );
    let mut stdin = sender.0.stdin.take().unwrap();
    let lines = lines.as_bytes().to_vec();
    let writer = std::thread::spawn(move || {
        let _ = stdin.write_all(&lines);
    });
    let r = finish(receiver);
    let s = finish(sender);
    writer.join().unwrap();
    (r, s)
}

#[test]
fn help_teaches_with_examples() {
    let out = run(&["--help"], b"");
    assert_eq!(out.code, Some(0));
    for want in [
        "send",
        "show",
        "check",
        "s3res-frames send --as f64",
        "layout:count:u64,mean:f64",
    ] {
        assert!(out.stdout.contains(want), "{want}: {}", out.stdout);
    }
    let out = run(&["show", "--help"], b"");
    assert!(out.stdout.contains("name:type[@offset]"), "{}", out.stdout);
    let out = run(&["send", "--help"], b"");
    assert!(out.stdout.contains("--as json --layout"), "{}", out.stdout);
    let out = run(&["check", "--help"], b"");
    assert!(out.stdout.contains("first difference"), "{}", out.stdout);
}

#[test]
fn numbers_go_out_little_endian_and_come_back_as_hex() {
    let (show, send) = pipeline("1\n258\n\n65535 7\n", &["--as", "u16"], &["show"]);
    assert_eq!(send.code, Some(0), "{}", send.stderr);
    assert_eq!(show.code, Some(0), "{}", show.stderr);
    assert_eq!(show.stdout, "0 0100\n1 0201\n2 ffff0700\n");
}

#[test]
fn text_and_json_round_trip_through_show_and_check() {
    let lines = "hello\n\nwith a \\ backslash\n";
    let (show, _) = pipeline(lines, &[], &["show", "--format", "text", "--no-index"]);
    assert_eq!(show.stdout, lines);
    let dir = tempfile::tempdir().unwrap();
    let expect = dir.path().join("expected.txt");
    std::fs::write(&expect, lines).unwrap();
    let expect = expect.to_str().unwrap();
    let (check, _) = pipeline(lines, &[], &["check", "--expect", expect]);
    assert_eq!(check.code, Some(0), "{}{}", check.stdout, check.stderr);
    assert_eq!(check.stdout, "check: 3 frames, all as expected: OK\n");
    let (check, _) = pipeline(
        "hello\n\nwith a / slash\nmore\n",
        &[],
        &["check", "--expect", expect],
    );
    assert_eq!(check.code, Some(1));
    assert_eq!(
        check.stdout,
        "check: first difference at frame 2 (line 3):\n  expected: with a \\ backslash\n  \
         got:      with a / slash\ncheck: 4 frames, 3 expected: 1 differing, 0 missing, 1 extra: FAILED\n"
    );
    let (show, send) = pipeline(
        "{\"x\": 1, \"y\": -2.5}\n[3, 4]\n",
        &["--as", "json", "--layout", "x:i32,y:f32"],
        &[
            "show",
            "--format",
            "layout:[{\"name\":\"y\",\"type\":\"f32\",\"offset\":4}]",
        ],
    );
    assert_eq!(send.code, Some(0), "{}", send.stderr);
    assert_eq!(show.stdout, "0 y=-2.5\n1 y=4.0\n");
}

#[test]
fn bad_input_names_the_line_and_never_panics() {
    let (show, send) = pipeline("1.5\n2\nnope\n3\n", &["--as", "f64"], &["show"]);
    assert_eq!(send.code, Some(1));
    assert!(
        send.stderr
            .contains("stdin:3: `nope` is not a number (f64 expected)\n  the line: nope"),
        "{}",
        send.stderr
    );
    // What came before the bad line was sent, and the port closed.
    assert_eq!(show.code, Some(0), "{}", show.stderr);
    assert_eq!(show.stdout.lines().count(), 2, "{}", show.stdout);
    for (args, want) in [
        (&["send", "--as", "u12"][..], "unknown encoding"),
        (
            &["send", "--layout", "x:f64"],
            "--layout goes with --as json",
        ),
        (
            &["send", "--as", "json", "--layout", "x:f64", "--size", "4"],
            "--size 4 is too small",
        ),
        (&["send", "--rate=-1"], "is not a rate"),
        (
            &["send", "--from", "/nonexistent/lines.txt"],
            "cannot open --from /nonexistent/lines.txt",
        ),
        (&["show", "--format", "bin"], "unknown format"),
        (&["show", "--format", "layout:x:f64,x:u8"], "appears twice"),
        (
            &["check", "--expect", "/nonexistent/expected.txt"],
            "cannot read --expect",
        ),
        (&["send", "--port", "cmd"], "no output port named \"cmd\""),
    ] {
        let out = run(args, b"");
        assert_eq!(out.code, Some(1), "{args:?}: {}", out.stderr);
        assert!(out.stderr.contains(want), "{args:?}: {}", out.stderr);
        assert!(!out.stderr.contains("panicked"), "{args:?}: {}", out.stderr);
    }
    // A cut frame breaks the stream: show prints what came, then fails; check fails.
    let out = run(&["show"], &[1, 0, 0, 0, 0xab, 5, 0, 0, 0, 1]);
    assert_eq!(out.code, Some(1));
    assert_eq!(out.stdout, "0 ab\n");
    assert!(
        out.stderr.contains("broke after 1 frames"),
        "{}",
        out.stderr
    );
    let out = run(&["check", "--expect", "/dev/null"], &[9, 0]);
    assert_eq!(out.code, Some(1));
    assert!(out.stdout.contains("the stream broke"), "{}", out.stdout);
}

#[test]
fn rate_paces_the_frames() {
    let t = Instant::now();
    let (show, send) = pipeline(
        &"x\n".repeat(11),
        &["--rate", "50"],
        &["show", "--format", "text"],
    );
    assert_eq!(send.code, Some(0), "{}", send.stderr);
    assert_eq!(show.stdout.lines().count(), 11);
    // Frame 10 is due 200 ms after the first.
    assert!(
        t.elapsed() >= Duration::from_millis(200),
        "{:?}",
        t.elapsed()
    );
}
