//! A malformed system description is refused before anything starts: `s3res-bootstrap
//! SYSTEM.json` exits with status 2, its error names the file's line of the offending field and
//! the component, channel or field, and no process was started.
//!
//! Each description is written by hand, so the line of the offending field is known: it is the
//! line holding the case's `needle`, which appears exactly once in the text.

use std::os::unix::fs::PermissionsExt;
use std::time::Duration;

use s3res_testkit::System;

/// Bound on one refusal; bootstrap refuses within milliseconds.
const LIMIT: Duration = Duration::from_secs(30);

/// 1-based line of the single occurrence of `needle` in `text`.
fn line_of(text: &str, needle: &str) -> usize {
    let mut hits = text.match_indices(needle);
    let (at, _) = hits
        .next()
        .unwrap_or_else(|| panic!("needle {needle:?} not in:\n{text}"));
    assert!(hits.next().is_none(), "needle {needle:?} occurs twice");
    text[..at].matches('\n').count() + 1
}

/// Starts bootstrap on `text` (built by `make` from the system's temp dir) and checks the
/// refusal: exit status 2, `:<line>:` of `needle`, at least one of `names`, nothing started.
fn refused(make: impl FnOnce(&System) -> String, needle: &str, names: &[&str]) {
    let sys = System::new().without_events();
    let text = make(&sys);
    let line = line_of(&text, needle);
    let mut run = sys.start(&text);
    let out = run.wait(LIMIT);
    let ctx = format!(
        "description:\n{text}\n--- stderr ---\n{}\n--- stdout ---\n{}",
        out.stderr, out.stdout
    );
    eprintln!("line {line}: {}", out.stderr.trim_end());
    assert_eq!(out.status.code(), Some(2), "want exit status 2\n{ctx}");
    assert!(
        out.stderr.contains(&format!(":{line}:")),
        "stderr does not give line {line} as `:{line}:`\n{ctx}"
    );
    assert!(
        names.iter().any(|n| out.stderr.contains(n)),
        "stderr names none of {names:?}\n{ctx}"
    );
    // Bootstrap exits before it spawns anything: its process group is empty.
    run.assert_nothing_left();
}

fn refused_text(text: &str, needle: &str, names: &[&str]) {
    let text = text.to_owned();
    refused(move |_| text, needle, names);
}

#[test]
fn malformed_json() {
    refused_text(
        r#"{
  "name": "bad-json",
  "components": {
    "source": { "exec": "s3res-source", "args": ["--count", "10"] }
    "sink":   { "exec": "s3res-sink" }
  },
  "channels": [
    { "from": "source.out", "to": "sink.in" }
  ]
}
"#,
        r#""sink":   {"#,
        &["json", "JSON", "expected", "syntax"],
    );
}

#[test]
fn unknown_component_in_a_channel() {
    refused_text(
        r#"{
  "name": "unknown-component",
  "components": {
    "source": { "exec": "s3res-source", "args": ["--count", "10"] },
    "sink":   { "exec": "s3res-sink" }
  },
  "channels": [
    { "from": "source.out", "to": "sink.in" },
    { "from": "source.out", "to": "nosuch.in" }
  ]
}
"#,
        "nosuch.in",
        &["nosuch"],
    );
}

#[test]
fn an_input_connected_twice() {
    refused_text(
        r#"{
  "name": "input-connected-twice",
  "components": {
    "source":  { "exec": "s3res-source", "args": ["--count", "10"] },
    "source2": { "exec": "s3res-source", "args": ["--count", "10"] },
    "echo":    { "exec": "s3res-echo" },
    "sink":    { "exec": "s3res-sink" }
  },
  "channels": [
    { "from": "source.out", "to": "echo.in" },
    { "from": "echo.out",   "to": "sink.in" },
    { "from": "source2.out", "to": "sink.in" }
  ]
}
"#,
        r#""source2.out""#,
        &["sink.in"],
    );
}

#[test]
fn an_output_connected_twice() {
    refused_text(
        r#"{
  "name": "output-connected-twice",
  "components": {
    "source": { "exec": "s3res-source", "args": ["--count", "10"] },
    "echo":   { "exec": "s3res-echo" },
    "sink":   { "exec": "s3res-sink" },
    "sink2":  { "exec": "s3res-sink" }
  },
  "channels": [
    { "from": "source.out", "to": "echo.in" },
    { "from": "echo.out",   "to": "sink.in" },
    { "from": "source.out", "to": "sink2.in" }
  ]
}
"#,
        r#""sink2.in""#,
        &["source.out"],
    );
}

#[test]
fn an_unconnected_declared_input() {
    refused_text(
        r#"{
  "name": "unconnected-input",
  "components": {
    "source": { "exec": "s3res-source", "args": ["--count", "10"] },
    "sink": {
      "exec": "s3res-sink",
      "inputs": ["in", "ctl"]
    }
  },
  "channels": [
    { "from": "source.out", "to": "sink.in" }
  ]
}
"#,
        r#""inputs""#,
        &["ctl"],
    );
}

#[test]
fn duplicate_component_names() {
    refused_text(
        r#"{
  "name": "duplicate-component",
  "components": {
    "source": { "exec": "s3res-source", "args": ["--count", "10"] },
    "echo":   { "exec": "s3res-echo" },
    "echo":   { "exec": "s3res-echo", "args": ["--stateful"] },
    "sink":   { "exec": "s3res-sink" }
  },
  "channels": [
    { "from": "source.out", "to": "echo.in" },
    { "from": "echo.out",   "to": "sink.in" }
  ]
}
"#,
        r#""args": ["--stateful"]"#,
        &["echo"],
    );
}

/// A source → echo → sink system whose echo component is `echo` (one or more lines).
fn with_echo(name: &str, echo: &str) -> String {
    format!(
        r#"{{
  "name": "{name}",
  "components": {{
    "source": {{ "exec": "s3res-source", "args": ["--count", "10"] }},
    "echo": {echo},
    "sink":   {{ "exec": "s3res-sink" }}
  }},
  "channels": [
    {{ "from": "source.out", "to": "echo.in" }},
    {{ "from": "echo.out",   "to": "sink.in" }}
  ]
}}
"#
    )
}

#[test]
fn unknown_redundancy() {
    let echo = r#"{
      "exec": "s3res-echo",
      "redundancy": "quintuple",
      "timeout_us": 20000
    }"#;
    refused_text(
        &with_echo("unknown-redundancy", echo),
        "quintuple",
        &["redundancy", "quintuple"],
    );
}

#[test]
fn unknown_mode() {
    let echo = r#"{
      "exec": "s3res-echo",
      "redundancy": "tmr",
      "mode": "psychic",
      "timeout_us": 20000
    }"#;
    refused_text(
        &with_echo("unknown-mode", echo),
        "psychic",
        &["mode", "psychic"],
    );
}

#[test]
fn missing_timeout_on_a_protected_component() {
    // The whole component on one line: the line of the component is the line of the omission.
    let echo = r#"{ "exec": "s3res-echo", "redundancy": "tmr" }"#;
    refused_text(
        &with_echo("missing-timeout", echo),
        r#""redundancy": "tmr""#,
        &["timeout_us"],
    );
}

#[test]
fn zero_timeout() {
    let echo = r#"{
      "exec": "s3res-echo",
      "redundancy": "tmr",
      "timeout_us": 0
    }"#;
    refused_text(
        &with_echo("zero-timeout", echo),
        r#""timeout_us": 0"#,
        &["timeout_us"],
    );
}

#[test]
fn a_cpu_this_machine_lacks() {
    let echo = r#"{
      "exec": "s3res-echo",
      "redundancy": "tmr",
      "timeout_us": 20000,
      "cpus": [4096]
    }"#;
    refused_text(
        &with_echo("missing-cpu", echo),
        r#""cpus""#,
        &["cpus", "4096"],
    );
}

#[test]
fn priority_zero() {
    let echo = r#"{
      "exec": "s3res-echo",
      "priority": 0
    }"#;
    refused_text(
        &with_echo("priority-0", echo),
        r#""priority""#,
        &["priority"],
    );
}

#[test]
fn priority_hundred() {
    let echo = r#"{
      "exec": "s3res-echo",
      "redundancy": "tmr",
      "timeout_us": 20000,
      "priority": 100
    }"#;
    refused_text(
        &with_echo("priority-100", echo),
        r#""priority""#,
        &["priority"],
    );
}

#[test]
fn an_exec_that_does_not_exist() {
    let echo = r#"{
      "exec": "/nonexistent/s3res-nothing",
      "redundancy": "tmr",
      "timeout_us": 20000
    }"#;
    refused_text(
        &with_echo("missing-exec", echo),
        "s3res-nothing",
        &["s3res-nothing"],
    );
}

#[test]
fn an_exec_that_is_not_executable() {
    refused(
        |sys| {
            let path = sys.path("not-executable");
            std::fs::write(&path, "#!/bin/sh\nexit 0\n").unwrap();
            std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o644)).unwrap();
            let echo = format!(
                r#"{{
      "exec": "{}",
      "redundancy": "tmr",
      "timeout_us": 20000
    }}"#,
                path.display()
            );
            with_echo("exec-mode-644", &echo)
        },
        "not-executable\"",
        &["not-executable"],
    );
}
