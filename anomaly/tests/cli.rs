//! `s3res-train` as a user runs it: write synthetic frames, train both models, check them on
//! held-out frames; bad input gets a clear error. Every child is bounded in time and reaped.

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

struct Run {
    ok: bool,
    stdout: String,
    stderr: String,
}

/// Runs s3res-train with `args` (split at spaces) in `dir`, killing it if it outlives 120 s.
fn train(dir: &Path, args: &str) -> Run {
    let args: Vec<&str> = args.split_whitespace().collect();
    let mut child = Command::new(env!("CARGO_BIN_EXE_s3res-train"))
        .args(&args)
        .current_dir(dir)
        .env("RUST_LOG", "warn")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("s3res-train starts");
    let deadline = Instant::now() + Duration::from_secs(120);
    loop {
        if child.try_wait().expect("waitpid works").is_some() {
            break;
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            let _ = child.wait();
            panic!("s3res-train {args:?} ran longer than 120 s");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let out = child.wait_with_output().expect("output is collected");
    Run {
        ok: out.status.success(),
        stdout: String::from_utf8_lossy(&out.stdout).into(),
        stderr: String::from_utf8_lossy(&out.stderr).into(),
    }
}

#[test]
fn train_and_check_both_models() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    for (seed, file) in [("1", "a.bin"), ("2", "b.bin"), ("3", "held.bin")] {
        let r = train(
            d,
            &format!("synthetic --seed {seed} --count 3000 --out {file} --layout-out layout.json"),
        );
        assert!(r.ok, "{}", r.stderr);
    }
    let r = train(
        d,
        "gaussian --layout layout.json --frames a.bin --frames b.bin --out g.json",
    );
    assert!(
        r.ok && r.stdout.contains("wrote gaussian model to g.json"),
        "{}{}",
        r.stdout,
        r.stderr
    );
    assert!(
        r.stdout
            .contains("on its 6000 training frames it alarms on 0 (0.00 per 10000)"),
        "{}",
        r.stdout
    );
    assert!(!r.stderr.contains("flags"), "{}", r.stderr);
    let r = train(
        d,
        "autoencoder --layout layout.json --frames a.bin --frames b.bin --out ae.json --seed 3 --epochs 10",
    );
    assert!(
        r.ok && r.stdout.contains("wrote autoencoder model"),
        "{}{}",
        r.stdout,
        r.stderr
    );
    let model: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.join("ae.json")).unwrap()).unwrap();
    assert_eq!(model["detector"]["kind"], "autoencoder");
    assert_eq!(model["detector"]["training"]["seed"], 3);
    assert_eq!(
        model["layout"][2],
        serde_json::json!({"name": "x", "type": "f64", "offset": 8})
    );

    for m in ["g.json", "ae.json"] {
        let r = train(d, &format!("check --model {m} --frames held.bin"));
        assert!(r.ok, "{}", r.stderr);
        assert!(
            r.stdout.contains("3000 frames, 0 alarms"),
            "{m}: {}",
            r.stdout
        );
    }
}

/// A threshold so tight that the model flags its own fault-free training frames is accepted
/// (the user asked for it) but said unusable, with the option to change.
#[test]
fn a_model_that_flags_its_own_training_frames_is_said_unusable() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let r = train(
        d,
        "synthetic --seed 4 --count 2000 --out a.bin --layout-out layout.json",
    );
    assert!(r.ok, "{}", r.stderr);
    let r = train(
        d,
        "gaussian --layout layout.json --frames a.bin --out g.json --sigmas 0.01",
    );
    assert!(r.ok, "{}", r.stderr);
    let flagged: u64 = r
        .stdout
        .split("on its 2000 training frames it alarms on ")
        .nth(1)
        .and_then(|rest| rest.split_whitespace().next()?.parse().ok())
        .unwrap_or_else(|| panic!("no alarm count: {}", r.stdout));
    assert!(flagged > 20, "{}", r.stdout);
    assert!(
        r.stderr
            .contains("of its own fault-free training frames: it will call normal frames faults; give a larger --sigmas"),
        "{}",
        r.stderr
    );
}

/// Runs s3res-train expecting it to fail with every one of `expected` in its error output.
fn refused(dir: &Path, args: &str, expected: &[&str]) {
    let r = train(dir, args);
    assert!(!r.ok, "{args} succeeded: {}", r.stdout);
    for e in expected {
        assert!(r.stderr.contains(e), "{args}: no {e:?} in {}", r.stderr);
    }
}

#[test]
fn bad_input_is_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let r = train(
        d,
        "synthetic --count 100 --out f.bin --layout-out good.json",
    );
    assert!(r.ok, "{}", r.stderr);
    let write = |name: &str, text: &str| std::fs::write(d.join(name), text).unwrap();

    write(
        "overlap.json",
        "[\n {\"name\":\"x\",\"type\":\"f64\",\"offset\":0},\n {\"name\":\"y\",\"type\":\"f64\",\"offset\":4}\n]",
    );
    refused(
        d,
        "gaussian --layout overlap.json --frames f.bin --out m.json",
        &[
            "layout overlap.json",
            "field `y` (bytes 4..12) overlaps field `x` (bytes 0..8)",
        ],
    );
    write(
        "typo.json",
        "[\n {\"name\":\"x\",\"type\":\"float\",\"offset\":0}\n]",
    );
    refused(
        d,
        "gaussian --layout typo.json --frames f.bin --out m.json",
        &["unknown variant `float`", "line 2"],
    );
    // A channel entry with a `fields` member is accepted as a layout too.
    write(
        "far.json",
        "{\"fields\": [{\"name\":\"far\",\"type\":\"u8\",\"offset\":200}]}",
    );
    refused(
        d,
        "gaussian --layout far.json --frames f.bin --out m.json",
        &["every frame is shorter than the layout needs (201 bytes)"],
    );
    std::fs::write(d.join("cut.bin"), [10u8, 0, 0, 0, 1, 2]).unwrap();
    refused(
        d,
        "gaussian --layout good.json --frames cut.bin --out m.json",
        &["frame file cut.bin, frame 0"],
    );
    // A σ floor the model could not be loaded with is refused before it is written (before,
    // NaN was written as null and `check` could not read the model).
    for floor in ["NaN", "inf", "-1"] {
        for kind in ["gaussian", "autoencoder --epochs 1"] {
            refused(
                d,
                &format!(
                    "{kind} --layout good.json --frames f.bin --out m.json --sigma-floor={floor}"
                ),
                &["must be a non-negative number"],
            );
            assert!(
                !d.join("m.json").exists(),
                "{kind} {floor}: a model was written"
            );
        }
    }
    write("notamodel.json", "{\"format\":\"x\"}");
    refused(
        d,
        "check --model notamodel.json --frames f.bin",
        &["model notamodel.json"],
    );

    let r = train(d, "--help");
    assert!(
        r.ok && r.stdout.contains("4-byte little-endian length"),
        "{}",
        r.stdout
    );
}
