//! A running s3res system: `s3res-bootstrap` started on a description written into a fresh temp
//! dir, as the leader of its own process group, so that every process the system causes to
//! exist can be found and killed, and torn down on drop even when the test fails.

use std::collections::BTreeMap;
use std::fs::File;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Mutex, MutexGuard, Once, OnceLock};
use std::thread::sleep;
use std::time::{Duration, Instant};

use std::os::unix::process::CommandExt;

use s3res_protocol::event::Event;
use tempfile::TempDir;

use crate::bins::bin_path;
use crate::events::{parse_events, replica_pids};
use crate::procs::{self, ProcStat};
use crate::spawner::spawn_tied_to_this_process;
use crate::tail;

/// `S3RES_KEEP_TMP=1` keeps each test's temp dir (its path is printed) for a post-mortem.
pub const KEEP_TMP_ENV: &str = "S3RES_KEEP_TMP";

/// Environment variable set on bootstrap with a value unique to the system; every process the
/// system causes to exist inherits it, so one that left the process group is still found.
pub const MARK_ENV: &str = "S3RES_TEST_SYSTEM";

/// `S3RES_TEST_UNPRIVILEGED=1` starts every test system as an unprivileged user (as
/// [`System::unprivileged`] does), so the whole suite can be run that way.
pub const UNPRIVILEGED_ENV: &str = "S3RES_TEST_UNPRIVILEGED";

/// The user and group an unprivileged system runs as when the tests run as root: `nobody`.
pub const UNPRIVILEGED_ID: u32 = 65534;

/// How long drop waits for bootstrap to stop by itself after SIGTERM.
const TERM_GRACE: Duration = Duration::from_secs(3);
/// bootstrap's keeper's process name (`s3res_bootstrap::keeper::KEEPER_NAME`).
const KEEPER_COMM: &str = "s3res-keeper";
/// How long a dead process may linger (as a zombie being reaped) before it counts as left.
const ZOMBIE_GRACE: Duration = Duration::from_secs(2);
const POLL: Duration = Duration::from_millis(10);

/// A system about to be started: a fresh temp dir, the description, optional stdin bytes.
pub struct System {
    dir: TempDir,
    stdin: Option<Vec<u8>>,
    /// bootstrap's stdin from a pipe the test holds the other end of (instead of `stdin`).
    stdin_pipe: Option<std::os::fd::OwnedFd>,
    /// bootstrap's stdout to this file instead of `stdout.txt` (which stays empty).
    stdout_file: Option<File>,
    events: bool,
    unprivileged: bool,
    /// Extra bootstrap options, before the description.
    args: Vec<std::ffi::OsString>,
    /// Extra environment for bootstrap (and so for every process it starts).
    envs: Vec<(std::ffi::OsString, std::ffi::OsString)>,
}

impl Default for System {
    fn default() -> Self {
        Self::new()
    }
}

impl System {
    /// A fresh temp dir to build the system in.
    pub fn new() -> Self {
        let dir = tempfile::Builder::new()
            .prefix("s3res-test-")
            .tempdir()
            .expect("creating a temp dir");
        System {
            dir,
            stdin: None,
            stdin_pipe: None,
            stdout_file: None,
            events: true,
            unprivileged: std::env::var_os(UNPRIVILEGED_ENV).is_some_and(|v| v != "0"),
            args: Vec::new(),
            envs: Vec::new(),
        }
    }

    /// Runs the system as an unprivileged user: when the tests run as root, bootstrap is
    /// started through `setpriv` as `nobody` (uid and gid 65534, no supplementary groups, so
    /// no capabilities), and the temp dir is handed to that user; when they do not run as
    /// root, the system already is unprivileged and starts as usual. bootstrap is still the
    /// leader of its own process group (`setpriv` execs it in place), so teardown is unchanged.
    pub fn unprivileged(mut self) -> Self {
        self.unprivileged = true;
        self
    }

    /// Whether the system's processes will be allowed SCHED_RR: tried on a throwaway process
    /// started the way bootstrap will be (`chrt -r 1 true`, through `setpriv` when the system
    /// is to drop to `nobody`).
    pub fn round_robin_allowed(&self) -> bool {
        let mut cmd = if self.unprivileged && is_root() {
            as_nobody("chrt")
        } else {
            Command::new("chrt")
        };
        cmd.args(["-r", "1", "true"])
            .stdout(Stdio::null())
            .stderr(Stdio::null());
        cmd.status()
            .unwrap_or_else(|e| panic!("running chrt (util-linux): {e}"))
            .success()
    }

    /// Whether this system's processes will lack root's privileges (see
    /// [`System::unprivileged`]).
    pub fn runs_unprivileged(&self) -> bool {
        self.unprivileged || !is_root()
    }

    /// The temp dir (bootstrap's working directory).
    pub fn dir(&self) -> &Path {
        self.dir.path()
    }

    /// `dir()/name`: a place for a file the system writes or reads (a sink's summary, ...).
    pub fn path(&self, name: &str) -> PathBuf {
        self.dir.path().join(name)
    }

    /// Bytes for bootstrap's stdin (from a file, so it can never block on a pipe).
    pub fn stdin(mut self, bytes: impl Into<Vec<u8>>) -> Self {
        self.stdin = Some(bytes.into());
        self
    }

    /// The read end of a pipe as bootstrap's stdin: input that ends only when the test closes
    /// the write end, as a producer piped into bootstrap (`sensor | s3res-bootstrap ...`).
    pub fn stdin_pipe(mut self, read_end: std::os::fd::OwnedFd) -> Self {
        self.stdin_pipe = Some(read_end);
        self
    }

    /// bootstrap's stdout to `file` (say `/dev/full`) instead of `stdout.txt`, which stays
    /// empty then.
    pub fn stdout_file(mut self, file: File) -> Self {
        self.stdout_file = Some(file);
        self
    }

    /// One more bootstrap option (e.g. `--state`, then a path), placed before the description.
    pub fn arg(mut self, arg: impl Into<std::ffi::OsString>) -> Self {
        self.args.push(arg.into());
        self
    }

    /// One more environment variable for bootstrap and everything it starts (e.g. `TMPDIR`).
    pub fn env(
        mut self,
        key: impl Into<std::ffi::OsString>,
        value: impl Into<std::ffi::OsString>,
    ) -> Self {
        self.envs.push((key.into(), value.into()));
        self
    }

    /// Do not pass `--events` (the plain `s3res-bootstrap SYSTEM.json` command line).
    pub fn without_events(mut self) -> Self {
        self.events = false;
        self
    }

    /// Writes `description` to `dir()/system.json` and starts
    /// `s3res-bootstrap --events dir()/events.jsonl dir()/system.json` in `dir()`.
    pub fn start(self, description: &str) -> RunningSystem {
        let bootstrap = bin_path("s3res-bootstrap");
        self.start_exec(&bootstrap, description)
    }

    /// Like [`System::start`] with a JSON value (written pretty-printed).
    pub fn start_json(self, description: &serde_json::Value) -> RunningSystem {
        let text = serde_json::to_string_pretty(description).expect("JSON always serializes");
        self.start(&text)
    }

    /// Like [`System::start`] with another program in bootstrap's place (it gets the same
    /// command line). For testing the harness itself.
    pub fn start_with(self, bootstrap: &Path, description: &str) -> RunningSystem {
        self.start_exec(bootstrap, description)
    }

    fn start_exec(mut self, bootstrap: &Path, description: &str) -> RunningSystem {
        reap_orphans_here();
        let desc = self.path("system.json");
        std::fs::write(&desc, description).expect("writing system.json");
        let events = self.events.then(|| self.path("events.jsonl"));
        let stdout = self.path("stdout.txt");
        let stderr = self.path("stderr.txt");

        static COUNTER: AtomicU64 = AtomicU64::new(0);
        let mark = format!(
            "{}-{}",
            std::process::id(),
            COUNTER.fetch_add(1, Ordering::Relaxed)
        );
        let mut cmd = if self.unprivileged && is_root() {
            self.hand_dir_to_unprivileged_user();
            as_nobody(bootstrap)
        } else {
            Command::new(bootstrap)
        };
        cmd.env(MARK_ENV, &mark);
        cmd.envs(self.envs.iter().map(|(k, v)| (k, v)));
        if let Some(ev) = &events {
            cmd.arg("--events").arg(ev);
        }
        cmd.args(&self.args)
            .arg(&desc)
            .current_dir(self.dir.path())
            .stdout(match self.stdout_file.take() {
                Some(file) => {
                    File::create(&stdout).expect("creating stdout.txt");
                    file
                }
                None => File::create(&stdout).expect("creating stdout.txt"),
            })
            .stderr(File::create(&stderr).expect("creating stderr.txt"))
            .process_group(0);
        match (&self.stdin, self.stdin_pipe.take()) {
            (_, Some(pipe)) => {
                cmd.stdin(Stdio::from(pipe));
            }
            (Some(bytes), None) => {
                let p = self.path("stdin.bin");
                std::fs::write(&p, bytes).expect("writing stdin.bin");
                cmd.stdin(File::open(&p).expect("opening stdin.bin"));
            }
            (None, None) => {
                cmd.stdin(Stdio::null());
            }
        }
        // Spawn and register under the lock, so that no other test's orphan reaping can take
        // a bootstrap that exits at once for an adopted orphan and steal its exit status.
        let mut bootstraps = lock_bootstraps();
        let child = spawn_tied_to_this_process(cmd)
            .unwrap_or_else(|e| panic!("starting {}: {e}", bootstrap.display()));
        let pgid = child.id() as i32;
        bootstraps.push(pgid);
        drop(bootstraps);
        RunningSystem {
            dir: Some(self.dir),
            child,
            pgid,
            mark,
            status: None,
            events,
            stdout,
            stderr,
            torn_down: false,
        }
    }
}

impl System {
    /// The unprivileged user must be able to create files (events, summaries) in the temp
    /// dir and use what the test put there (a FIFO, inputs): the dir and its entries are
    /// handed to it. (The harness, as root, still reads and removes everything.)
    fn hand_dir_to_unprivileged_user(&self) {
        use std::os::unix::fs::PermissionsExt;
        let dir = self.dir.path();
        let give = |p: &Path| {
            std::os::unix::fs::chown(p, Some(UNPRIVILEGED_ID), Some(UNPRIVILEGED_ID))
                .unwrap_or_else(|e| panic!("handing {} to uid {UNPRIVILEGED_ID}: {e}", p.display()))
        };
        give(dir);
        std::fs::set_permissions(dir, std::fs::Permissions::from_mode(0o755))
            .unwrap_or_else(|e| panic!("chmod {}: {e}", dir.display()));
        for entry in std::fs::read_dir(dir)
            .expect("listing the temp dir")
            .flatten()
        {
            give(&entry.path());
        }
    }
}

/// Whether the tests run as root (then an unprivileged system must drop to another user).
pub fn is_root() -> bool {
    replica_rt::sys::effective_uid() == 0
}

/// `setpriv` (util-linux): on Debian/Ubuntu in `/usr/bin`. Panics naming the package if absent.
fn setpriv() -> PathBuf {
    for dir in ["/usr/bin", "/bin", "/usr/sbin", "/sbin"] {
        let p = Path::new(dir).join("setpriv");
        if p.exists() {
            return p;
        }
    }
    panic!("an unprivileged test run needs `setpriv` (package util-linux), which is not installed");
}

/// `program` run as [`UNPRIVILEGED_ID`] (`nobody`, groups cleared) through `setpriv`, by a
/// test running as root. A change of user clears the parent-death signal
/// ([`spawn_tied_to_this_process`]); `setpriv` is told to keep it where it can.
pub fn as_nobody(program: impl AsRef<std::ffi::OsStr>) -> Command {
    let mut cmd = Command::new(setpriv());
    cmd.arg(format!("--reuid={UNPRIVILEGED_ID}"))
        .arg(format!("--regid={UNPRIVILEGED_ID}"))
        .arg("--clear-groups");
    if setpriv_keeps_pdeathsig() {
        cmd.arg("--pdeathsig=keep");
    }
    cmd.arg("--").arg(program);
    cmd
}

/// Whether this `setpriv` has `--pdeathsig` (util-linux 2.33 and later).
fn setpriv_keeps_pdeathsig() -> bool {
    static KEEPS: OnceLock<bool> = OnceLock::new();
    *KEEPS.get_or_init(|| {
        Command::new(setpriv())
            .arg("--help")
            .stdin(Stdio::null())
            .stderr(Stdio::null())
            .output()
            .is_ok_and(|out| String::from_utf8_lossy(&out.stdout).contains("--pdeathsig"))
    })
}

/// What a finished system left: exit status, bootstrap's output, and the event log.
#[derive(Debug, Clone)]
pub struct Outcome {
    pub status: ExitStatus,
    pub stdout: String,
    pub stderr: String,
    pub events: Vec<Event>,
}

impl Outcome {
    /// The `voter_restart` events, which must be `kills` (one per voter killed); prints how
    /// long the restarts took (median, max).
    pub fn voter_restarts(&self, kills: usize) -> Vec<&Event> {
        use s3res_protocol::event::EventKind;
        let restarts: Vec<&Event> = self
            .events
            .iter()
            .filter(|e| e.kind == EventKind::VoterRestart)
            .collect();
        assert_eq!(restarts.len(), kills, "voter_restart events: {restarts:#?}");
        let mut took: Vec<u64> = restarts.iter().filter_map(|e| e.recovery_us).collect();
        took.sort_unstable();
        if let (Some(median), Some(max)) = (took.get(took.len() / 2), took.last()) {
            eprintln!(
                "voter restart (bootstrap saw it gone -> adopted), us: median {median} max {max}"
            );
        }
        restarts
    }

    /// The fault events (everything but `start`, `recovery`, `anomaly`, `voter_restart`,
    /// `lost` and `diverged`: an alarm is an opinion, what the voter concluded from it is a
    /// fault event of its own; a voter restart is about the voter, not a replica; a frame lost
    /// is what faults cost, not a fault; a replica diverged for a state no fork could give
    /// back is kept, not faulted).
    pub fn faults(&self) -> Vec<&Event> {
        use s3res_protocol::event::EventKind;
        self.events
            .iter()
            .filter(|e| {
                !matches!(
                    e.kind,
                    EventKind::Start
                        | EventKind::Recovery
                        | EventKind::Anomaly
                        | EventKind::VoterRestart
                        | EventKind::Lost
                        | EventKind::Diverged
                )
            })
            .collect()
    }
}

/// A started system. Dropping it stops bootstrap (SIGTERM, then SIGKILL to the whole process
/// group), reaps it, and fails the test if any process of the group is left. If the test
/// process itself dies (Ctrl-C, a time limit's SIGKILL), the kernel SIGKILLs bootstrap, which
/// takes its system with it (`spawner.rs`).
pub struct RunningSystem {
    dir: Option<TempDir>,
    child: Child,
    pgid: i32,
    mark: String,
    status: Option<ExitStatus>,
    events: Option<PathBuf>,
    stdout: PathBuf,
    stderr: PathBuf,
    torn_down: bool,
}

impl RunningSystem {
    /// Bootstrap's pid, which is also the process group of the whole system.
    pub fn pid(&self) -> i32 {
        self.pgid
    }

    /// The value of [`MARK_ENV`] that every process of this system carries.
    pub fn mark(&self) -> &str {
        &self.mark
    }

    pub fn pgid(&self) -> i32 {
        self.pgid
    }

    pub fn dir(&self) -> &Path {
        self.dir.as_ref().expect("temp dir present").path()
    }

    pub fn path(&self, name: &str) -> PathBuf {
        self.dir().join(name)
    }

    /// Bootstrap's stderr so far.
    pub fn stderr(&self) -> String {
        read_lossy(&self.stderr)
    }

    /// Bootstrap's stdout so far.
    pub fn stdout(&self) -> String {
        read_lossy(&self.stdout)
    }

    /// Bootstrap's exit status if it has exited (reaping it).
    pub fn try_status(&mut self) -> Option<ExitStatus> {
        if self.status.is_none() {
            self.status = self.child.try_wait().expect("waitpid on bootstrap");
        }
        self.status
    }

    /// Waits for bootstrap to exit. On timeout: tears the system down and panics with the tail
    /// of bootstrap's stderr.
    pub fn wait(&mut self, timeout: Duration) -> Outcome {
        let deadline = Instant::now() + timeout;
        loop {
            if let Some(status) = self.try_status() {
                return Outcome {
                    status,
                    stdout: self.stdout(),
                    stderr: self.stderr(),
                    events: self.events(),
                };
            }
            if Instant::now() >= deadline {
                self.teardown_and_panic(&format!("bootstrap did not exit within {timeout:?}"));
            }
            sleep(POLL);
        }
    }

    /// Every complete event in the log so far (empty if none yet).
    pub fn events(&self) -> Vec<Event> {
        let Some(path) = &self.events else {
            return Vec::new();
        };
        let text = read_lossy(path);
        parse_events(&text).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
    }

    /// Waits until an event satisfying `pred` is in the log and returns the first such event.
    /// Panics (after tearing down) on timeout, or if bootstrap exits without it appearing.
    pub fn wait_for_event(
        &mut self,
        mut pred: impl FnMut(&Event) -> bool,
        timeout: Duration,
    ) -> Event {
        assert!(self.events.is_some(), "system started without --events");
        let deadline = Instant::now() + timeout;
        loop {
            let exited = self.try_status();
            if let Some(e) = self.events().into_iter().find(|e| pred(e)) {
                return e;
            }
            if let Some(st) = exited {
                self.teardown_and_panic(&format!(
                    "bootstrap exited ({st}) without the awaited event; events:\n{}",
                    self.events_summary()
                ));
            }
            if Instant::now() >= deadline {
                self.teardown_and_panic(&format!(
                    "awaited event did not come within {timeout:?}; events:\n{}",
                    self.events_summary()
                ));
            }
            sleep(POLL);
        }
    }

    /// Current pid of each replica slot of `component`, from the event log.
    pub fn replica_pids(&self, component: &str) -> BTreeMap<usize, i32> {
        replica_pids(&self.events(), component)
    }

    /// The pid of this system's process whose command name is `comm` (an unprotected
    /// component, say `s3res-source`), if there is exactly one.
    pub fn process_named(&self, comm: &str) -> Option<i32> {
        let mut found = crate::procs::in_group(self.pgid())
            .into_iter()
            .filter(|p| p.comm == comm && !p.is_zombie());
        let first = found.next()?;
        found.next().is_none().then_some(first.pid)
    }

    /// The pid of the voter of `component` in this system (its plan, on its command line,
    /// names the component), if it runs.
    pub fn voter_of(&self, component: &str) -> Option<i32> {
        let needle = format!("\"component\":\"{component}\"");
        crate::procs::in_group(self.pgid())
            .into_iter()
            .filter(|p| p.comm == "s3res-voter" && !p.is_zombie())
            .find(|p| {
                std::fs::read(format!("/proc/{}/cmdline", p.pid))
                    .is_ok_and(|c| String::from_utf8_lossy(&c).contains(&needle))
            })
            .map(|p| p.pid)
    }

    /// Waits until the system's one `s3res-voter` is a process other than `old` (the successor
    /// bootstrap starts when a voter dies); its pid. Panics, with bootstrap's last lines, if
    /// none comes within `timeout` or the system ends first.
    pub fn next_voter(&mut self, old: i32, timeout: std::time::Duration) -> i32 {
        let deadline = std::time::Instant::now() + timeout;
        loop {
            if let Some(pid) = self.process_named("s3res-voter").filter(|&p| p != old) {
                return pid;
            }
            if self.try_status().is_some() || std::time::Instant::now() >= deadline {
                let out = self.wait(std::time::Duration::from_secs(10));
                panic!(
                    "no new voter after {old} was killed (bootstrap: {}):\n{}",
                    out.status,
                    crate::tail(&out.stderr, 30)
                );
            }
            std::thread::sleep(std::time::Duration::from_millis(2));
        }
    }

    /// SIGKILLs the system's voter `kills` times, each at a seeded random moment 110–310 ms
    /// after the last one's successor appeared (anywhere in a round, or between; at most 9 a
    /// second, within the default restart budget of 10 within 1 s), waiting for each
    /// successor. Panics if the system ends before the last kill (feed it more).
    pub fn kill_voter_repeatedly(&mut self, rng: &mut crate::Rng, kills: usize) {
        let mut voter = self.process_named("s3res-voter").expect("the voter");
        for kill in 0..kills {
            std::thread::sleep(std::time::Duration::from_micros(
                110_000 + rng.below(200_000),
            ));
            assert!(
                self.try_status().is_none(),
                "the system ended before kill {kill}; feed it more"
            );
            crate::kill_pid(voter, libc::SIGKILL).expect("kill the voter");
            let killed = std::time::Instant::now();
            voter = self.next_voter(voter, std::time::Duration::from_secs(10));
            eprintln!(
                "kill {kill}: new voter {voter} after {:?}",
                killed.elapsed()
            );
        }
    }

    /// Asks bootstrap to stop the system (SIGTERM).
    pub fn stop(&mut self) {
        if self.try_status().is_none() {
            let _ = crate::kill_pid(self.pgid, libc::SIGTERM);
        }
    }

    /// After bootstrap exited by itself: proves that it stopped and reaped everything it
    /// started, without any help from the harness. Panics naming what is left.
    pub fn assert_nothing_left(&mut self) {
        assert!(
            self.try_status().is_some(),
            "assert_nothing_left: bootstrap is still running (call wait() first)"
        );
        let left = self.leftovers();
        if !left.is_empty() {
            let list = describe(&left);
            self.teardown();
            panic!("bootstrap exited but left processes behind:\n{list}");
        }
    }

    /// Processes of the system (in its group, or carrying its mark) once dead ones have had `ZOMBIE_GRACE` to be reaped.
    /// Living processes are returned at once (never waited for) — but for bootstrap's keeper,
    /// which outlives a SIGKILLed bootstrap by the moments it takes to kill what is left, in a
    /// process group of its own, and ends by itself: it gets the same grace.
    fn leftovers(&self) -> Vec<ProcStat> {
        let deadline = Instant::now() + ZOMBIE_GRACE;
        loop {
            reap_orphans_here();
            let mut left = procs::in_group(self.pgid);
            for p in procs::with_env(MARK_ENV, &self.mark) {
                if !left.iter().any(|q| q.pid == p.pid) {
                    left.push(p);
                }
            }
            let ending = |p: &ProcStat| p.is_zombie() || p.comm == KEEPER_COMM;
            if left.iter().any(|p| !ending(p)) || left.is_empty() || Instant::now() >= deadline {
                return left;
            }
            sleep(POLL);
        }
    }

    fn events_summary(&self) -> String {
        let lines: Vec<String> = self
            .events()
            .iter()
            .map(|e| e.to_line().trim_end().to_owned())
            .collect();
        tail(&lines.join("\n"), 40)
    }

    fn teardown_and_panic(&mut self, why: &str) -> ! {
        let stderr = tail(&self.stderr(), 40);
        self.teardown();
        panic!("{why}\n--- bootstrap stderr (tail) ---\n{stderr}");
    }

    /// SIGTERM bootstrap and give it `TERM_GRACE` to stop the system; if it exited (before or
    /// now), whatever is still alive in its group was left behind by it. Then SIGKILL the whole
    /// group, reap bootstrap, and kill anything still there. Returns what was left behind.
    fn teardown(&mut self) -> Vec<ProcStat> {
        if self.torn_down {
            return Vec::new();
        }
        self.torn_down = true;
        if self.try_status().is_none() {
            let _ = crate::kill_pid(self.pgid, libc::SIGTERM);
            let deadline = Instant::now() + TERM_GRACE;
            while self.try_status().is_none() && Instant::now() < deadline {
                sleep(POLL);
            }
        }
        let mut left = Vec::new();
        if self.status.is_some() {
            left.extend(self.leftovers().into_iter().filter(|p| !p.is_zombie()));
        } else {
            eprintln!(
                "s3res-testkit: bootstrap (pid {}) did not stop within {TERM_GRACE:?} of SIGTERM; \
                 killing its process group",
                self.pgid
            );
        }
        // The whole group, whether or not bootstrap went quietly: a well-behaved system has
        // nothing left and this is a no-op (ESRCH).
        killpg(self.pgid);
        if self.status.is_none() {
            self.status = Some(self.child.wait().expect("reaping bootstrap"));
        }
        unregister_bootstrap(self.pgid);
        // Everything was sent SIGKILL; give the kernel ZOMBIE_GRACE to finish them off. What
        // still lives after that escaped the group (the mark finds it): kill it by pid.
        let deadline = Instant::now() + ZOMBIE_GRACE;
        loop {
            let living: Vec<ProcStat> = self
                .leftovers()
                .into_iter()
                .filter(|p| !p.is_zombie())
                .collect();
            if living.is_empty() {
                break;
            }
            for p in &living {
                let _ = crate::kill_pid(p.pid, libc::SIGKILL);
            }
            if Instant::now() >= deadline {
                for p in living {
                    if !left.iter().any(|q| q.pid == p.pid) {
                        left.push(p);
                    }
                }
                break;
            }
            sleep(POLL);
        }
        left
    }
}

impl Drop for RunningSystem {
    fn drop(&mut self) {
        let panicking = std::thread::panicking();
        let left = self.teardown();
        if let Some(dir) = self.dir.take() {
            if std::env::var_os(KEEP_TMP_ENV).is_some() {
                let kept = dir.keep();
                eprintln!("s3res-testkit: kept {}", kept.display());
            } else if panicking {
                eprintln!("s3res-testkit: set {KEEP_TMP_ENV}=1 to keep the system's temp dir");
            }
        }
        if !left.is_empty() && !panicking {
            panic!(
                "left processes behind (bootstrap had exited; the harness killed them):\n{}",
                describe(&left)
            );
        }
    }
}

fn describe(procs: &[ProcStat]) -> String {
    procs
        .iter()
        .map(|p| format!("  {p}"))
        .collect::<Vec<_>>()
        .join("\n")
}

fn read_lossy(path: &Path) -> String {
    match std::fs::read(path) {
        Ok(b) => String::from_utf8_lossy(&b).into_owned(),
        Err(_) => String::new(),
    }
}

fn killpg(pgid: i32) {
    // A negative pid signals the whole process group.
    let _ = crate::kill_pid(-pgid, libc::SIGKILL);
}

/// The test process is a child subreaper, so a process whose parent died before reaping it
/// becomes our child instead of init's; we reap those dead orphans here (by pid, never with
/// `waitpid(-1)`, which could steal the status of a `std::process::Child`). Without this, a
/// zombie adopted by a container's init that never reaps would look like a leftover forever.
///
/// An adopted orphan is told from a child we spawned ourselves thus: it is not a registered
/// bootstrap (whose `Child` reaps it), and it is not in the test's own process group (where a
/// cargo build, or anything a test spawns directly, stays).
pub fn reap_orphans_here() {
    static SUBREAPER: Once = Once::new();
    SUBREAPER.call_once(|| {
        if let Err(e) = replica_rt::sys::set_child_subreaper() {
            eprintln!("s3res-testkit: cannot become a child subreaper: {e}");
        }
    });
    let me = std::process::id() as i32;
    let own_group = replica_rt::sys::process_group(me);
    let bootstraps = lock_bootstraps();
    for p in procs::all() {
        if p.ppid == me
            && p.is_zombie()
            && Some(p.pgrp) != own_group
            && !bootstraps.contains(&p.pid)
        {
            let _ = replica_rt::sys::reap(p.pid);
        }
    }
}

/// Bootstraps started and not yet reaped by their `Child`.
static BOOTSTRAPS: Mutex<Vec<i32>> = Mutex::new(Vec::new());

fn lock_bootstraps() -> MutexGuard<'static, Vec<i32>> {
    BOOTSTRAPS.lock().unwrap_or_else(|e| e.into_inner())
}

fn unregister_bootstrap(pid: i32) {
    lock_bootstraps().retain(|&p| p != pid);
}
