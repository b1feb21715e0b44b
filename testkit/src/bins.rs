//! Where the workspace's binaries are, and making sure they are built and current.
//!
//! `cargo test --workspace` builds the normal executables of a package's bin targets only when
//! that package has integration tests of its own; the voter and the components have none, so
//! their executables would be missing, or stale from an earlier build. So the first call here in
//! each test process runs `cargo build --workspace --bins --lib` with the same cargo, target dir and
//! profile as the test executable. Cargo releases its build-directory lock before it runs test
//! executables, so the nested build does not deadlock; when everything is current it is a no-op
//! that takes a fraction of a second.
//!
//! `S3RES_BIN_DIR=/path` skips the build and uses the executables found there (for example
//! `target/release`, to run the end-to-end tests against a release build).
//!
//! [`static_component_dir`] builds the example components again, statically linked, as
//! docs/writing-a-component.md ("Statically linked") tells a user to, and
//! [`musl_component_dir`] builds them small, for musl ("Small replicas"): for the tests that
//! run such builds.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

/// Bound on the build (a cold debug build of the workspace takes about a minute on 2 cores).
const BUILD_LIMIT: Duration = Duration::from_secs(30 * 60);

/// Environment variable naming a directory of already-built executables (no build is run).
pub const BIN_DIR_ENV: &str = "S3RES_BIN_DIR";

/// Path of the workspace executable `name` (for example `s3res-bootstrap`), built and current.
pub fn bin_path(name: &str) -> PathBuf {
    let path = bin_dir().join(name);
    assert!(
        path.is_file(),
        "{} does not exist after building the workspace's binaries",
        path.display()
    );
    path
}

/// The directory holding the workspace's executables (built on first use, see module docs).
pub fn bin_dir() -> &'static Path {
    static DIR: OnceLock<Result<PathBuf, String>> = OnceLock::new();
    once(&DIR, find_or_build)
}

/// What `init` finds, the first time it is asked for in this process (a build, say); a
/// failure panics, every time it is asked for.
fn once(
    cell: &'static OnceLock<Result<PathBuf, String>>,
    init: fn() -> Result<PathBuf, String>,
) -> &'static Path {
    match cell.get_or_init(init) {
        Ok(p) => p,
        Err(e) => panic!("{e}"),
    }
}

fn find_or_build() -> Result<PathBuf, String> {
    if let Some(dir) = std::env::var_os(BIN_DIR_ENV) {
        return Ok(PathBuf::from(dir));
    }
    let layout = test_layout()?;
    let mut cmd = cargo_build(&layout)?;
    cmd.arg("--workspace")
        .arg("--bins")
        // The libraries too: the preload library (a cdylib) is not a bin, and no bin needs it.
        .arg("--lib");
    eprintln!("s3res-testkit: building the workspace's binaries: {cmd:?}");
    run_cargo(cmd)?;
    Ok(layout.profile_dir)
}

/// The folder of the `s3res-components` executables (`s3res-echo`, `s3res-sink`, ...) built
/// statically linked (`RUSTFLAGS=-C target-feature=+crt-static`, with the target named, so
/// that build scripts and proc macros stay dynamic) for the triple and profile of the tests,
/// into a target folder of their own beside the workspace's (`static-components`). Built on
/// first use in each test process; a no-op when current. Needs a static C library (Debian's
/// `libc6-dev`): the tests that call it are ignored without one (`s3res_cc_static`).
pub fn static_component_dir() -> &'static Path {
    static DIR: OnceLock<Result<PathBuf, String>> = OnceLock::new();
    once(&DIR, build_static_components)
}

fn build_static_components() -> Result<PathBuf, String> {
    let layout = test_layout()?;
    let triple = layout
        .triple
        .clone()
        .unwrap_or_else(|| env!("S3RES_TESTKIT_TARGET").to_owned());
    // With `--target`, RUSTFLAGS reach only what is built for the target, not the build
    // scripts and proc macros (which cannot be linked statically).
    build_components(
        Layout::new(
            layout.target_dir.join("static-components"),
            Some(triple),
            layout.profile,
        ),
        Some("-C target-feature=+crt-static"),
        "statically linked",
    )
}

/// The folder of the `s3res-components` executables built small, as
/// docs/writing-a-component.md ("Small replicas") tells a user to: for the musl twin of the
/// tests' target (`x86_64-unknown-linux-musl`), in the workspace's `replica` profile, into a
/// target folder of their own beside the workspace's (`musl-components`). Built on first use
/// in each test process; a no-op when current. Needs that target's standard library (`rustup
/// target add`): the tests that call it are ignored without it (`s3res_musl_target`).
pub fn musl_component_dir() -> &'static Path {
    static DIR: OnceLock<Result<PathBuf, String>> = OnceLock::new();
    once(&DIR, build_musl_components)
}

fn build_musl_components() -> Result<PathBuf, String> {
    let triple = option_env!("S3RES_TESTKIT_MUSL_TARGET").ok_or(
        "the musl target's standard library was not installed when the tests were built \
         (`rustup target add x86_64-unknown-linux-musl`, then `cargo clean -p s3res-testkit`)",
    )?;
    let layout = test_layout()?;
    build_components(
        Layout::new(
            layout.target_dir.join("musl-components"),
            Some(triple.to_owned()),
            "replica".to_owned(),
        ),
        None,
        "for musl, profile `replica`",
    )
}

/// Builds the `s3res-components` executables into `layout` with exactly `rustflags` (none of
/// the caller's), and returns their folder.
fn build_components(layout: Layout, rustflags: Option<&str>, how: &str) -> Result<PathBuf, String> {
    let mut cmd = cargo_build(&layout)?;
    cmd.args(["--package", "s3res-components", "--bins"])
        .env_remove("RUSTFLAGS")
        .env_remove("CARGO_ENCODED_RUSTFLAGS");
    if let Some(flags) = rustflags {
        cmd.env("RUSTFLAGS", flags);
    }
    eprintln!("s3res-testkit: building the components {how}: {cmd:?}");
    run_cargo(cmd)?;
    Ok(layout.profile_dir)
}

/// The layout of the running test executable's build.
fn test_layout() -> Result<Layout, String> {
    let exe = std::env::current_exe().map_err(|e| format!("current_exe: {e}"))?;
    Layout::from_test_exe(&exe)
}

/// A `cargo build` of this workspace into `layout`'s target folder, for its profile and
/// triple, by the cargo that builds the tests; what to build is the caller's to add.
fn cargo_build(layout: &Layout) -> Result<Command, String> {
    let manifest = Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .ok_or("the testkit crate has no parent directory")?
        .join("Cargo.toml");
    let mut cmd = Command::new(env!("CARGO"));
    cmd.arg("build")
        .arg("--manifest-path")
        .arg(&manifest)
        .arg("--target-dir")
        .arg(&layout.target_dir)
        .args(layout.cargo_args())
        .stdin(Stdio::null());
    Ok(cmd)
}

/// Runs a `cargo build`, within [`BUILD_LIMIT`], its output kept for the error.
fn run_cargo(mut cmd: Command) -> Result<(), String> {
    // Output to a file, not a pipe, so a chatty build can never block on a full pipe.
    let log = tempfile::tempfile().map_err(|e| format!("temp file for cargo's output: {e}"))?;
    let log_err = log.try_clone().map_err(|e| format!("dup: {e}"))?;
    cmd.stdout(Stdio::null()).stderr(log_err);
    let mut child = cmd.spawn().map_err(|e| format!("running {cmd:?}: {e}"))?;
    let started = Instant::now();
    let status = loop {
        if let Some(st) = child
            .try_wait()
            .map_err(|e| format!("waiting for cargo: {e}"))?
        {
            break st;
        }
        if started.elapsed() > BUILD_LIMIT {
            let _ = child.kill();
            let _ = child.wait();
            return Err(format!(
                "{cmd:?} did not finish within {BUILD_LIMIT:?} (is the build directory locked?)\n{}",
                read_all(log)
            ));
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    if !status.success() {
        return Err(format!("{cmd:?} failed ({status}):\n{}", read_all(log)));
    }
    Ok(())
}

fn read_all(mut f: std::fs::File) -> String {
    use std::io::{Read, Seek};
    let mut s = String::new();
    let _ = f.rewind();
    let _ = f.read_to_string(&mut s);
    s
}

/// Where a test executable sits: `<target>/[<triple>/]<profile>/deps/<test>-<hash>`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Layout {
    pub target_dir: PathBuf,
    pub triple: Option<String>,
    /// Directory name of the profile (`debug` for the dev and test profiles, `release`, ...).
    pub profile: String,
    /// Where the executables are: `<target>/[<triple>/]<profile>`.
    pub profile_dir: PathBuf,
}

impl Layout {
    /// The layout cargo makes in `target_dir` for `triple` (if named) and `profile`.
    pub fn new(target_dir: PathBuf, triple: Option<String>, profile: String) -> Self {
        let mut profile_dir = target_dir.clone();
        profile_dir.extend(&triple);
        profile_dir.push(&profile);
        Layout {
            target_dir,
            triple,
            profile,
            profile_dir,
        }
    }

    pub fn from_test_exe(exe: &Path) -> Result<Self, String> {
        let bad = || format!("{} is not in <target>/<profile>/deps/", exe.display());
        let deps = exe.parent().ok_or_else(bad)?;
        if deps.file_name().and_then(|n| n.to_str()) != Some("deps") {
            return Err(bad());
        }
        let profile_dir = deps.parent().ok_or_else(bad)?.to_path_buf();
        let profile = profile_dir
            .file_name()
            .and_then(|n| n.to_str())
            .ok_or_else(bad)?
            .to_owned();
        let above = profile_dir.parent().ok_or_else(bad)?;
        // The target dir's root holds CACHEDIR.TAG; with --target there is a <triple> level.
        let (target_dir, triple) = if above.join("CACHEDIR.TAG").exists() {
            (above.to_path_buf(), None)
        } else {
            match (above.parent(), above.file_name().and_then(|n| n.to_str())) {
                (Some(t), Some(triple)) if t.join("CACHEDIR.TAG").exists() => {
                    (t.to_path_buf(), Some(triple.to_owned()))
                }
                _ => (above.to_path_buf(), None),
            }
        };
        Ok(Layout::new(target_dir, triple, profile))
    }

    /// The `cargo build` arguments that select this profile and target.
    pub fn cargo_args(&self) -> Vec<String> {
        let mut args = match self.profile.as_str() {
            "debug" => vec![],
            "release" => vec!["--release".to_owned()],
            other => vec!["--profile".to_owned(), other.to_owned()],
        };
        if let Some(t) = &self.triple {
            args.push("--target".to_owned());
            args.push(t.clone());
        }
        args
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layout_of_a_plain_debug_build() {
        let t = tempfile::tempdir().unwrap();
        std::fs::write(t.path().join("CACHEDIR.TAG"), "").unwrap();
        let exe = t.path().join("debug/deps/e2e-0123abcd");
        let l = Layout::from_test_exe(&exe).unwrap();
        assert_eq!(l.target_dir, t.path());
        assert_eq!(l.profile_dir, t.path().join("debug"));
        assert_eq!(l.triple, None);
        assert!(l.cargo_args().is_empty());
    }

    #[test]
    fn layout_with_triple_and_release() {
        let t = tempfile::tempdir().unwrap();
        std::fs::write(t.path().join("CACHEDIR.TAG"), "").unwrap();
        let exe = t
            .path()
            .join("x86_64-unknown-linux-gnu/release/deps/e2e-0123abcd");
        let l = Layout::from_test_exe(&exe).unwrap();
        assert_eq!(l.target_dir, t.path());
        assert_eq!(l.triple.as_deref(), Some("x86_64-unknown-linux-gnu"));
        assert_eq!(
            l.cargo_args(),
            ["--release", "--target", "x86_64-unknown-linux-gnu"]
        );
    }

    #[test]
    fn layout_rejects_other_places() {
        assert!(Layout::from_test_exe(Path::new("/usr/bin/true")).is_err());
    }

    #[test]
    fn custom_profile() {
        let l = Layout {
            target_dir: "/t".into(),
            triple: None,
            profile: "ci".into(),
            profile_dir: "/t/ci".into(),
        };
        assert_eq!(l.cargo_args(), ["--profile", "ci"]);
    }
}
