//! What the tests of the C library share: where the built libraries and the header are,
//! compiling C and C++ with the system's compilers, and running a program under a deadline.

#![allow(dead_code)] // each test binary uses its own part

use std::fs::File;
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::sync::mpsc;
use std::time::Duration;

use s3res_testkit::{RunningSystem, System};

/// What a program linked against the static library needs besides it. (`rustc --print
/// native-static-libs` lists `-lgcc_s -lutil -lrt -lpthread -lm -ldl -lc`: the compiler driver
/// links libgcc_s and libc anyway, and libutil and librt are stubs on glibc ≥ 2.34.)
pub const STATIC_LINK_LIBS: [&str; 3] = ["-lpthread", "-ldl", "-lm"];

/// Bound on one compiler run or one run of a test program.
pub const PROGRAM_LIMIT: Duration = Duration::from_secs(120);

/// The repository's root.
pub fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("replica-c has a parent folder")
        .to_path_buf()
}

/// `replica-c/include`, where `s3res.h` is.
pub fn include_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("include")
}

/// The folder of `libs3res_replica_c.a` and `.so`: the profile folder of this test executable
/// (`<target>/<profile>/deps/<test>` → `<target>/<profile>`). Cargo builds them with the rlib
/// this test links (one rustc run makes every crate type of the library), so they are current.
pub fn lib_dir() -> PathBuf {
    let exe = std::env::current_exe().expect("current_exe");
    let layout = s3res_testkit::bins::Layout::from_test_exe(&exe).expect("test executable layout");
    for dir in [layout.profile_dir.clone(), layout.profile_dir.join("deps")] {
        if dir.join("libs3res_replica_c.a").is_file() && dir.join("libs3res_replica_c.so").is_file()
        {
            return dir;
        }
    }
    panic!(
        "libs3res_replica_c.a/.so not found in {} (cargo build -p s3res-replica-c)",
        layout.profile_dir.display()
    );
}

/// How a program is linked against the library.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Link {
    /// `libs3res_replica_c.a` and [`STATIC_LINK_LIBS`]: a self-contained executable.
    Static,
    /// `-ls3res_replica_c` with an rpath to [`lib_dir`].
    Shared,
}

/// Compiles and links `sources` into `out` with `compiler` (`cc` or `c++`) and `flags`; panics
/// with the compiler's messages if it fails (warnings are errors: `-Werror`).
pub fn compile(compiler: &str, sources: &[PathBuf], out: &Path, link: Link, flags: &[&str]) {
    let lib = lib_dir();
    let mut cmd = Command::new(compiler);
    cmd.args(["-Wall", "-Wextra", "-Werror", "-pedantic", "-O2", "-I"])
        .arg(include_dir())
        .args(flags)
        .args(sources)
        .arg("-o")
        .arg(out);
    match link {
        Link::Static => {
            cmd.arg(lib.join("libs3res_replica_c.a"))
                .args(STATIC_LINK_LIBS);
        }
        Link::Shared => {
            cmd.arg("-L")
                .arg(&lib)
                .arg("-ls3res_replica_c")
                .arg(format!("-Wl,-rpath,{}", lib.display()));
        }
    }
    let out = run(&mut cmd, &[]);
    assert!(
        out.status.success(),
        "{cmd:?} failed ({}):\n{}{}",
        out.status,
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

/// Fails, naming `compiler`, if it cannot be run although the build found it (see build.rs).
pub fn require_compiler(compiler: &str) {
    let answer = Command::new(compiler).arg("--version").output();
    s3res_testkit::require(
        answer.is_ok_and(|o| o.status.success()),
        &format!("`{compiler}` cannot be run"),
    );
}

/// A started program that is killed (and reaped) by [`Watched::finish`], on drop, or by a
/// watchdog once [`PROGRAM_LIMIT`] has passed.
pub struct Watched {
    pub child: Child,
    stop: Option<mpsc::Sender<()>>,
    watchdog: Option<std::thread::JoinHandle<()>>,
}

impl Watched {
    pub fn spawn(cmd: &mut Command) -> Watched {
        let child = cmd
            .spawn()
            .unwrap_or_else(|e| panic!("starting {cmd:?}: {e}"));
        let pid = child.id() as i32;
        let (stop, stopped) = mpsc::channel::<()>();
        // The child is reaped only after this thread has ended, so the pid it kills is ours.
        let watchdog = std::thread::spawn(move || {
            if let Err(mpsc::RecvTimeoutError::Timeout) = stopped.recv_timeout(PROGRAM_LIMIT) {
                let _ = s3res_testkit::kill_pid(pid, libc::SIGKILL);
            }
        });
        Watched {
            child,
            stop: Some(stop),
            watchdog: Some(watchdog),
        }
    }

    /// Closes stdin, reads what is left of stdout and stderr, and reaps the program.
    pub fn finish(mut self) -> Output {
        drop(self.child.stdin.take());
        let mut stdout = Vec::new();
        let mut stderr = Vec::new();
        if let Some(mut s) = self.child.stdout.take() {
            let _ = s.read_to_end(&mut stdout);
        }
        if let Some(mut s) = self.child.stderr.take() {
            let _ = s.read_to_end(&mut stderr);
        }
        self.end_watchdog();
        let status = self.child.wait().expect("waiting for the program");
        Output {
            status,
            stdout,
            stderr,
        }
    }

    fn end_watchdog(&mut self) {
        drop(self.stop.take());
        if let Some(w) = self.watchdog.take() {
            let _ = w.join();
        }
    }
}

impl Drop for Watched {
    fn drop(&mut self) {
        if self.watchdog.is_some() {
            let _ = self.child.kill();
            self.end_watchdog();
            let _ = self.child.wait();
        }
    }
}

/// Runs `cmd` with `stdin` as its input to the end, under the deadline.
pub fn run(cmd: &mut Command, stdin: &[u8]) -> Output {
    cmd.stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    let mut w = Watched::spawn(cmd);
    let mut input = w.child.stdin.take().expect("stdin");
    let bytes = stdin.to_vec();
    // A program may stop reading early (a bad frame): a broken pipe is expected then.
    let writer = std::thread::spawn(move || {
        let _ = input.write_all(&bytes);
    });
    // stderr is read by a thread of its own, so neither pipe can fill up and stall the program.
    let mut err_pipe = w.child.stderr.take().expect("stderr");
    let err_reader = std::thread::spawn(move || {
        let mut v = Vec::new();
        let _ = err_pipe.read_to_end(&mut v);
        v
    });
    let mut out = w.finish();
    writer.join().expect("stdin writer");
    out.stderr = err_reader.join().expect("stderr reader");
    out
}

/// Frames as the wire carries them: a 4-byte little-endian length, then the payload.
pub fn frames(payloads: &[&[u8]]) -> Vec<u8> {
    let mut out = Vec::new();
    for p in payloads {
        out.extend_from_slice(&(p.len() as u32).to_le_bytes());
        out.extend_from_slice(p);
    }
    out
}

/// Splits a byte stream into frame payloads; panics on a partial frame.
pub fn parse_frames(mut bytes: &[u8]) -> Vec<Vec<u8>> {
    let mut out = Vec::new();
    while !bytes.is_empty() {
        assert!(bytes.len() >= 4, "a partial frame header at the end");
        let len = u32::from_le_bytes(bytes[..4].try_into().unwrap()) as usize;
        assert!(bytes.len() >= 4 + len, "a partial frame at the end");
        out.push(bytes[4..4 + len].to_vec());
        bytes = &bytes[4 + len..];
    }
    out
}

/// A TMR system `feeder → exec → stdout` whose feeder copies a FIFO the test writes into
/// (bootstrap's own stdin is read to its end before a test could inject anything). Returns the
/// running system and the FIFO's write end.
pub fn start_fed_system(
    sys: System,
    component: &str,
    exec: &Path,
    timeout_us: u64,
) -> (RunningSystem, File) {
    let fifo = sys.path("samples.fifo");
    let made = Command::new("mkfifo").arg(&fifo).status().expect("mkfifo");
    assert!(made.success(), "mkfifo {}", fifo.display());
    // Read and write: opening never blocks, and the feeder sees the end when we close it.
    let writer = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .open(&fifo)
        .expect("opening the FIFO");
    let description = serde_json::json!({
        "name": "running-mean-tmr",
        "components": {
            "feeder": {
                "exec": "/bin/sh",
                "args": ["-c", format!("exec cat '{}' >&3", fifo.display())],
                "outputs": ["out"]
            },
            component: {
                "exec": exec,
                "redundancy": "tmr",
                "timeout_us": timeout_us,
                "inputs": ["samples"],
                "outputs": ["mean"]
            }
        },
        "channels": [
            { "from": "feeder.out", "to": format!("{component}.samples") },
            { "from": format!("{component}.mean"), "to": "stdout" }
        ]
    });
    let mut run = sys.start_json(&description);
    run.wait_for_replicas(component, 3);
    (run, writer)
}
