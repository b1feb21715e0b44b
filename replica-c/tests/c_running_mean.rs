//! The C example, `examples/c-running-mean/running_mean.c`, compiled here with the system's C
//! compiler and linked against the static library: it answers exactly as the Rust running mean
//! does (by hand, and as the doc shows it), and under TMR, run by the real `s3res-bootstrap`,
//! it keeps every answer exact through kills, SIGSTOPs and corrupted frames, each repaired by
//! fork with its state (count and sum) intact.

mod common;

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use common::{compile, Link};
use s3res_testkit::{signals, EventKind, RecoveryMethod, Rng, RunningSystem, System};

const DOC: &str = include_str!("../../docs/writing-a-component.md");
const EXAMPLE: &str = include_str!("../../examples/c-running-mean/running_mean.c");

const COMPONENT: &str = "c-running-mean";
const LIMIT: Duration = Duration::from_secs(240);

/// Compiles the example into `dir` (static library, as a deployed component would be).
fn build_example(dir: &Path) -> PathBuf {
    common::require_compiler("cc");
    let exe = dir.join("s3res-c-running-mean");
    let source = common::repo_root().join("examples/c-running-mean/running_mean.c");
    compile("cc", &[source], &exe, Link::Static, &["-std=c11"]);
    exe
}

/// One frame per sample: the f64, little-endian.
fn sample_frames(samples: &[f64]) -> Vec<u8> {
    let payloads: Vec<[u8; 8]> = samples.iter().map(|x| x.to_le_bytes()).collect();
    let borrowed: Vec<&[u8]> = payloads.iter().map(|p| &p[..]).collect();
    common::frames(&borrowed)
}

/// `n` samples of either sign between about 2^4 and 2^44 in magnitude, most with a fraction,
/// so that the running mean rounds.
fn random_samples(rng: &mut Rng, n: usize) -> Vec<f64> {
    let mut out = Vec::with_capacity(n);
    while out.len() < n {
        let scale = (-(rng.range(20, 60) as f64)).exp2();
        out.push(rng.next_u64() as i64 as f64 * scale);
    }
    out
}

/// Every answer frame is count then mean, equal bit for bit to sum += x; count += 1;
/// mean = sum / count over `samples`: every sample answered once, in order, state continuous.
fn assert_exact(stdout: &[u8], samples: &[f64]) {
    let answers = common::parse_frames(stdout);
    assert_eq!(answers.len(), samples.len(), "number of answers");
    let (mut count, mut sum) = (0u64, 0.0f64);
    for (i, (a, x)) in answers.iter().zip(samples).enumerate() {
        sum += x;
        count += 1;
        let mean = sum / count as f64;
        let mut want = count.to_le_bytes().to_vec();
        want.extend_from_slice(&mean.to_le_bytes());
        assert_eq!(a, &want, "answer {i} (want count {count}, mean {mean})");
    }
}

#[test]
fn the_doc_shows_the_c_example_verbatim() {
    assert!(
        DOC.contains(&format!("```c\n{EXAMPLE}```\n")),
        "docs/writing-a-component.md must show examples/c-running-mean/running_mean.c \
         verbatim, in a ```c block; copy the file into the doc again"
    );
}

/// By hand, with the doc's port map: the same answers as the Rust component, and a bad frame
/// ends it with a clear message and status 1; `--help` answers without ports.
#[test]
#[cfg_attr(not(s3res_cc), ignore = "no C compiler (`cc`) on this machine")]
fn the_c_example_answers_exactly_by_hand() {
    let dir = tempfile::tempdir().unwrap();
    let exe = build_example(dir.path());
    let ports = r#"{"ports":[{"name":"samples","dir":"in","fd":0,"max_frame":65536},{"name":"mean","dir":"out","fd":1,"max_frame":65536}]}"#;
    let by_hand = |stdin: Vec<u8>| {
        let mut cmd = Command::new(&exe);
        cmd.env("S3RES_PORTS", ports)
            .env_remove("S3RES_VOTER_SOCKET")
            .env_remove("S3RES_REPLICA")
            .env_remove("S3RES_COMPONENT");
        common::run(&mut cmd, &stdin)
    };
    let mut rng = Rng::from_env();
    let samples = random_samples(&mut rng, 300);
    let out = by_hand(sample_frames(&samples));
    assert!(
        out.status.success(),
        "{}: {}",
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    assert_exact(&out.stdout, &samples);

    let mut bytes = sample_frames(&samples[..2]);
    bytes.extend_from_slice(&[3, 0, 0, 0, b'a', b'b', b'c']);
    let out = by_hand(bytes);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains("a sample frame must be 8 bytes (one f64), got 3"),
        "{stderr}"
    );
    assert_exact(&out.stdout, &samples[..2]);

    // Without S3RES_PORTS only `in`/`out` exist: the runtime's message, status 1.
    let mut cmd = Command::new(&exe);
    cmd.env_remove("S3RES_PORTS")
        .env_remove("S3RES_VOTER_SOCKET");
    let out = common::run(&mut cmd, &[]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains("Error: opening port `samples`: no input port named \"samples\""),
        "{stderr}"
    );

    let out = common::run(Command::new(&exe).arg("--help"), &[]);
    assert!(out.status.success());
    assert!(String::from_utf8_lossy(&out.stdout).contains("running mean"));
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Fault {
    Kill,
    Stop,
    Sdc,
    /// The control-flow-error hook (signal 36, glibc's SIGRTMIN+2): the replica spins in the
    /// handler.
    Cfe,
}

impl Fault {
    fn detected_as(self) -> EventKind {
        match self {
            Fault::Kill => EventKind::Crash,
            Fault::Stop => EventKind::Hang,
            Fault::Sdc => EventKind::Sdc,
            Fault::Cfe => EventKind::Hang,
        }
    }
}

/// Each of `FAULTS_PER_KIND` SIGKILLs, SIGSTOPs and SDC signals (a random bit of the next
/// answer), and `CFE_FAULTS` control-flow errors, hits a random replica, in a random order,
/// while samples flow; each must be detected as what it is (`crash`, `hang`, `sdc`, `hang`) in
/// that replica and repaired by fork with the state
/// kept, and at the end every answer is exact: each sample answered once, in order, with the
/// count and the mean continuous through all repairs.
#[test]
#[cfg_attr(not(s3res_cc), ignore = "no C compiler (`cc`) on this machine")]
fn the_c_example_keeps_its_mean_through_kills_stops_and_corruptions_under_tmr() {
    const FAULTS_PER_KIND: usize = 30;
    /// A few control-flow errors as well: the C component has that hook too.
    const CFE_FAULTS: usize = 5;
    const CHUNK: usize = 5;
    const TAIL: usize = 30;
    let mut rng = Rng::from_env();
    let sys = System::new();
    let exe = build_example(sys.dir());
    let (mut run, mut writer) = common::start_fed_system(sys, COMPONENT, &exe, 300_000);

    let kinds = [Fault::Kill, Fault::Stop, Fault::Sdc];
    let mut faults: Vec<Fault> = (0..kinds.len() * FAULTS_PER_KIND)
        .map(|i| kinds[i % kinds.len()])
        .chain((0..CFE_FAULTS).map(|_| Fault::Cfe))
        .collect();
    for i in (1..faults.len()).rev() {
        faults.swap(i, rng.below(i as u64 + 1) as usize);
    }
    let samples = random_samples(&mut rng, 20 + faults.len() * CHUNK + TAIL);
    let mut sent = 0;
    let mut feed = |run: &mut RunningSystem, n: usize| {
        writer
            .write_all(&sample_frames(&samples[sent..sent + n]))
            .expect("writing samples");
        sent += n;
        run.wait_for_stdout_frames(sent, Duration::from_secs(60));
    };
    // Every replica has answered before the first fault: each is a donor that keeps state.
    feed(&mut run, 20);

    for (i, &fault) in faults.iter().enumerate() {
        let slot = rng.below(3) as usize;
        let pid = run.replica_pids(COMPONENT)[&slot];
        match fault {
            Fault::Kill => s3res_testkit::kill_pid(pid, libc::SIGKILL).expect("SIGKILL"),
            Fault::Stop => s3res_testkit::kill_pid(pid, libc::SIGSTOP).expect("SIGSTOP"),
            Fault::Cfe => s3res_testkit::kill_pid(pid, signals::inject_cfe()).expect("signal 36"),
            Fault::Sdc => {
                let bit = rng.below(128) as i32;
                s3res_testkit::sigqueue(pid, signals::INJECT_SDC, bit).expect("sigqueue")
            }
        }
        // A stopped or corrupted replica shows itself on the next samples.
        feed(&mut run, CHUNK);
        let seen = run.wait_for_event(
            |e| e.component == COMPONENT && e.pid == Some(pid) && e.kind != EventKind::Start,
            Duration::from_secs(30),
        );
        assert_eq!(
            seen.kind,
            fault.detected_as(),
            "fault {i} ({fault:?} into replica {slot}, pid {pid}) seen as {seen:?}"
        );
        assert_eq!(seen.replica, Some(slot), "{seen:?}");
        let rec = run.wait_for_recovery(COMPONENT, slot, pid);
        assert_eq!(rec.method, Some(RecoveryMethod::Fork), "{rec:?}");
        assert_eq!(rec.state_lost, Some(false), "{rec:?}");
    }
    feed(&mut run, TAIL);
    drop(writer);

    let out = run.wait_success(LIMIT);
    for (kind, want) in [
        (EventKind::Crash, FAULTS_PER_KIND),
        (EventKind::Hang, FAULTS_PER_KIND + CFE_FAULTS),
        (EventKind::Sdc, FAULTS_PER_KIND),
    ] {
        let n = s3res_testkit::of_kind(&out.events, COMPONENT, kind).len();
        assert_eq!(n, want, "{kind:?} events");
    }
    let others: Vec<_> = out
        .events
        .iter()
        .filter(|e| {
            !matches!(
                e.kind,
                EventKind::Start
                    | EventKind::Recovery
                    | EventKind::Crash
                    | EventKind::Hang
                    | EventKind::Sdc
            )
        })
        .collect();
    assert!(others.is_empty(), "faults nobody injected: {others:?}");
    let bytes = std::fs::read(run.path("stdout.txt")).expect("bootstrap's stdout");
    assert_exact(&bytes, &samples);
}
