//! One test per validation rule: each checks that the message says what is wrong, names the
//! component/channel/field, and points at the right line.

use std::fs;
use std::os::unix::fs::PermissionsExt;

use super::*;
use s3res_protocol::sched::Schedule;

/// A folder with an executable `run.sh` and a non-executable `notes.txt`; CPUs 0 and 1.
struct Fixture {
    dir: tempfile::TempDir,
    ctx: HostContext,
}

fn fixture() -> Fixture {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run.sh");
    fs::write(&run, "#!/bin/sh\n").unwrap();
    fs::set_permissions(&run, fs::Permissions::from_mode(0o755)).unwrap();
    let notes = dir.path().join("notes.txt");
    fs::write(&notes, "x").unwrap();
    fs::set_permissions(&notes, fs::Permissions::from_mode(0o644)).unwrap();
    let ctx = HostContext {
        base_dir: dir.path().to_path_buf(),
        search: SearchPath {
            self_dir: Some(dir.path().to_path_buf()),
            path_dirs: Vec::new(),
        },
        cpus: vec![0, 1],
    };
    Fixture { dir, ctx }
}

impl Fixture {
    fn ok(&self, text: &str) -> SystemPlan {
        match parse("sys.json", text, &self.ctx) {
            Ok(p) => p,
            Err(e) => panic!("expected a valid description, got: {e}"),
        }
    }

    /// Asserts the error is on `line`, names `subject`, and its message contains `needle`.
    fn fails(&self, text: &str, line: usize, subject: &str, needle: &str) -> String {
        let e = match parse("sys.json", text, &self.ctx) {
            Ok(_) => panic!("expected an error containing {needle:?}"),
            Err(e) => e,
        };
        let msg = e.to_string();
        assert!(
            msg.starts_with(&format!("sys.json:{line}: ")),
            "wrong line: {msg}"
        );
        assert!(
            msg.ends_with(&format!("({subject})")),
            "wrong subject: {msg}"
        );
        assert!(msg.contains(needle), "{needle:?} not in: {msg}");
        assert!(!msg.contains('\n'), "not one line: {msg}");
        msg
    }
}

const ECHO: &str = r#"{
  "name": "echo-demo",
  "components": {
    "source": { "exec": "run.sh", "args": ["--count", "2000"], "priority": 40 },
    "echo":   { "exec": "./run.sh", "args": ["--stateful"], "redundancy": "tmr",
                "timeout_us": 20000, "priority": 30, "cpus": [0, 1] },
    "sink":   { "exec": "run.sh", "priority": 20 }
  },
  "channels": [
    { "from": "source.out", "to": "echo.in" },
    { "from": "echo.out",   "to": "sink.in" }
  ]
}"#;

#[test]
fn echo_demo_plan() {
    let f = fixture();
    let plan = f.ok(ECHO);
    assert_eq!(plan.name, "echo-demo");
    let names: Vec<&str> = plan.components.iter().map(|c| c.name.as_str()).collect();
    assert_eq!(names, ["source", "echo", "sink"], "document order is kept");
    let echo = &plan.components[1];
    assert_eq!(echo.replicas, 3);
    assert_eq!(echo.timeout_us, 20000);
    assert_eq!(echo.exec, f.dir.path().join("run.sh"));
    assert_eq!(echo.cpus, [0, 1]);
    assert_eq!(echo.priority, Some(30));
    assert_eq!(echo.restart_timeout_ms, default_restart_timeout_ms());
    assert_eq!(echo.inputs[0].name, "in");
    assert_eq!(echo.inputs[0].channel, Some(0));
    assert_eq!(echo.outputs[0].channel, Some(1));
    assert_eq!(echo.inputs[0].max_frame, DEFAULT_MAX_FRAME);
    assert_eq!(
        echo.rounds,
        [RoundTrigger {
            input: "in".into(),
            outputs: vec!["out".into()]
        }]
    );
    let source = &plan.components[0];
    assert_eq!(source.replicas, 0);
    assert!(source.rounds.is_empty());
    assert!(source.inputs.is_empty());
    assert!(!plan.uses_stdout());
    assert!(plan.warnings.is_empty());
    let text = plan.describe(None, None);
    assert!(text.contains("component echo: runs under s3res-voter with 3 replica(s) (tmr)"));
    assert!(text.contains("out out      -> echo.in (channel 0"));
}

#[test]
fn replicas_override_and_explicit_rounds() {
    let f = fixture();
    let plan = f.ok(r#"{
  "name": "n",
  "components": {
    "a": { "exec": "run.sh", "redundancy": "dmr", "replicas": 5, "timeout_us": 10,
           "restart_timeout_ms": 50,
           "inputs": ["cmd", "tick"], "outputs": ["out", "log"],
           "rounds": [ { "input": "tick", "outputs": ["out"] }, { "input": "cmd" } ] }
  },
  "channels": [
    { "from": "stdin", "to": "a.tick", "max_frame": 16 },
    { "from": "a.out", "to": "stdout" },
    { "from": "a.log", "to": "b.in" },
    { "from": "b.out", "to": "a.cmd" }
  ]
}"#
    .replace("\"a\": {", "\"b\": { \"exec\": \"run.sh\" },\n    \"a\": {")
    .as_str());
    let a = &plan.components[1];
    assert_eq!(a.replicas, 5);
    assert_eq!(a.restart_timeout_ms, 50);
    let ins: Vec<_> = a
        .inputs
        .iter()
        .map(|p| (p.name.as_str(), p.channel))
        .collect();
    assert_eq!(ins, [("cmd", Some(3)), ("tick", Some(0))], "declared order");
    assert_eq!(a.inputs[1].max_frame, 16);
    assert_eq!(a.rounds[0].outputs, ["out"]);
    assert_eq!(
        a.rounds[1].outputs,
        ["out", "log"],
        "absent outputs: all of them"
    );
    assert!(plan.uses_stdout());
}

#[test]
fn declared_but_unread_output_goes_nowhere() {
    let f = fixture();
    let plan =
        f.ok(r#"{"name": "n", "components": {"a": {"exec": "run.sh", "outputs": ["debug"]}}}"#);
    assert_eq!(plan.components[0].outputs[0].channel, None);
}

#[test]
fn ignored_fields_warn() {
    let f = fixture();
    let plan = f.ok(r#"{"name": "n", "components": {"a": {"exec": "run.sh", "timeout_us": 5}}}"#);
    assert_eq!(plan.warnings.len(), 1);
    assert!(plan.warnings[0].contains("timeout_us"));
}

#[test]
fn malformed_json() {
    let f = fixture();
    f.fails(
        "{\n  \"name\": \"x\",\n  \"components\": {\n    \"a\": { \"exec\": \"run.sh\" }\n    \"b\": {}\n  }\n}",
        5,
        "JSON syntax",
        "malformed JSON: expected `,` or `}`",
    );
    f.fails("", 1, "JSON syntax", "malformed JSON");
}

#[test]
fn unknown_field() {
    let f = fixture();
    f.fails(
        "{\n \"name\": \"x\",\n \"components\": {\n  \"a\": {\n   \"exec\": \"run.sh\",\n   \"prio\": 3\n  }\n }\n}",
        6,
        "components.a.prio",
        "unknown field `prio`",
    );
    f.fails(
        "{\n \"name\": \"x\",\n \"components\": {\"a\": {\"exec\": \"run.sh\"}},\n \"chanels\": []\n}",
        4,
        "chanels",
        "unknown field `chanels`",
    );
    f.fails(
        "{\"name\": \"x\", \"components\": {\"a\": {\"exec\": \"run.sh\"}},\n \"channels\": [\n {\"from\": \"stdin\", \"to\": \"a.in\",\n \"size\": 3}]}",
        4,
        "channels[0].size",
        "unknown field `size`",
    );
}

#[test]
fn missing_required_fields() {
    let f = fixture();
    f.fails(
        "{\"components\": {}}",
        1,
        "top level",
        "missing field `name`",
    );
    f.fails(
        "{\"name\": \"x\",\n \"components\": {\n  \"a\": {\n  \"args\": []\n }}}",
        3,
        "components.a",
        "missing field `exec`",
    );
    f.fails(
        "{\"name\": \"x\",\n \"components\": {}}",
        2,
        "components",
        "at least one component",
    );
}

#[test]
fn duplicate_component_names() {
    let f = fixture();
    f.fails(
        "{\"name\": \"x\",\n \"components\": {\n  \"a\": {\"exec\": \"run.sh\"},\n  \"a\": {\"exec\": \"run.sh\"}\n }\n}",
        4,
        "components.a",
        "duplicate component name `a`",
    );
    f.fails(
        "{\"name\": \"x\",\n \"components\": {\n  \"a\": {\"exec\": \"run.sh\",\n  \"exec\": \"run.sh\"}\n }\n}",
        4,
        "components.a.exec",
        "duplicate key `exec`",
    );
}

#[test]
fn unknown_redundancy_and_mode() {
    let f = fixture();
    f.fails(
        "{\"name\": \"x\", \"components\": {\n \"a\": {\"exec\": \"run.sh\",\n \"redundancy\": \"qmr\", \"timeout_us\": 5}}}",
        3,
        "components.a.redundancy",
        "unknown variant `qmr`",
    );
    f.fails(
        "{\"name\": \"x\", \"components\": {\n \"a\": {\"exec\": \"run.sh\",\n \"mode\": \"batch\"}}}",
        3,
        "components.a.mode",
        "unknown variant `batch`",
    );
}

#[test]
fn stream_mode_is_passed_to_the_voter_without_rounds() {
    let f = fixture();
    let plan = f.ok(
        r#"{"name": "x", "components": {
  "planner": {"exec": "run.sh", "redundancy": "tmr", "timeout_us": 5, "mode": "stream", "window": 8},
  "mapper": {"exec": "run.sh", "redundancy": "dmr", "timeout_us": 5, "mode": "stream"}},
 "channels": [{"from": "stdin", "to": "planner.in"}, {"from": "planner.out", "to": "mapper.in"}]}"#,
    );
    let planner = &plan.components[0];
    assert_eq!(planner.mode, Mode::Stream);
    assert_eq!(planner.window, 8);
    assert!(planner.rounds.is_empty());
    let mapper = &plan.components[1];
    assert!(mapper.outputs.is_empty(), "outputs may be none");
    assert_eq!(mapper.window, s3res_protocol::plan::DEFAULT_STREAM_WINDOW);
}

#[test]
fn stream_mode_wants_an_input_no_rounds_and_a_sane_window() {
    let f = fixture();
    f.fails(
        "{\"name\": \"x\", \"components\": {\n \"a\": {\"exec\": \"run.sh\", \"redundancy\": \"tmr\", \"timeout_us\": 5,\n \"mode\": \"stream\", \"rounds\": []}}}",
        3,
        "components.a.rounds",
        "a stream component has no rounds",
    );
    f.fails(
        "{\"name\": \"x\", \"components\": {\n \"a\": {\"exec\": \"run.sh\", \"redundancy\": \"tmr\", \"timeout_us\": 5,\n \"mode\": \"stream\",\n \"window\": 0}}}",
        4,
        "components.a.window",
        "window 0 is outside 1..=65536",
    );
    f.fails(
        "{\"name\": \"x\", \"components\": {\n \"a\": {\"exec\": \"run.sh\", \"redundancy\": \"tmr\", \"timeout_us\": 5,\n \"mode\": \"stream\"}}}",
        3,
        "components.a.mode",
        "stream mode needs one",
    );
    let plan = f.ok(
        r#"{"name": "x", "components": {"a": {"exec": "run.sh", "redundancy": "tmr", "timeout_us": 5, "window": 3}},
 "channels": [{"from": "stdin", "to": "a.in"}]}"#,
    );
    assert!(
        plan.warnings[0].contains("`window` is for stream mode only"),
        "{:?}",
        plan.warnings
    );
}

#[test]
fn timeout_missing_or_zero_on_protected() {
    let f = fixture();
    f.fails(
        "{\"name\": \"x\", \"components\": {\n \"a\": {\"exec\": \"run.sh\", \"redundancy\": \"dmr\"}}}",
        2,
        "components.a",
        "`timeout_us` is required for a protected component (redundancy dmr)",
    );
    f.fails(
        "{\"name\": \"x\", \"components\": {\n \"a\": {\"exec\": \"run.sh\", \"redundancy\": \"smr\",\n \"timeout_us\": 0}}}",
        3,
        "components.a.timeout_us",
        "timeout_us must be more than 0",
    );
}

#[test]
fn replicas_rules() {
    let f = fixture();
    f.fails(
        "{\"name\": \"x\", \"components\": {\n \"a\": {\"exec\": \"run.sh\",\n \"replicas\": 3}}}",
        3,
        "components.a.replicas",
        "needs a redundancy",
    );
    f.fails(
        "{\"name\": \"x\", \"components\": {\n \"a\": {\"exec\": \"run.sh\", \"redundancy\": \"tmr\", \"timeout_us\": 9,\n \"replicas\": 10}}}",
        3,
        "components.a.replicas",
        "replicas 10 is outside 1..=9",
    );
}

#[test]
fn priority_out_of_range() {
    let f = fixture();
    for p in ["0", "100", "-1"] {
        f.fails(
            &format!("{{\"name\": \"x\", \"components\": {{\n \"a\": {{\"exec\": \"run.sh\",\n \"priority\": {p}}}}}}}"),
            3,
            "components.a.priority",
            &format!("priority {p} is outside 1..=99"),
        );
    }
}

#[test]
fn cpu_that_does_not_exist() {
    let f = fixture();
    f.fails(
        "{\"name\": \"x\", \"components\": {\n \"a\": {\"exec\": \"run.sh\", \"cpus\": [\n 0,\n 7]}}}",
        4,
        "components.a.cpus[1]",
        "CPU 7 does not exist on this machine (usable CPUs: 0, 1)",
    );
    f.fails(
        "{\"name\": \"x\", \"components\": {\n \"a\": {\"exec\": \"run.sh\", \"cpus\": [1, 1]}}}",
        2,
        "components.a.cpus[1]",
        "CPU 1 is listed twice",
    );
}

#[test]
fn executable_missing_or_not_executable() {
    let f = fixture();
    f.fails(
        "{\"name\": \"x\", \"components\": {\n \"a\": {\n \"exec\": \"./nope.sh\"}}}",
        3,
        "components.a.exec",
        "executable `./nope.sh` does not exist",
    );
    f.fails(
        "{\"name\": \"x\", \"components\": {\n \"a\": {\n \"exec\": \"notes.txt\"}}}",
        3,
        "components.a.exec",
        "not an executable file",
    );
    f.fails(
        "{\"name\": \"x\", \"components\": {\n \"a\": {\n \"exec\": \"./notes.txt\"}}}",
        3,
        "components.a.exec",
        "is not executable",
    );
    f.fails(
        "{\"name\": \"x\", \"components\": {\n \"a\": {\n \"exec\": \"no-such-program\"}}}",
        3,
        "components.a.exec",
        "not found beside s3res-bootstrap nor on PATH",
    );
}

#[test]
fn unknown_component_in_endpoint() {
    let f = fixture();
    f.fails(
        "{\"name\": \"x\", \"components\": {\"a\": {\"exec\": \"run.sh\"}},\n \"channels\": [\n {\"from\": \"stdin\",\n \"to\": \"ecko.in\"}]}",
        4,
        "channels[0].to",
        "unknown component `ecko` in endpoint `ecko.in`",
    );
    f.fails(
        "{\"name\": \"x\", \"components\": {\"a\": {\"exec\": \"run.sh\"}},\n \"channels\": [\n {\"from\": \"a\", \"to\": \"stdout\"}]}",
        3,
        "channels[0].from",
        "endpoint `a` must be `component.port`, `stdin` or `stdout`",
    );
}

#[test]
fn unknown_port_against_declared_ports() {
    let f = fixture();
    f.fails(
        "{\"name\": \"x\", \"components\": {\"a\": {\"exec\": \"run.sh\", \"inputs\": [\"in\"]}},\n \"channels\": [\n {\"from\": \"stdin\", \"to\": \"a.in\"},\n {\"from\": \"stdin\", \"to\": \"a.inn\"}]}",
        4,
        "channels[1].from",
        "stdin is already read by channels[0]",
    );
    f.fails(
        "{\"name\": \"x\", \"components\": {\"a\": {\"exec\": \"run.sh\", \"outputs\": [\"out\"]}},\n \"channels\": [\n {\"from\": \"a.ouT\",\n \"to\": \"stdout\"}]}",
        3,
        "channels[0].from",
        "unknown port `ouT`: component `a` declares outputs [out]",
    );
}

#[test]
fn round_naming_an_unused_port() {
    let f = fixture();
    f.fails(
        "{\"name\": \"x\", \"components\": {\"a\": {\"exec\": \"run.sh\", \"redundancy\": \"tmr\", \"timeout_us\": 9,\n \"rounds\": [{\"input\": \"in\",\n \"outputs\": [\"status\"]}]}},\n \"channels\": [{\"from\": \"stdin\", \"to\": \"a.in\"}, {\"from\": \"a.out\", \"to\": \"stdout\"}]}",
        3,
        "components.a.rounds[0].outputs[0]",
        "unknown output port `status` in a round of component `a` (no channel starts at `a.status`)",
    );
    f.fails(
        "{\"name\": \"x\", \"components\": {\"a\": {\"exec\": \"run.sh\", \"redundancy\": \"tmr\", \"timeout_us\": 9, \"inputs\": [\"in\"],\n \"rounds\": [{\"input\": \"tick\"}]}},\n \"channels\": [{\"from\": \"stdin\", \"to\": \"a.in\"}]}",
        2,
        "components.a.rounds[0].input",
        "unknown input port `tick` in a round of component `a`",
    );
}

#[test]
fn input_connected_nowhere() {
    let f = fixture();
    f.fails(
        "{\"name\": \"x\", \"components\": {\"a\": {\"exec\": \"run.sh\",\n \"inputs\": [\"in\",\n \"cmd\"]}},\n \"channels\": [{\"from\": \"stdin\", \"to\": \"a.in\"}]}",
        3,
        "components.a.inputs[1]",
        "input port `a.cmd` is connected nowhere",
    );
    f.fails(
        "{\"name\": \"x\", \"components\": {\"a\": {\"exec\": \"run.sh\", \"redundancy\": \"tmr\", \"timeout_us\": 9,\n \"rounds\": [\n {\"input\": \"tick\"}]}},\n \"channels\": [{\"from\": \"stdin\", \"to\": \"a.in\"}]}",
        3,
        "components.a.rounds[0].input",
        "round input `a.tick` is connected nowhere",
    );
}

#[test]
fn port_connected_twice() {
    let f = fixture();
    let base = |chans: &str| {
        format!("{{\"name\": \"x\", \"components\": {{\"a\": {{\"exec\": \"run.sh\"}}, \"b\": {{\"exec\": \"run.sh\"}}}},\n \"channels\": [\n{chans}]}}")
    };
    f.fails(
        &base("{\"from\": \"a.out\", \"to\": \"b.in\"},\n{\"from\": \"a.out2\", \"to\": \"b.in\"}"),
        4,
        "channels[1].to",
        "input port `b.in` is already connected by channels[0]; a pipe has one reader",
    );
    f.fails(
        &base("{\"from\": \"a.out\", \"to\": \"b.in\"},\n{\"from\": \"a.out\", \"to\": \"b.in2\"}"),
        4,
        "channels[1].from",
        "output port `a.out` is already connected by channels[0]; a pipe has one writer",
    );
    f.fails(
        &base(
            "{\"from\": \"a.out\", \"to\": \"stdout\"},\n{\"from\": \"b.out\", \"to\": \"stdout\"}",
        ),
        4,
        "channels[1].to",
        "stdout is already written by channels[0]",
    );
}

#[test]
fn port_used_both_ways() {
    let f = fixture();
    f.fails(
        "{\"name\": \"x\", \"components\": {\"a\": {\"exec\": \"run.sh\"}, \"b\": {\"exec\": \"run.sh\"}},\n \"channels\": [\n {\"from\": \"a.io\", \"to\": \"b.in\"},\n {\"from\": \"b.out\", \"to\": \"a.io\"}]}",
        4,
        "channels[1].to",
        "port `a.io` is used both as an output (channels[0].from) and as an input",
    );
    f.fails(
        "{\"name\": \"x\", \"components\": {\"a\": {\"exec\": \"run.sh\", \"inputs\": [\"io\"],\n \"outputs\": [\"io\"]}},\n \"channels\": [{\"from\": \"stdin\", \"to\": \"a.io\"}]}",
        2,
        "components.a.outputs[0]",
        "port `io` of component `a` is both an input and an output",
    );
}

#[test]
fn reserved_endpoints_in_the_wrong_place() {
    let f = fixture();
    f.fails(
        "{\"name\": \"x\", \"components\": {\"a\": {\"exec\": \"run.sh\"}},\n \"channels\": [\n {\"from\": \"a.out\", \"to\": \"stdin\"}]}",
        3,
        "channels[0].to",
        "`stdin` can only be a channel's `from`",
    );
    f.fails(
        "{\"name\": \"x\", \"components\": {\"a\": {\"exec\": \"run.sh\"}},\n \"channels\": [\n {\"from\": \"stdout\", \"to\": \"a.in\"}]}",
        3,
        "channels[0].from",
        "`stdout` can only be a channel's `to`",
    );
    f.fails(
        "{\"name\": \"x\", \"components\": {\"a\": {\"exec\": \"run.sh\"}},\n \"channels\": [\n {\"from\": \"stdin\", \"to\": \"stdout\"}]}",
        3,
        "channels[0]",
        "connects no component",
    );
    f.fails(
        "{\"name\": \"x\", \"components\": {\n \"stdin\": {\"exec\": \"run.sh\"}}}",
        2,
        "components.stdin",
        "reserved",
    );
}

#[test]
fn max_frame_range() {
    let f = fixture();
    for m in ["0", "16777217"] {
        f.fails(
            &format!("{{\"name\": \"x\", \"components\": {{\"a\": {{\"exec\": \"run.sh\"}}}},\n \"channels\": [\n {{\"from\": \"stdin\", \"to\": \"a.in\",\n \"max_frame\": {m}}}]}}"),
            4,
            "channels[0].max_frame",
            &format!("max_frame {m} is outside 1..=16777216"),
        );
    }
}

#[test]
fn too_many_ports() {
    let f = fixture();
    let chans: Vec<String> = (0..=MAX_PORTS)
        .map(|i| format!("{{\"from\": \"a.o{i}\", \"to\": \"b.i{i}\"}}"))
        .collect();
    let text = format!(
        "{{\"name\": \"x\",\n \"components\": {{\n \"a\": {{\"exec\": \"run.sh\"}},\n \"b\": {{\"exec\": \"run.sh\"}}}},\n \"channels\": [{}]}}",
        chans.join(",\n")
    );
    f.fails(
        &text,
        3,
        "components.a",
        &format!(
            "component `a` has {} ports, more than the limit of {MAX_PORTS}",
            MAX_PORTS + 1
        ),
    );
}

#[test]
fn component_names_must_fit_endpoints() {
    let f = fixture();
    f.fails(
        "{\"name\": \"x\", \"components\": {\n \"a.b\": {\"exec\": \"run.sh\"}}}",
        2,
        "components.a.b",
        "contains '.'; names use ASCII letters, digits, `_` and `-`",
    );
    f.fails(
        "{\"name\": \"\",\n \"components\": {\"a\": {\"exec\": \"run.sh\"}}}",
        1,
        "name",
        "the system name is empty",
    );
}

#[test]
fn names_are_bounded_and_printable() {
    let f = fixture();
    // A NUL in a component name passed `--check` and failed at start.
    f.fails(
        "{\"name\": \"x\", \"components\": {\n \"a\\u0000b\": {\"exec\": \"run.sh\"}}}",
        2,
        "components.a\u{0}b",
        "contains '\\0'",
    );
    let long = "c".repeat(MAX_NAME_LEN + 1);
    f.fails(
        &format!(
            "{{\"name\": \"x\", \"components\": {{\n \"{long}\": {{\"exec\": \"run.sh\"}}}}}}"
        ),
        2,
        &format!("components.{long}"),
        "is longer than 64 characters",
    );
    f.fails(
        "{\"name\": \"x\\u0007y\",\n \"components\": {\"a\": {\"exec\": \"run.sh\"}}}",
        1,
        "name",
        "control character",
    );
    f.fails(
        "{\"name\": \"x\", \"components\": {\"a\": {\"exec\": \"run.sh\"}},\n \"channels\": [{\"from\": \"a.oüt\", \"to\": \"stdout\"}]}",
        2,
        "channels[0].from",
        "names use ASCII letters",
    );
}

#[test]
fn durations_are_bounded_to_a_minute() {
    let f = fixture();
    // 2^64 - 1 passed, and a spinning replica was then never found.
    f.fails(
        "{\"name\": \"x\", \"components\": {\"a\": {\"exec\": \"run.sh\", \"redundancy\": \"tmr\",\n \"timeout_us\": 18446744073709551615}}}",
        2,
        "components.a.timeout_us",
        "is above 60000000 (one minute",
    );
    for field in ["restart_timeout_ms", "start_timeout_ms"] {
        f.fails(
            &format!("{{\"name\": \"x\", \"components\": {{\"a\": {{\"exec\": \"run.sh\", \"redundancy\": \"tmr\", \"timeout_us\": 1000,\n \"{field}\": 60001}}}}}}"),
            2,
            &format!("components.a.{field}"),
            "is above 60000 (one minute)",
        );
    }
}

#[test]
fn commands_are_bounded_and_free_of_nul() {
    let f = fixture();
    f.fails(
        "{\"name\": \"x\", \"components\": {\"a\": {\"exec\": \"run.sh\",\n \"args\": [\"ok\", \"a\\u0000b\"]}}}",
        2,
        "components.a.args[1]",
        "NUL byte",
    );
    let long = "y".repeat(MAX_ARG_LEN + 1);
    f.fails(
        &format!("{{\"name\": \"x\", \"components\": {{\"a\": {{\"exec\": \"run.sh\",\n \"args\": [\"{long}\"]}}}}}}"),
        2,
        "components.a.args[0]",
        "bytes long; at most 4096",
    );
    let many = vec!["\"z\""; MAX_ARGS + 1].join(", ");
    f.fails(
        &format!("{{\"name\": \"x\", \"components\": {{\"a\": {{\"exec\": \"run.sh\",\n \"args\": [{many}]}}}}}}"),
        2,
        "components.a.args",
        "arguments; at most 256",
    );
}

#[test]
fn a_loop_of_reactive_components_that_nothing_feeds_is_refused() {
    let f = fixture();
    let looped = |a_redundancy: &str| {
        format!(
            r#"{{"name": "x", "components": {{
  "a": {{"exec": "run.sh", "redundancy": "{a_redundancy}", "timeout_us": 1000}},
  "b": {{"exec": "run.sh", "redundancy": "tmr", "timeout_us": 1000}}
}},
 "channels": [{{"from": "a.out", "to": "b.in"}}, {{"from": "b.out", "to": "a.in"}}]}}"#
        )
    };
    f.fails(
        &looped("dmr"),
        2,
        "components.a",
        "reactive components `a`, `b` can never start a round",
    );
    // An unprotected component in the loop sends on its own (the robot's simulator does).
    assert!(parse("sys.json", &looped("none"), &f.ctx).is_ok());
}

#[test]
fn wrong_types_name_the_field() {
    let f = fixture();
    f.fails(
        "{\"name\": \"x\", \"components\": {\n \"a\": {\"exec\": \"run.sh\",\n \"args\": \"--fast\"}}}",
        3,
        "components.a.args",
        "invalid type",
    );
}

#[test]
fn cpu_list_format() {
    assert_eq!(parse_cpu_list("0-3,6,8-9\n"), [0, 1, 2, 3, 6, 8, 9]);
    assert_eq!(parse_cpu_list("0"), [0]);
    assert!(parse_cpu_list("").is_empty());
}

#[test]
fn unreadable_file() {
    let f = fixture();
    let e = load(&f.dir.path().join("absent.json"), &f.ctx).unwrap_err();
    assert!(e.to_string().contains("cannot read the description"), "{e}");
    assert_eq!(e.line(), 0);
}

#[test]
fn protected_component_needs_an_input_that_starts_rounds() {
    let f = fixture();
    f.fails(
        "{\"name\": \"x\", \"components\": {\n \"a\": {\"exec\": \"run.sh\",\n \"redundancy\": \"tmr\", \"timeout_us\": 9},\n \"b\": {\"exec\": \"run.sh\"}},\n \"channels\": [{\"from\": \"a.out\", \"to\": \"b.in\"}]}",
        3,
        "components.a.redundancy",
        "no input that starts a round",
    );
}

#[test]
fn placement_fields_resolve_the_schedule() {
    let f = fixture();
    let plan = f.ok(ECHO);
    let echo = &plan.components[1];
    assert_eq!(echo.schedule, Schedule::Sequential, "3 replicas on 2 CPUs");
    assert!(echo.schedule_auto);
    assert_eq!(echo.voter_cpu, None);
    let plan = f.ok(r#"{ "name": "n", "components": {
  "s": { "exec": "run.sh" },
  "e": { "exec": "run.sh", "redundancy": "dmr", "timeout_us": 10, "cpus": [1, 0],
         "voter_cpu": 1, "schedule": "sequential" } },
  "channels": [ { "from": "s.out", "to": "e.in" } ] }"#);
    let e = &plan.components[1];
    assert_eq!(
        (e.schedule, e.schedule_auto, e.voter_cpu),
        (Schedule::Sequential, false, Some(1))
    );
    assert!(plan.warnings.is_empty(), "{:?}", plan.warnings);
}

#[test]
fn placement_warnings() {
    let f = fixture();
    let plan = f.ok(r#"{ "name": "n", "components": {
  "s": { "exec": "run.sh", "priority": 70, "schedule": "parallel", "voter_cpu": 0 },
  "e": { "exec": "run.sh", "redundancy": "tmr", "timeout_us": 10, "cpus": [0],
         "schedule": "parallel" } },
  "channels": [ { "from": "s.out", "to": "e.in" } ] }"#);
    let w = plan.warnings.join("\n");
    assert!(
        w.contains("component s: priority 70 is at or above 50"),
        "{w}"
    );
    assert!(
        w.contains("component s: `schedule` is ignored without redundancy"),
        "{w}"
    );
    assert!(
        w.contains("component s: `voter_cpu` is ignored without redundancy"),
        "{w}"
    );
    assert!(
        w.contains("component e: `schedule: parallel` with 3 replicas on 1 CPU(s)"),
        "{w}"
    );
    assert_eq!(plan.warnings.len(), 4, "{w}");
}

#[test]
fn placement_errors() {
    let f = fixture();
    let sys = |echo: &str| {
        format!(
            r#"{{ "name": "n", "components": {{
  "s": {{ "exec": "run.sh" }},
  "e": {{ "exec": "run.sh", "redundancy": "tmr", "timeout_us": 10,
         {echo} }} }},
  "channels": [ {{ "from": "s.out", "to": "e.in" }} ] }}"#
        )
    };
    f.fails(
        &sys(r#""voter_cpu": 7"#),
        4,
        "components.e.voter_cpu",
        "CPU 7 does not exist on this machine",
    );
    f.fails(
        &sys(r#""priority": 4"#),
        4,
        "components.e.priority",
        "priority 4 is too low for 3 replica(s)",
    );
    f.fails(
        &sys(r#""schedule": "round-robin""#),
        4,
        "components.e.schedule",
        "unknown variant `round-robin`",
    );
}

// ----- monitored fields, detectors, capture --------------------------------------------------

const XY_FIELDS: &str =
    r#"[{"name": "x", "type": "f64", "offset": 0}, {"name": "y", "type": "f64", "offset": 8}]"#;

/// Trains a Gaussian model on smooth (x, y) frames and saves it as `name` in the fixture.
fn xy_model(f: &Fixture, name: &str) {
    let layout: FieldLayout = serde_json::from_str(XY_FIELDS).unwrap();
    let mut t = s3res_anomaly::Trainer::new(layout, s3res_anomaly::Preprocess::default());
    for k in 0..200 {
        let mut frame = (k as f64).sin().to_le_bytes().to_vec();
        frame.extend_from_slice(&(k as f64).cos().to_le_bytes());
        t.push(&frame).unwrap();
    }
    t.gaussian(6.0, 1e-6)
        .unwrap()
        .save(&f.dir.path().join(name))
        .unwrap();
}

/// `a` (protected with `redundancy`) writes channel 1; `extra` is added to that channel.
fn monitored(redundancy: &str, extra: &str) -> String {
    format!(
        r#"{{
  "name": "n",
  "components": {{
    "s": {{ "exec": "run.sh" }},
    "a": {{ "exec": "run.sh", "redundancy": "{redundancy}", "timeout_us": 1000 }}
  }},
  "channels": [
    {{ "from": "s.out", "to": "a.in" }},
    {{ "from": "a.out", "to": "stdout", "max_frame": 16,
      {extra} }}
  ]
}}"#
    )
}

#[test]
fn detector_and_capture_go_to_the_writers_voter() {
    let f = fixture();
    xy_model(&f, "xy.json");
    let plan = f.ok(&monitored(
        "dmr",
        &format!(
            r#""fields": {XY_FIELDS}, "detector": {{"model": "xy.json", "kind": "gaussian", "sigma": 8}}, "capture": "cap.bin""#
        ),
    ));
    let a = &plan.components[1];
    assert_eq!(a.monitors.len(), 1);
    assert_eq!(a.monitors[0].output, "out");
    assert_eq!(a.monitors[0].model, f.dir.path().join("xy.json"));
    assert_eq!(a.monitors[0].threshold, Some(8.0));
    assert_eq!(a.monitors[0].fields.len(), 2);
    assert_eq!(a.captures[0].path, f.dir.path().join("cap.bin"));
    let text = plan.describe(None, None);
    assert!(text.contains("detector  on out: fields [x, y]"), "{text}");
    assert!(text.contains("capture   voted frames of out"), "{text}");
}

#[test]
fn a_stream_writer_runs_detectors_and_captures_too() {
    let f = fixture();
    xy_model(&f, "xy.json");
    let stream = |extra: &str| {
        monitored("tmr", extra).replace(
            r#""redundancy": "tmr","#,
            r#""redundancy": "tmr", "mode": "stream","#,
        )
    };
    let plan = f.ok(&stream(&format!(
        r#""fields": {XY_FIELDS}, "detector": {{"model": "xy.json"}}, "capture": "cap.bin""#
    )));
    let a = &plan.components[1];
    assert_eq!(a.mode, Mode::Stream);
    assert_eq!(a.monitors.len(), 1);
    assert_eq!(a.captures[0].path, f.dir.path().join("cap.bin"));
    // The other checks still apply in stream mode.
    f.fails(
        &stream(r#""detector": {"model": "xy.json"}"#),
        10,
        "channels[1].detector",
        "needs the channel's `fields`",
    );
}

#[test]
fn monitoring_errors_name_the_field_and_line() {
    let f = fixture();
    xy_model(&f, "xy.json");
    // A field beyond the channel's largest frame (16 bytes).
    f.fails(
        &monitored(
            "dmr",
            r#""fields": [{"name": "x", "type": "f64", "offset": 0},
                          {"name": "far", "type": "f64", "offset": 12}]"#,
        ),
        11,
        "channels[1].fields[1]",
        "field `far` (f64, offset 12) ends at byte 20, beyond the channel's maximum frame of 16",
    );
    f.fails(
        &monitored(
            "dmr",
            r#""fields": [{"name": "x", "type": "f65", "offset": 0}]"#,
        ),
        10,
        "channels[1].fields[0].type",
        "unknown variant `f65`",
    );
    // The model must exist and match the layout.
    f.fails(
        &monitored(
            "dmr",
            &format!(r#""fields": {XY_FIELDS}, "detector": {{"model": "none.json"}}"#),
        ),
        10,
        "channels[1].detector.model",
        "cannot read model",
    );
    f.fails(
        &monitored(
            "dmr",
            r#""fields": [{"name": "x", "type": "f64", "offset": 0}], "detector": {"model": "xy.json"}"#,
        ),
        10,
        "channels[1].detector.model",
        "trained on fields [x:f64@0, y:f64@8] but the channel declares [x:f64@0]",
    );
    f.fails(
        &monitored(
            "dmr",
            &format!(r#""fields": {XY_FIELDS}, "detector": {{"model": "xy.json", "kind": "autoencoder"}}"#),
        ),
        10,
        "channels[1].detector.kind",
        "is a gaussian model",
    );
    f.fails(
        &monitored(
            "dmr",
            &format!(
                r#""fields": {XY_FIELDS}, "detector": {{"model": "xy.json", "threshold": 2}}"#
            ),
        ),
        10,
        "channels[1].detector.threshold",
        "use `sigma`",
    );
    f.fails(
        &monitored(
            "dmr",
            &format!(r#""fields": {XY_FIELDS}, "detector": {{"model": "xy.json", "sigma": -1}}"#),
        ),
        10,
        "channels[1].detector.sigma",
        "must be a positive number",
    );
    f.fails(
        &monitored("dmr", r#""detector": {"model": "xy.json"}"#),
        10,
        "channels[1].detector",
        "needs the channel's `fields`",
    );
    // Only a voter can run a detector or write a capture.
    f.fails(
        &monitored(
            "none",
            &format!(r#""fields": {XY_FIELDS}, "detector": {{"model": "xy.json"}}"#),
        ),
        10,
        "channels[1].detector",
        "needs a channel written by a protected component",
    );
}

/// ECHO with `extra` inserted after the name (on line 2 of the text).
fn echo_with(extra: &str) -> String {
    ECHO.replacen(
        "\"name\": \"echo-demo\",",
        &format!("\"name\": \"echo-demo\",\n  {extra},"),
        1,
    )
}

/// A run file that cannot be made is refused with the description, naming the field: before,
/// `--check` accepted it and the run failed with the system's error (`File exists` for a
/// folder on the way that is a file, `Device or resource busy` for `"state": "."`).
#[test]
fn run_files_that_cannot_be_made_name_their_field() {
    let f = fixture();
    let notes = f.dir.path().join("notes.txt").display().to_string();
    let dir = f.dir.path().display().to_string();
    f.fails(
        &echo_with(&format!(r#""events": "{notes}/events.jsonl""#)),
        3,
        "events",
        &format!("`{notes}` is a file, not a folder"),
    );
    f.fails(
        &echo_with(&format!(r#""outcome": "{notes}/a/b/task.json""#)),
        3,
        "outcome",
        &format!("`{notes}` is a file, not a folder"),
    );
    f.fails(
        &echo_with(&format!(r#""state": "{dir}""#)),
        3,
        "state",
        &format!("`{dir}` is a folder: give the path of a file (e.g. `{dir}/state.json`)"),
    );
    // Folders still to be made are made by bootstrap.
    f.ok(&echo_with(&format!(
        r#""events": "{dir}/new/deeper/events.jsonl""#
    )));
}

#[test]
fn inject_outputs_and_outcome() {
    let f = fixture();
    let p = f.ok(&echo_with(
        r#""inject": {"faults": ["exec", "cfe"], "rate_hz": 4, "seed": 9},
  "events": "out/events.jsonl", "state": "out/state.json", "outcome": "out/task.json""#,
    ));
    let i = p.inject.expect("inject");
    assert_eq!(i.faults, vec!["exec", "cfe"]);
    assert_eq!((i.rate_hz, i.seed, i.after_s), (4.0, 9, 1.0));
    assert_eq!(
        i.components,
        vec!["echo"],
        "default: the protected components"
    );
    assert_eq!(p.events.as_deref(), Some(Path::new("out/events.jsonl")));
    assert_eq!(p.outcome.as_deref(), Some(Path::new("out/task.json")));
    assert!(f.ok(ECHO).inject.is_none());
}

#[test]
fn inject_errors_name_the_field() {
    let f = fixture();
    f.fails(
        &echo_with(r#""inject": {"faults": ["exec", "boom"]}"#),
        3,
        "inject.faults[1]",
        "unknown fault kind `boom` (known: exec, sdc, cfe)",
    );
    f.fails(
        &echo_with(r#""inject": {"rate_hz": 0}"#),
        3,
        "inject.rate_hz",
        "0 is not a rate",
    );
    f.fails(
        &echo_with(r#""inject": {"rate_hz": 5000}"#),
        3,
        "inject.rate_hz",
        "5000.0 injections per second: at most 1000",
    );
    f.fails(
        &echo_with(r#""inject": {"components": ["sink"]}"#),
        3,
        "inject.components[0]",
        "`sink` is not a protected component (protected: echo)",
    );
    f.fails(
        &echo_with(r#""inject": {"after": 1}"#),
        3,
        "inject.after",
        "unknown field `after`",
    );
}

/// A protected component's choice `field`, as the plan has it (`value`): `default` when
/// absent, `set` when given; a value none of `variants` refused with its line; a warning
/// without redundancy.
fn component_choice_is_passed_on_and_checked(
    field: &str,
    (default, set): (&str, &str),
    bad: &str,
    variants: &str,
    value: impl Fn(&ComponentPlan) -> &'static str,
) {
    let f = fixture();
    let plan = f.ok(&format!(
        r#"{{ "name": "n", "components": {{
  "s": {{ "exec": "run.sh" }},
  "a": {{ "exec": "run.sh", "redundancy": "tmr", "timeout_us": 10 }},
  "u": {{ "exec": "run.sh", "redundancy": "dmr", "timeout_us": 10, "{field}": "{set}" }} }},
  "channels": [ {{ "from": "s.out", "to": "a.in" }}, {{ "from": "a.out", "to": "u.in" }} ] }}"#
    ));
    let of = |name: &str| value(plan.components.iter().find(|c| c.name == name).unwrap());
    assert_eq!(of("a"), default, "{field}'s default");
    assert_eq!(of("u"), set);
    assert!(plan.warnings.is_empty(), "{:?}", plan.warnings);

    f.fails(
        &format!("{{\"name\": \"x\", \"components\": {{\n \"a\": {{\"exec\": \"run.sh\",\n \"redundancy\": \"tmr\", \"{field}\": \"{bad}\"}}}}}}"),
        3,
        &format!("components.a.{field}"),
        &format!("unknown variant `{bad}`, expected {variants}"),
    );
    let plan = f.ok(&format!(
        r#"{{ "name": "n", "components": {{
  "s": {{ "exec": "run.sh", "{field}": "{set}" }} }} }}"#
    ));
    assert_eq!(
        plan.warnings,
        vec![format!(
            "component s: `{field}` is ignored without redundancy"
        )]
    );
}

#[test]
fn cpu_idle_is_passed_on_and_checked() {
    // Idle CPUs sleep by default.
    component_choice_is_passed_on_and_checked(
        "cpu_idle",
        ("halt", "poll"),
        "spin",
        "`halt` or `poll`",
        |c| c.cpu_idle.as_str(),
    );
}

#[test]
fn lock_memory_is_passed_on_and_checked() {
    // The default locks every page.
    component_choice_is_passed_on_and_checked(
        "lock_memory",
        ("all", "used"),
        "some",
        "`all` or `used`",
        |c| c.lock_memory.as_str(),
    );
}

#[test]
fn spin_us_is_passed_on_checked_and_explained() {
    let f = fixture();
    let tmr = |extra: &str| {
        format!(
            r#"{{ "name": "n", "components": {{ "s": {{ "exec": "run.sh" }},
  "e": {{ "exec": "run.sh", "redundancy": "tmr", "timeout_us": 10{extra} }} }},
  "channels": [ {{ "from": "s.out", "to": "e.in" }} ] }}"#
        )
    };
    let spin = |plan: &SystemPlan| {
        plan.components
            .iter()
            .find(|c| c.name == "e")
            .unwrap()
            .spin_us
    };
    // The default, where it spins (voter apart from its replicas) or not.
    let plan = f.ok(&tmr(r#", "cpus": [1], "voter_cpu": 0"#));
    assert_eq!(spin(&plan), s3res_protocol::plan::DEFAULT_SPIN_US);
    assert!(plan.warnings.is_empty(), "{:?}", plan.warnings);
    let plan = f.ok(&tmr(""));
    assert_eq!(spin(&plan), s3res_protocol::plan::DEFAULT_SPIN_US);
    assert!(plan.warnings.is_empty(), "{:?}", plan.warnings);
    // Set, and off.
    let plan = f.ok(&tmr(r#", "cpus": [1], "voter_cpu": 0, "spin_us": 120"#));
    assert_eq!(spin(&plan), 120);
    let plan = f.ok(&tmr(r#", "spin_us": 0"#));
    assert_eq!(spin(&plan), 0);
    assert!(plan.warnings.is_empty(), "{:?}", plan.warnings);
    // Asked for where no answer comes from another CPU: said once, and the system runs.
    for placement in [
        "",
        r#", "voter_cpu": 0"#,
        r#", "cpus": [0, 1], "voter_cpu": 1"#,
    ] {
        let plan = f.ok(&tmr(&format!(r#"{placement}, "spin_us": 30"#)));
        assert_eq!(
            plan.warnings,
            vec![
                "component e: `spin_us` has no effect unless `voter_cpu` is a CPU apart from \
                  the replicas' `cpus` (the voter spins only for answers from other CPUs)"
                    .to_owned()
            ],
            "{placement}"
        );
    }
    f.fails(
        &format!(
            "{{\"name\": \"x\", \"components\": {{\n \"e\": {{\"exec\": \"run.sh\",\n \
             \"redundancy\": \"tmr\", \"timeout_us\": 10, \"spin_us\": {}}}}}}}",
            s3res_protocol::plan::MAX_SPIN_US + 1
        ),
        3,
        "components.e.spin_us",
        "spin_us 1001 is above 1000",
    );
    f.fails(
        "{\"name\": \"x\", \"components\": {\n \"e\": {\"exec\": \"run.sh\",\n \
         \"redundancy\": \"tmr\", \"spin_us\": -5}}}",
        3,
        "components.e.spin_us",
        "invalid value",
    );
    let plan = f.ok(&tmr(
        r#", "mode": "stream", "cpus": [1], "voter_cpu": 0, "spin_us": 30"#,
    ));
    assert_eq!(
        plan.warnings,
        vec![
            "component e: `spin_us` has no effect in stream mode (only a reactive voter spins \
              for its replicas' answers)"
                .to_owned()
        ]
    );
    let plan =
        f.ok(r#"{ "name": "n", "components": { "s": { "exec": "run.sh", "spin_us": 30 } } }"#);
    assert_eq!(
        plan.warnings,
        vec!["component s: `spin_us` is ignored without redundancy".to_owned()]
    );
}
