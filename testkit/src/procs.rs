//! What `/proc` says about processes: enough to find every process of a process group.

use std::fmt;

/// The fields of `/proc/PID/stat` the harness needs.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ProcStat {
    pub pid: i32,
    pub comm: String,
    /// `R`, `S`, `D`, `Z`, `T`, ...
    pub state: char,
    pub ppid: i32,
    pub pgrp: i32,
}

impl ProcStat {
    pub fn is_zombie(&self) -> bool {
        self.state == 'Z' || self.state == 'X'
    }
}

impl fmt::Display for ProcStat {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "pid {} ({}) state {} ppid {} pgrp {}",
            self.pid, self.comm, self.state, self.ppid, self.pgrp
        )
    }
}

/// Parses one `/proc/PID/stat` line. `comm` (field 2) may hold spaces and parentheses, so the
/// numeric fields are read after the *last* `)`: field 3 state, 4 ppid, 5 pgrp.
pub fn parse_stat(line: &str) -> Option<ProcStat> {
    let open = line.find('(')?;
    let close = line.rfind(')')?;
    if close < open {
        return None;
    }
    let pid = line[..open].trim().parse().ok()?;
    let comm = line[open + 1..close].to_owned();
    let mut rest = line[close + 1..].split_whitespace();
    let state = rest.next()?.chars().next()?;
    let ppid = rest.next()?.parse().ok()?;
    let pgrp = rest.next()?.parse().ok()?;
    Some(ProcStat {
        pid,
        comm,
        state,
        ppid,
        pgrp,
    })
}

/// What `/proc` says about `pid` now (`None`: gone).
pub fn stat(pid: i32) -> Option<ProcStat> {
    parse_stat(&std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?)
}

/// Every process visible in `/proc` right now (processes that vanish mid-scan are skipped).
pub fn all() -> Vec<ProcStat> {
    let Ok(dir) = std::fs::read_dir("/proc") else {
        return Vec::new();
    };
    dir.filter_map(|e| {
        let e = e.ok()?;
        let name = e.file_name();
        let pid: i32 = name.to_str()?.parse().ok()?;
        let text = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
        parse_stat(&text)
    })
    .collect()
}

/// The processes whose process group is `pgid`.
pub fn in_group(pgid: i32) -> Vec<ProcStat> {
    all().into_iter().filter(|p| p.pgrp == pgid).collect()
}

/// The processes whose environment holds `key=value` (as started: `/proc/PID/environ`). Finds
/// a process however it left its group or session, since descendants inherit the environment.
/// Zombies have no readable environment and are not found here.
pub fn with_env(key: &str, value: &str) -> Vec<ProcStat> {
    let needle = format!("{key}={value}");
    all()
        .into_iter()
        .filter(|p| {
            std::fs::read(format!("/proc/{}/environ", p.pid))
                .is_ok_and(|env| env.split(|&b| b == 0).any(|v| v == needle.as_bytes()))
        })
        .collect()
}

/// Kills (SIGKILL) every live process whose environment holds `key=value`, until none is left
/// (bounded: 50 rounds, 20 ms apart); returns what it found, for a test to fail on.
pub fn kill_with_env(key: &str, value: &str) -> Vec<String> {
    let mut found = Vec::new();
    for _ in 0..50 {
        let live: Vec<_> = with_env(key, value)
            .into_iter()
            .filter(|p| !p.is_zombie())
            .collect();
        if live.is_empty() {
            break;
        }
        for p in live {
            found.push(p.to_string());
            let _ = crate::kill_pid(p.pid, libc::SIGKILL);
        }
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    found
}

/// How a process is scheduled right now: policy, real-time priority, nice value, CPUs.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Scheduling {
    pub pid: i32,
    pub round_robin: bool,
    /// SCHED_RR/FIFO priority (0 for the normal policy).
    pub priority: i32,
    pub nice: i32,
    pub cpus: Vec<usize>,
}

impl fmt::Display for Scheduling {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let policy = if self.round_robin {
            "SCHED_RR"
        } else {
            "other"
        };
        write!(
            f,
            "pid {}: {policy} {} nice {} cpus {:?}",
            self.pid, self.priority, self.nice, self.cpus
        )
    }
}

/// `pid`'s scheduling (through sched_getscheduler, sched_getparam, getpriority and
/// sched_getaffinity); panics naming the pid if it is gone.
pub fn scheduling(pid: i32) -> Scheduling {
    use replica_rt::sys;
    let policy =
        sys::sched_policy(pid).unwrap_or_else(|e| panic!("sched_getscheduler({pid}): {e}"));
    Scheduling {
        pid,
        round_robin: policy.is_round_robin(),
        priority: policy.priority,
        nice: sys::nice_of(pid).unwrap_or_else(|e| panic!("getpriority({pid}): {e}")),
        cpus: sys::cpu_affinity(pid).unwrap_or_else(|e| panic!("sched_getaffinity({pid}): {e}")),
    }
}

/// Whether `pid` catches every signal replica-rt handles (restart, SDC and CFE injection): the
/// handlers `replica_rt::init` installs. Read from `SigCgt` in `/proc/PID/status`; a process
/// that is gone handles nothing.
pub fn handles_hooks(pid: i32) -> bool {
    use replica_rt::contract::signals;
    use replica_rt::sys::{caught_signals, signal_bit};
    caught_signals(pid).is_some_and(|mask| {
        [signals::RESTART, signals::INJECT_SDC, signals::inject_cfe()]
            .iter()
            .all(|&sig| mask & signal_bit(sig) != 0)
    })
}

/// I/O counters of a process (`/proc/PID/io`; root, or the same user).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Io {
    /// Bytes read by `read`-like calls (`rchar`): pipes included.
    pub rchar: u64,
    /// Bytes written by `write`-like calls (`wchar`).
    pub wchar: u64,
    /// `read`-like calls (`syscr`).
    pub syscr: u64,
    /// `write`-like calls (`syscw`).
    pub syscw: u64,
}

/// `pid`'s I/O counters; `None` if it is gone (or not ours to read).
pub fn io(pid: i32) -> Option<Io> {
    let text = std::fs::read_to_string(format!("/proc/{pid}/io")).ok()?;
    let field = |name: &str| {
        text.lines()
            .find_map(|l| l.strip_prefix(name)?.strip_prefix(':'))
            .and_then(|v| v.trim().parse().ok())
    };
    Some(Io {
        rchar: field("rchar")?,
        wchar: field("wchar")?,
        syscr: field("syscr")?,
        syscw: field("syscw")?,
    })
}

/// Voluntary context switches of `pid` (`voluntary_ctxt_switches` in `/proc/PID/status`: how
/// often it blocked); `None` if it is gone.
pub fn voluntary_switches(pid: i32) -> Option<u64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    status
        .lines()
        .find_map(|l| l.strip_prefix("voluntary_ctxt_switches:"))
        .and_then(|v| v.trim().parse().ok())
}

/// Memory `pid` has locked, KiB (`VmLck` in `/proc/PID/status`: non-zero once it has called
/// `mlockall`, which a fork child does again right after its `Hello`); `None` if it is gone.
pub fn locked_kib(pid: i32) -> Option<u64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmLck:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
}

/// Time `pid` has spent on a CPU, ns (the first field of `/proc/PID/schedstat`); `None` if it
/// is gone.
pub fn cpu_time_ns(pid: i32) -> Option<u64> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/schedstat")).ok()?;
    stat.split_whitespace().next()?.parse().ok()
}

/// Where in the kernel `pid` sleeps (`/proc/PID/wchan`, e.g. `pipe_read`, `anon_pipe_read`,
/// `do_sys_poll`); `None` if it is gone, `Some("0")` while it runs.
pub fn wchan(pid: i32) -> Option<String> {
    std::fs::read_to_string(format!("/proc/{pid}/wchan")).ok()
}

/// Whether `pid` sleeps waiting to read a pipe (its input): asleep, in the pipe's read.
pub fn waits_on_pipe_read(pid: i32) -> bool {
    replica_rt::sys::process_state(pid) == Some('S')
        && wchan(pid).is_some_and(|w| w.contains("pipe_read"))
}

/// The real uid and gid of `pid` (`Uid:`/`Gid:` in `/proc/PID/status`).
pub fn owner(pid: i32) -> Option<(u32, u32)> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let first = |key: &str| -> Option<u32> {
        let line = status.lines().find(|l| l.starts_with(key))?;
        line.split_whitespace().nth(1)?.parse().ok()
    };
    Some((first("Uid:")?, first("Gid:")?))
}

/// The soft limit on processes (`RLIMIT_NPROC`) of `pid`, from `/proc/PID/limits` (`None`:
/// unlimited).
pub fn nproc_soft(pid: i32) -> Option<u64> {
    let limits = std::fs::read_to_string(format!("/proc/{pid}/limits"))
        .unwrap_or_else(|e| panic!("reading the limits of {pid}: {e}"));
    let line = limits
        .lines()
        .find(|l| l.starts_with("Max processes"))
        .unwrap_or_else(|| panic!("no `Max processes` in /proc/{pid}/limits"));
    line["Max processes".len()..]
        .split_whitespace()
        .next()
        .and_then(|v| v.parse().ok())
}

/// Sets the soft limit on processes (`RLIMIT_NPROC`) of `pid` to `soft` (`None`: unlimited),
/// with util-linux `prlimit` run as the process's own user (through `setpriv` when the tests
/// run as root: changing another user's limits takes CAP_SYS_RESOURCE, which a container's
/// root may lack). Panics with prlimit's words if it fails.
pub fn set_nproc_soft(pid: i32, soft: Option<u64>) {
    let (uid, gid) = owner(pid).unwrap_or_else(|| panic!("process {pid} is gone"));
    let limit = format!(
        "--nproc={}:",
        soft.map_or("unlimited".into(), |n| n.to_string())
    );
    let me = std::fs::metadata("/proc/self").map(|m| std::os::unix::fs::MetadataExt::uid(&m));
    let mut cmd = if me.ok() == Some(uid) {
        std::process::Command::new("prlimit")
    } else {
        let mut cmd = std::process::Command::new("setpriv");
        cmd.arg(format!("--reuid={uid}"))
            .arg(format!("--regid={gid}"))
            .arg("--clear-groups")
            .arg("--")
            .arg("prlimit");
        cmd
    };
    let out = cmd
        .arg(format!("--pid={pid}"))
        .arg(limit)
        .output()
        .unwrap_or_else(|e| panic!("running prlimit (util-linux): {e}"));
    assert!(
        out.status.success(),
        "prlimit on {pid}: {}",
        String::from_utf8_lossy(&out.stderr).trim()
    );
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_plain_stat() {
        let s = "1234 (s3res-voter) S 1200 1200 1100 34816 1200 4194560 123 0 0 0 1 2 0 0 20 0 1 0";
        let p = parse_stat(s).unwrap();
        assert_eq!(
            p,
            ProcStat {
                pid: 1234,
                comm: "s3res-voter".into(),
                state: 'S',
                ppid: 1200,
                pgrp: 1200
            }
        );
        assert!(!p.is_zombie());
    }

    #[test]
    fn parses_comm_with_spaces_and_parens() {
        let s = "77 (a) b (c) Z 1 70 70 0 -1 4194560\n";
        let p = parse_stat(s).unwrap();
        assert_eq!(p.pid, 77);
        assert_eq!(p.comm, "a) b (c");
        assert_eq!(p.state, 'Z');
        assert_eq!(p.ppid, 1);
        assert_eq!(p.pgrp, 70);
        assert!(p.is_zombie());
    }

    #[test]
    fn rejects_garbage() {
        assert_eq!(parse_stat(""), None);
        assert_eq!(parse_stat("12 (x"), None);
        assert_eq!(parse_stat("12 (x) S"), None);
        assert_eq!(parse_stat("x (y) S 1 2"), None);
    }

    #[test]
    fn finds_a_child_by_its_environment() {
        let value = format!("env-test-{}", std::process::id());
        let mut child = std::process::Command::new("sleep")
            .arg("30")
            .env("S3RES_PROCS_TEST", &value)
            .spawn()
            .unwrap();
        // Until the child has exec'd, its environ is still ours: look again for a while.
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(5);
        let mut found = with_env("S3RES_PROCS_TEST", &value);
        while found.is_empty() && std::time::Instant::now() < deadline {
            std::thread::sleep(std::time::Duration::from_millis(5));
            found = with_env("S3RES_PROCS_TEST", &value);
        }
        child.kill().unwrap();
        child.wait().unwrap();
        assert_eq!(found.len(), 1, "{found:?}");
        assert_eq!(found[0].pid, child.id() as i32);
    }

    #[test]
    fn reads_io_counters_and_a_pipe_reader() {
        use std::io::Write;
        let mut cat = std::process::Command::new("cat")
            .stdin(std::process::Stdio::piped())
            .stdout(std::process::Stdio::null())
            .spawn()
            .unwrap();
        let pid = cat.id() as i32;
        crate::wait::wait_until(
            "cat to wait on its stdin",
            std::time::Duration::from_secs(10),
            || waits_on_pipe_read(pid).then_some(()),
        );
        let before = io(pid).expect("cat's /proc/PID/io");
        cat.stdin.as_mut().unwrap().write_all(b"12345").unwrap();
        let after = crate::wait::wait_until(
            "cat to read 5 bytes",
            std::time::Duration::from_secs(10),
            || io(pid).filter(|a| a.rchar >= before.rchar + 5),
        );
        assert!(after.syscr > before.syscr);
        drop(cat.stdin.take());
        cat.wait().unwrap();
    }

    #[test]
    fn finds_own_process() {
        let me = std::process::id() as i32;
        let mine = all()
            .into_iter()
            .find(|p| p.pid == me)
            .expect("own /proc entry");
        assert_eq!(Some(mine.pgrp), replica_rt::sys::process_group(me));
    }
}
