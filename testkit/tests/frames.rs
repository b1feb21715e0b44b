//! `s3res-frames` as a component of real systems: `send` feeds a protected component from a
//! file, `check` compares what comes out with an expected file (and fails, naming the first
//! difference, when it differs), `show` prints the fields of a layout. Every system runs under
//! the real `s3res-bootstrap`; the harness kills and reaps everything on drop.

use std::time::Duration;

use s3res_testkit::{of_kind, tail, EventKind, Outcome, RunningSystem, System};

const LIMIT: Duration = Duration::from_secs(120);
const MEAN_LAYOUT: &str = "layout:count:u64,mean:f64";

/// Samples of mixed sign, some fractional, so that the running mean rounds.
fn samples(n: usize) -> Vec<f64> {
    (0..n)
        .map(|i| (i as f64 * 0.37 - 11.0) * if i % 3 == 0 { -1.0 } else { 1.0 })
        .collect()
}

/// The running mean's answers as `show`/`check` render them with [`MEAN_LAYOUT`], one line
/// each, computed as the component does (sum += x; count += 1; sum / count).
fn mean_lines(samples: &[f64]) -> Vec<String> {
    let sums = samples.iter().scan(0.0f64, |sum, x| {
        *sum += x;
        Some(*sum)
    });
    sums.zip(1u64..)
        .map(|(sum, count)| format!("count={count} mean={:?}", sum / count as f64))
        .collect()
}

/// A system: `feed` (`s3res-frames` with `send`) → `middle` (a TMR component, frames in on
/// port `ports.0`, out on `ports.1`) → `watch` (`s3res-frames` with `watch`).
fn feed_middle_watch(
    send: &[&str],
    exec: &str,
    ports: (&str, &str),
    watch: &[&str],
) -> serde_json::Value {
    let send: Vec<&str> = ["send"].iter().chain(send).copied().collect();
    serde_json::json!({
        "name": "frames",
        "components": {
            "feed": { "exec": "s3res-frames", "args": send },
            "middle": { "exec": exec, "redundancy": "tmr", "timeout_us": 250000 },
            "watch": { "exec": "s3res-frames", "args": watch }
        },
        "channels": [
            { "from": "feed.out", "to": format!("middle.{}", ports.0) },
            { "from": format!("middle.{}", ports.1), "to": "watch.in" }
        ]
    })
}

/// `s3res-frames send` from `samples.txt` → TMR running mean → `s3res-frames check` against
/// `expected.txt`, both files written from the arguments.
fn run_mean_check(samples_txt: &str, expected: &str) -> (RunningSystem, Outcome) {
    let sys = System::new();
    let samples_path = sys.path("samples.txt");
    let expected_path = sys.path("expected.txt");
    std::fs::write(&samples_path, samples_txt).unwrap();
    std::fs::write(&expected_path, expected).unwrap();
    let description = feed_middle_watch(
        &[
            "--from",
            samples_path.to_str().unwrap(),
            "--as",
            "f64",
            "--rate",
            "2000",
        ],
        "s3res-running-mean",
        ("samples", "mean"),
        &[
            "check",
            "--expect",
            expected_path.to_str().unwrap(),
            "--format",
            MEAN_LAYOUT,
        ],
    );
    let mut run = sys.start_json(&description);
    let out = run.wait(LIMIT);
    run.assert_nothing_left();
    (run, out)
}

fn as_text(samples: &[f64]) -> String {
    samples.iter().map(|x| format!("{x}\n")).collect()
}

#[test]
fn send_through_tmr_then_check_passes_on_an_exact_match() {
    let xs = samples(300);
    let expected = mean_lines(&xs).join("\n") + "\n";
    let (_run, out) = run_mean_check(&as_text(&xs), &expected);
    assert!(
        out.status.success(),
        "bootstrap failed ({}):\nstdout:\n{}\nstderr:\n{}",
        out.status,
        out.stdout,
        tail(&out.stderr, 30)
    );
    assert!(
        out.stdout
            .contains("check: 300 frames, all as expected: OK"),
        "{}",
        out.stdout
    );
    let starts = of_kind(&out.events, "middle", EventKind::Start);
    assert_eq!(starts.len(), 3, "TMR: three replicas: {:?}", out.events);
}

#[test]
fn a_mismatch_fails_the_check_naming_the_first_difference() {
    let xs = samples(50);
    let mut lines = mean_lines(&xs);
    let got_at_7 = lines[7].clone();
    lines[7] = "count=8 mean=12345.0".to_owned();
    lines.truncate(49); // the stream then has one frame more than the file
    let (_run, out) = run_mean_check(&as_text(&xs), &(lines.join("\n") + "\n"));
    assert_eq!(
        out.status.code(),
        Some(1),
        "the check fails, so does the system:\n{}\n{}",
        out.stdout,
        tail(&out.stderr, 30)
    );
    let want = format!(
        "check: first difference at frame 7 (line 8):\n  expected: count=8 mean=12345.0\n  got:      {got_at_7}\n\
         check: 50 frames, 49 expected: 1 differing, 0 missing, 1 extra: FAILED"
    );
    assert!(
        out.stdout.contains(&want),
        "want:\n{want}\ngot:\n{}",
        out.stdout
    );
    assert!(
        out.stderr.contains("component watch failed"),
        "{}",
        tail(&out.stderr, 30)
    );
}

#[test]
fn a_bad_number_stops_send_with_its_line_and_the_system_ends_cleanly() {
    let xs = samples(5);
    let mut text = as_text(&xs[..2]);
    text.push_str("2.5x\n");
    text.push_str(&as_text(&xs[2..]));
    let (_run, out) = run_mean_check(&text, &(mean_lines(&xs).join("\n") + "\n"));
    assert_eq!(out.status.code(), Some(1), "{}", tail(&out.stderr, 30));
    assert!(
        out.stderr
            .contains("samples.txt:3: `2.5x` is not a number (f64 expected)"),
        "{}",
        tail(&out.stderr, 30)
    );
    assert!(!out.stderr.contains("panicked"), "{}", out.stderr);
    // What was sent before the bad line went through; the rest is missing.
    assert!(
        out.stdout.contains(
            "first difference at frame 2 (line 3): the stream ended\n  expected: count=3"
        ) && out
            .stdout
            .contains("check: 2 frames, 5 expected: 0 differing, 3 missing, 0 extra: FAILED"),
        "{}",
        out.stdout
    );
}

#[test]
fn show_prints_the_fields_of_a_layout() {
    let layout = "seq:u32@0,x:f64@8,n:i16@16";
    let sys = System::new();
    let poses = sys.path("poses.jsonl");
    let shown = sys.path("shown.txt");
    std::fs::write(
        &poses,
        "{\"seq\": 0, \"x\": 0.5, \"n\": -3}\n\n[1, -1e300, 32767]\n{\"n\": 7, \"x\": 3, \"seq\": 4294967295}\n",
    )
    .unwrap();
    let format = format!("layout:{layout}");
    let description = feed_middle_watch(
        &[
            "--from",
            poses.to_str().unwrap(),
            "--as",
            "json",
            "--layout",
            layout,
            "--size",
            "24",
        ],
        "s3res-echo",
        ("in", "out"),
        &[
            "show",
            "--format",
            &format,
            "--out",
            shown.to_str().unwrap(),
        ],
    );
    let mut run = sys.start_json(&description);
    run.wait_success(LIMIT);
    let text = std::fs::read_to_string(run.path("shown.txt")).unwrap();
    assert_eq!(
        text,
        "0 seq=0 x=0.5 n=-3\n1 seq=1 x=-1e300 n=32767\n2 seq=4294967295 x=3.0 n=7\n"
    );
}

/// The `s3res-frames` example of `docs/system-description.md`, verbatim, passes its check with
/// `samples.txt` and `means.txt` in the folder bootstrap runs in (the doc's relative paths).
#[test]
fn the_documented_feed_and_check_example_runs_clean() {
    let path =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/system-description.md");
    let doc = std::fs::read_to_string(&path).unwrap();
    let json = doc
        .split("```json")
        .find(|block| block.contains("\"name\": \"mean-check\""))
        .and_then(|s| s.split("```").next())
        .expect("docs/system-description.md has the mean-check example");
    let xs = samples(40);
    let sys = System::new();
    std::fs::write(sys.path("samples.txt"), as_text(&xs)).unwrap();
    std::fs::write(sys.path("means.txt"), mean_lines(&xs).join("\n") + "\n").unwrap();
    let out = sys.start(json).wait_success(LIMIT);
    assert!(
        out.stdout.contains("check: 40 frames, all as expected: OK"),
        "{}",
        out.stdout
    );
}
