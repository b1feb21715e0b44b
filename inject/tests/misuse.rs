//! What a user gets wrong with `--fault mixed` and `--bit` is refused in one line, before
//! anything is started or written.

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

#[test]
fn classify_and_storm_refuse_mixed_and_name_the_kinds() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    refused(
        &[
            "classify",
            "--system",
            "no-such-system.json",
            "--fault",
            "mixed",
            "--runs",
            "1",
            "--seed",
            "1",
            "--out",
            out.to_str().unwrap(),
        ],
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
