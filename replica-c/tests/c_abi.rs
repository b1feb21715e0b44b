//! `include/s3res.h` is true to the library: it declares exactly the functions the library
//! exports and the same constants; a C program that calls every declared function compiles
//! with `-Wall -Wextra -Werror -pedantic`, links against the static and against the shared
//! library, and gets the documented answers; and C++ uses the same header.

mod common;

use std::collections::BTreeSet;
use std::io::{Read, Write};
use std::os::fd::AsRawFd;
use std::path::Path;
use std::process::{Command, Stdio};

use common::{compile, frames, parse_frames, Link, Watched};

const HEADER: &str = include_str!("../include/s3res.h");
const SOURCE: &str = include_str!("../src/lib.rs");
const ABI_CHECK: &str = include_str!("c/abi_check.c");

/// The header without its comments.
fn header_code() -> String {
    let mut out = String::new();
    let mut rest = HEADER;
    while let Some(start) = rest.find("/*") {
        out.push_str(&rest[..start]);
        let end = rest[start..].find("*/").expect("unterminated comment");
        rest = &rest[start + end + 2..];
    }
    out.push_str(rest);
    out
}

/// Every `s3res_…(` in the header's code: the declared functions.
fn declared_functions() -> BTreeSet<String> {
    let code = header_code();
    let mut names = BTreeSet::new();
    for (at, _) in code.match_indices("s3res_") {
        let ident: String = code[at..]
            .chars()
            .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
            .collect();
        if code[at + ident.len()..].trim_start().starts_with('(') {
            names.insert(ident);
        }
    }
    names
}

/// Every function after a `#[no_mangle]` in src/lib.rs: the exported ones.
fn exported_functions() -> BTreeSet<String> {
    let mut names = BTreeSet::new();
    let mut lines = SOURCE.lines();
    while let Some(line) = lines.next() {
        if line.trim() != "#[no_mangle]" {
            continue;
        }
        let decl = lines.next().expect("#[no_mangle] on the last line");
        let after = decl.split("fn ").nth(1).expect("#[no_mangle] not on a fn");
        names.insert(after.split('(').next().unwrap().to_owned());
    }
    names
}

#[test]
fn the_header_declares_exactly_the_exported_functions() {
    let declared = declared_functions();
    let exported = exported_functions();
    assert!(exported.len() > 20, "{exported:?}");
    assert_eq!(
        declared,
        exported,
        "include/s3res.h and src/lib.rs disagree: declared only {:?}, exported only {:?}",
        declared.difference(&exported).collect::<Vec<_>>(),
        exported.difference(&declared).collect::<Vec<_>>()
    );
}

#[test]
fn the_c_check_calls_every_declared_function() {
    let missing: Vec<_> = declared_functions()
        .into_iter()
        .filter(|f| !ABI_CHECK.contains(&format!("{f}(")))
        .collect();
    assert!(
        missing.is_empty(),
        "tests/c/abi_check.c does not call {missing:?}"
    );
}

#[test]
fn the_header_constants_are_the_library_s() {
    use s3res_replica_c as lib;
    let code = header_code();
    let define = |name: &str| -> i32 {
        let line = code
            .lines()
            .find(|l| l.split_whitespace().take(2).eq(["#define", name]))
            .unwrap_or_else(|| panic!("no #define {name} in the header"));
        line.split_whitespace().nth(2).unwrap().parse().unwrap()
    };
    for (name, value) in [
        ("S3RES_MODE_STANDALONE", lib::S3RES_MODE_STANDALONE),
        ("S3RES_MODE_UNPROTECTED", lib::S3RES_MODE_UNPROTECTED),
        ("S3RES_MODE_REPLICA", lib::S3RES_MODE_REPLICA),
        ("S3RES_LOG_ERROR", lib::S3RES_LOG_ERROR),
        ("S3RES_LOG_WARN", lib::S3RES_LOG_WARN),
        ("S3RES_LOG_INFO", lib::S3RES_LOG_INFO),
        ("S3RES_LOG_DEBUG", lib::S3RES_LOG_DEBUG),
        ("S3RES_LOG_TRACE", lib::S3RES_LOG_TRACE),
    ] {
        assert_eq!(define(name), value, "{name}");
    }
    assert!(code.contains("#define S3RES_NO_TIMEOUT (-1)"));
}

/// The port map abi_check.c expects: `in` on stdin (1024 bytes), `out` on stdout (64 bytes),
/// `aux` on fd 3.
const ABI_PORTS: &str = r#"{"ports":[{"name":"in","dir":"in","fd":0,"max_frame":1024},{"name":"out","dir":"out","fd":1,"max_frame":64},{"name":"aux","dir":"in","fd":3,"max_frame":1024}]}"#;

/// Reads one frame from `r` (blocking; the watchdog bounds it).
fn read_frame(r: &mut impl Read) -> Vec<u8> {
    let mut header = [0u8; 4];
    r.read_exact(&mut header).expect("reading a frame header");
    let mut payload = vec![0u8; u32::from_le_bytes(header) as usize];
    r.read_exact(&mut payload).expect("reading a frame");
    payload
}

/// Builds tests/c/abi_check.c linked as `link` and holds the conversation its comment
/// describes.
fn abi_check(link: Link) {
    common::require_compiler("cc");
    let dir = tempfile::tempdir().unwrap();
    let exe = dir.path().join("abi_check");
    let source = common::repo_root().join("replica-c/tests/c/abi_check.c");
    compile("cc", &[source], &exe, link, &["-std=c11"]);

    let mut cmd = Command::new(&exe);
    cmd.env("S3RES_PORTS", ABI_PORTS)
        .env_remove("S3RES_VOTER_SOCKET")
        .env_remove("S3RES_REPLICA")
        .env_remove("S3RES_COMPONENT")
        .env("RUST_LOG", "debug")
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    let (aux_read, aux_write) = replica_rt::sys::pipe().unwrap();
    replica_rt::sys::map_fds_on_exec(&mut cmd, vec![(aux_read.as_raw_fd(), 3)]);
    let mut w = Watched::spawn(&mut cmd);
    drop(aux_read);
    let mut aux = std::fs::File::from(aux_write);
    let mut input = w.child.stdin.take().unwrap();
    let mut output = w.child.stdout.take().unwrap();
    aux.write_all(&frames(&[b"side"])).unwrap();
    assert_eq!(read_frame(&mut output), b"side");
    input.write_all(&frames(&[b"one"])).unwrap();
    assert_eq!(read_frame(&mut output), b"one");
    input.write_all(&frames(&[b"two", b"three"])).unwrap();
    assert_eq!(read_frame(&mut output), b"two");
    assert_eq!(read_frame(&mut output), b"three");
    drop(input);
    drop(aux);
    assert_eq!(read_frame(&mut output), b"");
    let mut rest = Vec::new();
    output.read_to_end(&mut rest).unwrap();
    let out = w.finish();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{}: {stderr}", out.status);
    assert!(rest.is_empty(), "extra output: {rest:?}");
    assert!(stderr.contains("abi check passed"), "{stderr}");
    // The runtime's logger carries the component's own lines, prefixed with its name.
    assert!(stderr.contains("[abi-check pid "), "{stderr}");
}

#[test]
#[cfg_attr(not(s3res_cc), ignore = "no C compiler (`cc`) on this machine")]
fn every_function_works_from_c_linked_statically() {
    abi_check(Link::Static);
}

#[test]
#[cfg_attr(not(s3res_cc), ignore = "no C compiler (`cc`) on this machine")]
fn every_function_works_from_c_linked_against_the_shared_library() {
    abi_check(Link::Shared);
}

/// C++ includes the same header (its declarations are `extern "C"`): tests/c/echo.cpp, a
/// C++17 echo that owns its handles with `unique_ptr`, and the C example itself compiled as
/// C++, both with `-Werror -pedantic`, linked against the shared library; the echo runs in
/// standalone mode (stdin → stdout).
#[test]
#[cfg_attr(not(s3res_cxx), ignore = "no C++ compiler (`c++`) on this machine")]
fn cxx_uses_the_same_header() {
    common::require_compiler("c++");
    let dir = tempfile::tempdir().unwrap();
    let root = common::repo_root();
    let echo = dir.path().join("cxx_echo");
    let builds: [(&str, &Path, &[&str]); 2] = [
        ("replica-c/tests/c/echo.cpp", &echo, &["-std=c++17"]),
        (
            "examples/c-running-mean/running_mean.c",
            &dir.path().join("cxx_running_mean"),
            &["-x", "c++", "-std=c++17"],
        ),
    ];
    for (source, exe, flags) in builds {
        compile("c++", &[root.join(source)], exe, Link::Shared, flags);
    }

    let payloads: [&[u8]; 4] = [b"alpha", b"", b"gamma", &[0u8; 300]];
    let mut cmd = Command::new(&echo);
    cmd.env_remove("S3RES_PORTS")
        .env_remove("S3RES_VOTER_SOCKET")
        .env_remove("S3RES_REPLICA");
    let out = common::run(&mut cmd, &frames(&payloads));
    assert!(
        out.status.success(),
        "{}: {}",
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(parse_frames(&out.stdout), payloads.map(<[u8]>::to_vec));
}
