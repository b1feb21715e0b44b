//! Probes what this machine allows, for the end-to-end tests that cannot run everywhere. Each
//! such test is `#[cfg_attr(not(s3res_…), ignore = "reason")]`: where it cannot run, `cargo
//! test` lists it as ignored with the reason (and counts it in the summary) instead of passing
//! it silently; where it can (CI runs as root), it runs by default. Each test also checks its
//! condition when it runs and fails, naming it, if the machine disagrees with the build (built
//! as root, run as a user: rebuild, or `cargo clean -p s3res-testkit`).
//!
//! | cfg                 | set when                                                         |
//! |---------------------|------------------------------------------------------------------|
//! | `s3res_pagemap_pfns`| `/proc/self/pagemap` shows page frame numbers (CAP_SYS_ADMIN)     |
//! | `s3res_sched_rr`    | `chrt -r 1 true` succeeds (SCHED_RR allowed: root or CAP_SYS_NICE) and `S3RES_TEST_UNPRIVILEGED` is not set |
//! | `s3res_two_cpus`    | at least two CPUs are usable                                     |
//! | `s3res_prlimit`     | `prlimit` is installed, and `setpriv` too when building as root   |
//! | `s3res_python3`     | `python3` runs                                                   |
//! | `s3res_awk`         | `awk` runs                                                       |
//! | `s3res_mawk`        | `awk` is mawk (the docs' example uses its `-W interactive`)       |
//! | `s3res_cc`          | `cc` compiles and links a C file                                 |
//! | `s3res_cc_static`   | `cc -static` links one too (a static libc is installed)           |
//! | `s3res_pidfd_exit`  | Linux 6.15+: a pidfd tells a non-parent how its process ended     |
//! | `s3res_setcap`      | as root, `setcap` (libcap2-bin) gives a file a capability here, and `setpriv` runs |
//! | `s3res_musl_target` | the toolchain has the standard library of the musl twin of the tests' target (`rustup target add x86_64-unknown-linux-musl`) |

use std::fs::File;
use std::os::unix::fs::FileExt;
use std::process::{Command, Stdio};

const CFGS: [&str; 12] = [
    "s3res_setcap",
    "s3res_pagemap_pfns",
    "s3res_sched_rr",
    "s3res_two_cpus",
    "s3res_prlimit",
    "s3res_python3",
    "s3res_awk",
    "s3res_mawk",
    "s3res_cc",
    "s3res_cc_static",
    "s3res_pidfd_exit",
    "s3res_musl_target",
];

/// The harness's `system::UNPRIVILEGED_ENV`.
const UNPRIVILEGED_ENV: &str = "S3RES_TEST_UNPRIVILEGED";

fn main() {
    for cfg in CFGS {
        println!("cargo::rustc-check-cfg=cfg({cfg})");
    }
    println!("cargo::rerun-if-changed=build.rs");
    // The triple the tests are built for: `bins::static_component_dir` builds for it.
    if let Ok(target) = std::env::var("TARGET") {
        println!("cargo::rustc-env=S3RES_TESTKIT_TARGET={target}");
    }
    // A change of user (sudo, su) probes again.
    for var in ["USER", "SUDO_USER", "HOME", "PATH", UNPRIVILEGED_ENV] {
        println!("cargo::rerun-if-env-changed={var}");
    }
    let set = |cfg: &str, on: bool| {
        if on {
            println!("cargo::rustc-cfg={cfg}");
        }
    };
    set("s3res_pagemap_pfns", pagemap_shows_pfns());
    // `S3RES_TEST_UNPRIVILEGED=1` runs every test system as `nobody`: no SCHED_RR then.
    let unprivileged = std::env::var_os(UNPRIVILEGED_ENV).is_some_and(|v| v != "0");
    set(
        "s3res_sched_rr",
        !unprivileged && succeeds("chrt", &["-r", "1", "true"]),
    );
    set(
        "s3res_two_cpus",
        std::thread::available_parallelism().is_ok_and(|n| n.get() >= 2),
    );
    let tools: &[&str] = if euid_is_root() {
        &["prlimit", "setpriv"]
    } else {
        &["prlimit"]
    };
    set(
        "s3res_prlimit",
        tools.iter().all(|t| succeeds(t, &["--version"])),
    );
    set("s3res_python3", succeeds("python3", &["--version"]));
    set("s3res_awk", succeeds("awk", &["BEGIN { exit 0 }"]));
    set(
        "s3res_mawk",
        Command::new("awk")
            .args(["-W", "version"])
            .stdin(Stdio::null())
            .output()
            .is_ok_and(|o| String::from_utf8_lossy(&o.stdout).contains("mawk")),
    );
    set("s3res_cc", compiles(&[]));
    set("s3res_cc_static", compiles(&["-static"]));
    set("s3res_pidfd_exit", kernel_at_least(6, 15));
    set(
        "s3res_setcap",
        euid_is_root() && succeeds("setpriv", &["--version"]) && gives_a_file_capability(),
    );
    let musl = std::env::var("TARGET").ok().and_then(|t| musl_twin(&t));
    let musl_installed = musl.as_deref().is_some_and(has_standard_library);
    if let (Some(triple), true) = (&musl, musl_installed) {
        // `bins::musl_component_dir` builds for it.
        println!("cargo::rustc-env=S3RES_TESTKIT_MUSL_TARGET={triple}");
    }
    set("s3res_musl_target", musl_installed);
}

/// The musl target beside a glibc one: `x86_64-unknown-linux-gnu` → `x86_64-unknown-linux-musl`.
fn musl_twin(target: &str) -> Option<String> {
    target
        .strip_suffix("-linux-gnu")
        .map(|arch| format!("{arch}-linux-musl"))
}

/// Whether the compiler that builds this crate has `triple`'s standard library installed. Adding
/// a target with rustup rewrites the sysroot's list of components, so that probes again.
fn has_standard_library(triple: &str) -> bool {
    let rustc = std::env::var("RUSTC").unwrap_or_else(|_| "rustc".to_owned());
    let Ok(out) = Command::new(rustc)
        .args(["--print", "sysroot"])
        .stderr(Stdio::null())
        .output()
    else {
        return false;
    };
    let sysroot = std::path::PathBuf::from(String::from_utf8_lossy(&out.stdout).trim());
    let rustlib = sysroot.join("lib").join("rustlib");
    // A missing path would run this script (and rebuild the tests) at every build; a
    // toolchain not installed by rustup has no `components`, and its `rustlib` is watched.
    let components = rustlib.join("components");
    let watched = if components.is_file() {
        components
    } else {
        rustlib.clone()
    };
    if watched.exists() {
        println!("cargo::rerun-if-changed={}", watched.display());
    }
    std::fs::read_dir(rustlib.join(triple).join("lib")).is_ok_and(|entries| {
        entries.flatten().any(|e| {
            let name = e.file_name();
            let name = name.to_string_lossy();
            name.starts_with("libstd-") && name.ends_with(".rlib")
        })
    })
}

/// Whether the running kernel's release (`6.18.4-…`) is `major.minor` or later.
fn kernel_at_least(major: u32, minor: u32) -> bool {
    let Ok(release) = std::fs::read_to_string("/proc/sys/kernel/osrelease") else {
        return false;
    };
    let mut parts = release
        .split(|c: char| !c.is_ascii_digit())
        .map(|p| p.parse::<u32>().unwrap_or(0));
    let (a, b) = (parts.next().unwrap_or(0), parts.next().unwrap_or(0));
    (a, b) >= (major, minor)
}

/// Whether `cc FLAGS` compiles and links a minimal C program.
fn compiles(flags: &[&str]) -> bool {
    let Some(out) = std::env::var_os("OUT_DIR").map(std::path::PathBuf::from) else {
        return false;
    };
    let src = out.join("probe.c");
    if std::fs::write(&src, "int main(void) { return 0; }\n").is_err() {
        return false;
    }
    let exe = out.join("probe");
    let mut args: Vec<&std::ffi::OsStr> = flags.iter().map(std::ffi::OsStr::new).collect();
    args.extend([std::ffi::OsStr::new("-o"), exe.as_os_str(), src.as_os_str()]);
    Command::new("cc")
        .args(args)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success())
}

/// Whether `setcap` gives a file of the build folder a capability (a file system without
/// extended attributes, or no `setcap`, cannot).
fn gives_a_file_capability() -> bool {
    let Some(dir) = std::env::var_os("OUT_DIR") else {
        return false;
    };
    let probe = std::path::Path::new(&dir).join("setcap-probe");
    if std::fs::write(&probe, b"").is_err() {
        return false;
    }
    let probe = probe.to_string_lossy();
    succeeds("setcap", &["cap_sys_nice+ep", &probe])
}

fn succeeds(program: &str, args: &[&str]) -> bool {
    Command::new(program)
        .args(args)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success())
}

/// Whether the page frame number of a page of our own, touched, reads as non-zero.
fn pagemap_shows_pfns() -> bool {
    const PAGE: u64 = 4096;
    let probe = vec![1u8; 4 * PAGE as usize];
    let Ok(pagemap) = File::open("/proc/self/pagemap") else {
        return false;
    };
    let first = probe.as_ptr() as u64 / PAGE;
    let seen = (first..first + 4).any(|page| {
        let mut entry = [0u8; 8];
        pagemap.read_exact_at(&mut entry, page * 8).is_ok()
            && u64::from_le_bytes(entry) & ((1 << 55) - 1) != 0
    });
    std::hint::black_box(&probe);
    seen
}

/// Effective uid 0, from `/proc/self/status` (`Uid: real effective saved fs`).
fn euid_is_root() -> bool {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find_map(|l| l.strip_prefix("Uid:"))
                .and_then(|v| v.split_whitespace().nth(1).map(|e| e == "0"))
        })
        .unwrap_or(false)
}
