//! What a user gets wrong with `--fault mixed`, `--bit` and classify's files is refused in
//! one line, before anything is started or written.

mod common;

use std::time::Duration;

use common::inject;

const LIMIT: Duration = Duration::from_secs(30);

/// Fails with exit status 1 and `want` on stderr.
fn refused(args: &[&str], want: &str) {
    let out = inject(args, LIMIT);
    assert!(!out.success, "{args:?} was accepted:\n{}", out.stderr);
    assert_eq!(out.code, Some(1), "{args:?}:\n{}", out.stderr);
    assert!(out.stderr.contains(want), "{args:?}:\n{}", out.stderr);
}

#[test]
fn bit_goes_with_sdc_only() {
    for fault in ["exec", "cfe", "mixed"] {
        refused(
            &[
                "inject",
                "--state",
                "no-such-state.json",
                "--component",
                "echo",
                "--fault",
                fault,
                "--bit",
                "3",
            ],
            "--bit chooses the bit of an sdc flip",
        );
    }
}

/// An option of one fault kind given with another did nothing (`--reg-bits 4 --fault exec`
/// ran the campaign with no word of it): refused, naming the option and the kinds.
#[test]
fn options_of_another_fault_kind_are_refused_not_ignored() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let out = out.to_str().unwrap();
    let cases: [(&str, &str, &[&str], &str); 4] = [
        (
            "campaign",
            "exec",
            &["--reg-bits", "4"],
            "--reg-bits applies to reg faults only, and this campaign injects exec",
        ),
        (
            "classify",
            "sdc",
            &["--var-offset", "8"],
            "--var-offset applies to var faults only, and this classify injects sdc",
        ),
        (
            "campaign",
            "reg",
            &["--var-flips", "2"],
            "--var-flips applies to var faults only",
        ),
        (
            "campaign",
            "var",
            &["--reg-registers", "rax"],
            "--reg-registers applies to reg faults only",
        ),
    ];
    for (command, fault, extra, want) in cases {
        let mut args = runs_of(command, fault, out);
        args.extend_from_slice(extra);
        refused(&args, want);
    }
    refused(
        &[
            "storm",
            "--state",
            "no-such-state.json",
            "--faults",
            "exec,sdc",
            "--rate",
            "2",
            "--reg-role",
            "source",
        ],
        "--reg-role applies to reg faults only, and this storm injects exec, sdc",
    );
    // The options of the kind chosen pass this check (and fail later, on the missing system).
    let mut args = runs_of("campaign", "var", out);
    args.extend_from_slice(&["--var-offset", "8"]);
    let run = common::inject(&args, LIMIT);
    assert!(!run.stderr.contains("applies to"), "{}", run.stderr);
}

/// A storm of `faults` into a system whose live view does not exist, with `extra`.
fn storm_of<'a>(faults: &'a str, extra: &[&'a str]) -> Vec<&'a str> {
    let mut args = vec!["storm", "--state", "no-such-state.json", "--faults", faults];
    args.extend_from_slice(extra);
    args
}

/// `command` (campaign or classify) of one run of `fault`, seed 1, into `out`, on a system
/// that does not exist: what is refused must be refused before the system is read.
fn runs_of<'a>(command: &'a str, fault: &'a str, out: &'a str) -> Vec<&'a str> {
    vec![
        command,
        "--system",
        "no-such-system.json",
        "--fault",
        fault,
        "--runs",
        "1",
        "--seed",
        "1",
        "--out",
        out,
    ]
}

#[test]
fn classify_and_storm_refuse_mixed_and_name_the_kinds() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    refused(
        &runs_of("classify", "mixed", out.to_str().unwrap()),
        "run it once per kind (exec, sdc, cfe)",
    );
    assert!(!out.exists(), "classify wrote {out:?}");
    refused(
        &[
            "storm",
            "--state",
            "no-such-state.json",
            "--faults",
            "exec,mixed",
            "--rate",
            "2",
        ],
        "name them (--faults exec,sdc,cfe), not `mixed`",
    );
}

#[test]
fn classify_refuses_a_mission_or_output_outside_the_run_folder() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let out = out.to_str().unwrap();
    let classify = |extra: &[&str]| {
        let mut args = vec!["classify", "--system", "s.json", "--fault", "exec"];
        args.extend_from_slice(&["--runs", "1", "--seed", "1", "--out", out]);
        args.extend_from_slice(extra);
        inject(&args, LIMIT)
    };
    for (flag, file) in [
        ("--mission", "/tmp/mission.json"),
        ("--mission", "../mission.json"),
        ("--output", "/etc/hostname"),
    ] {
        let f = classify(&[flag, file]);
        assert_eq!(f.code, Some(1), "{flag} {file}: {}", f.stderr);
        let want = format!("{flag} {file}: give a file in the run's folder");
        assert!(f.stderr.contains(&want), "{}", f.stderr);
    }
    // Both at once: one of them would be ignored.
    let f = classify(&["--mission", "m.json", "--output", "stdout"]);
    assert_eq!(f.code, Some(2), "{}", f.stderr);
    assert!(f.stderr.contains("cannot be used with"), "{}", f.stderr);
    assert!(
        !dir.path().join("out").exists(),
        "classify wrote its folder"
    );
}

/// A mistyped `--rate`, `--runs` or window is refused in one line before anything is planned.
/// Before, `--rate 1e9 --duration 1` planned a billion injections for the first run (24 GB,
/// killed by the kernel's OOM killer), and a huge `--runs` walked the run numbers for minutes,
/// deaf to SIGTERM; `--run-timeout 0` blamed the system for never starting; `--rate 1000
/// --duration 1e9` planned 10^12 injections for the first run (memory exhausted, abort).
#[test]
fn absurd_rates_runs_and_windows_are_refused_before_anything_is_planned() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let campaign = |extra: &[&str]| {
        let mut args = vec![
            "campaign",
            "--system",
            "no-such-system.json",
            "--fault",
            "exec",
            "--seed",
            "1",
            "--out",
            out.to_str().unwrap(),
        ];
        args.extend_from_slice(extra);
        args.iter().map(|s| s.to_string()).collect::<Vec<_>>()
    };
    let cases: [(&[&str], &str); 6] = [
        (
            &["--runs", "1", "--rate", "1e9"],
            "--rate 1000000000.0 injections per second: at most 1000",
        ),
        (
            &[
                "--runs",
                "1",
                "--rate",
                "1000",
                "--duration",
                "1e9",
                "--run-timeout",
                "2e9",
            ],
            "--rate and --duration: 1000.0 injections per second for 1000000000.0 s plan \
             1.000e12 injections in one run: at most 1e6",
        ),
        (
            &["--runs", "1", "--rate", "nan"],
            "--rate NaN is not a rate",
        ),
        (
            &["--runs", "18446744073709551615"],
            "--runs 18446744073709551615: at most 1000000",
        ),
        (
            &["--runs", "1", "--run-timeout", "0"],
            "--run-timeout 0 s is not longer than --duration 3 s",
        ),
        (&["--runs", "1", "--duration", "1e300"], "--duration 1e300"),
    ];
    for (extra, want) in cases {
        let args = campaign(extra);
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        refused(&args, want);
    }
    assert!(!out.exists(), "the campaign wrote {out:?}");
    refused(
        &storm_of("exec", &["--rate", "5000"]),
        "--rate 5000.0 injections per second: at most 1000",
    );
}

/// Register options that no flip can meet are refused once, before anything runs. Before, a
/// campaign ran every run, each flip was 'missed' with an error line, and it exited 0
/// (`--reg-registers foo`); `--reg-bits 0` flipped one bit while the campaign recorded 0; a
/// flip wider than the chosen field stopped the target for every attempt.
#[test]
fn register_options_no_flip_can_meet_are_refused_before_the_first_run() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let cases: [(&[&str], &str); 4] = [
        (
            &["--reg-registers", "foo"],
            "--reg-registers: unknown register `foo`",
        ),
        (&["--reg-bits", "0"], "--reg-bits 0: must be 1 to 128"),
        (
            &["--reg-field", "sign", "--reg-bits", "2"],
            "--reg-bits 2: the sign field of an f64 has 1 bit",
        ),
        (&["--reg-role", "foo"], "--reg-role foo"),
    ];
    for (extra, want) in cases {
        for command in ["campaign", "classify"] {
            let mut args = runs_of(command, "reg", out.to_str().unwrap());
            args.extend_from_slice(extra);
            refused(&args, want);
        }
    }
    assert!(!out.exists(), "wrote {out:?}");
}

/// A storm told to hit a component the running system lacks says so at once. Before, it
/// waited for that component to run until the system ended, then exited 0 having injected
/// nothing, without a word (even with -v).
#[test]
fn a_storm_at_a_component_the_system_lacks_names_the_ones_it_has() {
    let dir = tempfile::tempdir().unwrap();
    let state = live_view_in(dir.path());
    refused(
        &[
            "storm",
            "--state",
            state.to_str().unwrap(),
            "--components",
            "ehco",
            "--faults",
            "exec",
            "--rate",
            "2",
        ],
        "the system echo-demo has no component ehco; it has: echo, sink",
    );
}

/// A live view of a running echo demo (TMR `echo`, unprotected `sink`) in `dir`.
fn live_view_in(dir: &std::path::Path) -> std::path::PathBuf {
    let state = dir.join("state.json");
    std::fs::write(
        &state,
        r#"{"system": "echo-demo", "bootstrap_pid": 1, "updated_ns": 1, "running": true,
            "components": {
              "echo": {"redundancy": "tmr", "protected": true, "pid": null, "voter_pid": 7,
                       "replicas": []},
              "sink": {"redundancy": "none", "protected": false, "pid": 9, "voter_pid": null,
                       "replicas": []}}}"#,
    )
    .unwrap();
    state
}

/// A one-off injection asked for what cannot be: a bit past the 64-bit value (it flipped a
/// byte of the next field), a replica of an unprotected component (it said "sink has 0
/// replica slot(s)").
#[test]
fn a_bit_past_the_value_or_a_replica_of_an_unprotected_component_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let state = live_view_in(dir.path());
    let state = state.to_str().unwrap();
    let inject = |extra: &[&str], want: &str| {
        let mut args = vec!["inject", "--state", state];
        args.extend_from_slice(extra);
        refused(&args, want);
    };
    inject(
        &[
            "--component",
            "echo",
            "--fault",
            "var",
            "--var-bits",
            "3,64",
        ],
        "--var-bits 64: the value at the offset is 64 bits wide (bits 0..=63)",
    );
    inject(
        &["--component", "sink", "--fault", "exec", "--replica", "0"],
        "sink is not protected: it has no replicas",
    );
}

/// A folder holding `files` (empty ones), in `dir`.
fn folder_with(dir: &std::path::Path, name: &str, files: &[&str]) -> std::path::PathBuf {
    let out = dir.join(name);
    std::fs::create_dir_all(&out).unwrap();
    for f in files {
        std::fs::write(out.join(f), "kept\n").unwrap();
    }
    out
}

/// `merge --out` a campaign's or classification's folder — running (its lock), killed (a
/// run's note) or finished — replaced its campaign.json, runs.jsonl and injections.jsonl: it
/// looked for summary.json only. Any folder that is not new or empty is refused, untouched.
#[test]
fn merge_writes_into_a_new_or_empty_folder_only() {
    let dir = tempfile::tempdir().unwrap();
    let cases: [(&[&str], &str); 5] = [
        (
            &[".s3res-inject.lock", "campaign.json", "runs.jsonl"],
            "it holds a campaign (campaign.json)",
        ),
        (
            &[".s3res-inject.lock"],
            "it holds the lock of a campaign or classification (.s3res-inject.lock)",
        ),
        (
            &["running-s3res-inject-AbC123"],
            "it holds a killed run's note (running-s3res-inject-AbC123)",
        ),
        (
            &["classify-run.json", "golden.out"],
            "it holds a classification (classify-run.json)",
        ),
        (&["notes.txt"], "it holds notes.txt"),
    ];
    for (i, (files, want)) in cases.into_iter().enumerate() {
        let out = folder_with(dir.path(), &format!("out-{i}"), files);
        refused(
            &["merge", "--out", out.to_str().unwrap(), "no-such-input"],
            want,
        );
        for f in files {
            assert_eq!(
                std::fs::read_to_string(out.join(f)).unwrap(),
                "kept\n",
                "{f}"
            );
        }
        let n = std::fs::read_dir(&out).unwrap().count();
        assert_eq!(n, files.len(), "merge wrote into {out:?}");
    }
}

/// `--out` is new or empty (or, with --resume, holds the same kind): a classification wrote
/// into a campaign's folder and a campaign into a classification's (then neither merged), and
/// a folder holding anything else (notes.txt) was taken, with or without --resume.
#[test]
fn out_holds_nothing_but_its_own_kind() {
    let dir = tempfile::tempdir().unwrap();
    let campaign = folder_with(dir.path(), "c", &["campaign.json", "runs.jsonl"]);
    let classification = folder_with(dir.path(), "k", &["classify-run.json", "golden.out"]);
    let notes = folder_with(dir.path(), "n", &["notes.txt"]);
    for resume in [false, true] {
        let with = |command, out: &std::path::Path, want: &str| {
            let mut args = runs_of(command, "exec", out.to_str().unwrap());
            if resume {
                args.push("--resume");
            }
            refused(&args, want);
        };
        with(
            "classify",
            &campaign,
            "holds a campaign (campaign.json); a classification needs a folder of its own",
        );
        with(
            "campaign",
            &classification,
            "holds a classification (classify-run.json); a campaign needs a folder of its own",
        );
        for command in ["campaign", "classify"] {
            with(
                command,
                &notes,
                "is not empty (it holds notes.txt) and holds no",
            );
        }
    }
    // What a start leaves in a folder it has not written yet (its lock, a killed run's note)
    // is no content: the check passes, and the missing system is what stops it.
    let started = folder_with(
        dir.path(),
        "s",
        &[".s3res-inject.lock", "running-s3res-golden-AbC123"],
    );
    for command in ["campaign", "classify"] {
        let f = inject(&runs_of(command, "exec", started.to_str().unwrap()), LIMIT);
        assert_eq!(f.code, Some(1), "{}", f.stderr);
        assert!(!f.stderr.contains("--out"), "{}", f.stderr);
        assert!(f.stderr.contains("no-such-system.json"), "{}", f.stderr);
    }
}

/// A zero injection window (`--duration 0`) ran a campaign that injected nothing under a fault's
/// name (`--rate 0` was refused); `--components echo,echo` drew echo twice as often; a
/// `--match-window-ms 0` made every detected fault a false positive and its injection benign.
/// Each is refused in one line; a baseline (`--fault none`) keeps its window of 0.
#[test]
fn a_zero_window_a_repeated_component_or_a_zero_match_window_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let out = out.to_str().unwrap();
    fn with<'a>(command: &'a str, fault: &'a str, out: &'a str, extra: &[&'a str]) -> Vec<&'a str> {
        let mut args = runs_of(command, fault, out);
        args.extend_from_slice(extra);
        args
    }
    for command in ["campaign", "classify"] {
        refused(
            &with(command, "exec", out, &["--duration", "0"]),
            "--duration 0: a window of 0 s leaves no time to inject exec faults",
        );
        refused(
            &with(command, "sdc", out, &["--components", "echo,echo,sink"]),
            "--components names echo twice",
        );
    }
    refused(
        &with("campaign", "exec", out, &["--match-window-ms", "0"]),
        "--match-window-ms 0: no fault event can follow an injection within 0 ms",
    );
    refused(
        &storm_of("exec", &["--components", "echo,sink,echo"]),
        "--components names echo twice",
    );
    let baseline = inject(&with("campaign", "none", out, &["--duration", "0"]), LIMIT);
    assert_eq!(baseline.code, Some(1), "{}", baseline.stderr);
    assert!(
        baseline.stderr.contains("no-such-system.json") && !baseline.stderr.contains("--duration"),
        "{}",
        baseline.stderr
    );
    assert!(!std::path::Path::new(out).exists(), "wrote {out}");
}

/// `--help` said "2 bad usage", but a refused value (`--runs 0`) exits 1: it says which is
/// which.
#[test]
fn help_says_what_each_exit_status_means() {
    let f = inject(&["--help"], LIMIT);
    assert!(f.success, "{}", f.stderr);
    let text = f.stdout.split_whitespace().collect::<Vec<_>>().join(" ");
    assert!(
        text.contains("1 failed or refused")
            && text.contains("2 a command line the parser cannot read"),
        "{}",
        f.stdout
    );
    assert!(!text.contains("2 bad usage"), "{}", f.stdout);
    let mut zero = runs_of("campaign", "exec", "out");
    zero[6] = "0";
    refused(&zero, "--runs 0: nothing to do");
}
