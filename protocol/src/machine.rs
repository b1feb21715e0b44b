//! What machine a measurement ran on: CPU model, cores, kernel, load, and the build that ran;
//! and how its CPUs spent their time (`/proc/stat`: [`CpuTimes`]).
//!
//! Campaigns and benchmarks record it next to their results, because false positives and
//! latencies track the machine's speed and load. Everything is read from `/proc` (and `git`
//! for the commit); what cannot be read is left empty rather than failing the measurement.

use std::path::Path;
use std::process::{Command, Stdio};

use serde::{Deserialize, Serialize};

/// The machine, as far as `/proc` tells.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Machine {
    /// `model name` (x86) or `Model`/`CPU part` (Arm) of the first CPU in `/proc/cpuinfo`.
    #[serde(default)]
    pub cpu_model: String,
    /// Online CPUs (`/proc/cpuinfo` processors).
    #[serde(default)]
    pub cores: usize,
    /// CPUs this process may run on (its affinity mask).
    #[serde(default)]
    pub usable_cores: usize,
    /// `/proc/sys/kernel/osrelease`.
    #[serde(default)]
    pub kernel: String,
    /// `/proc/loadavg` when probed.
    #[serde(default)]
    pub load: Option<LoadAverage>,
}

/// The 1-, 5- and 15-minute load averages.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LoadAverage {
    pub one: f64,
    pub five: f64,
    pub fifteen: f64,
}

/// How the measuring binaries were built.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Build {
    /// `release` or `debug`: the cargo profile folder the executable sits in (`target/release/…`),
    /// else how the caller itself was compiled.
    pub profile: String,
    /// `git rev-parse HEAD` of the checkout holding the executable, if it is in one.
    #[serde(default)]
    pub commit: Option<String>,
    /// The checkout had uncommitted changes to tracked files.
    #[serde(default)]
    pub dirty: bool,
}

impl Machine {
    /// Reads the machine's description now.
    pub fn probe() -> Machine {
        let cpuinfo = std::fs::read_to_string("/proc/cpuinfo").unwrap_or_default();
        let cores = cpuinfo
            .lines()
            .filter(|l| l.starts_with("processor"))
            .count();
        Machine {
            cpu_model: cpu_model(&cpuinfo),
            cores,
            usable_cores: std::thread::available_parallelism().map_or(0, |n| n.get()),
            kernel: std::fs::read_to_string("/proc/sys/kernel/osrelease")
                .map(|s| s.trim().to_owned())
                .unwrap_or_default(),
            load: LoadAverage::now(),
        }
    }

    /// One line for a figure's subtitle or a log: `Intel Xeon …, 2 cores, Linux 6.1, load 0.52`.
    pub fn one_line(&self) -> String {
        let mut s = if self.cpu_model.is_empty() {
            "unknown CPU".to_owned()
        } else {
            self.cpu_model.clone()
        };
        s.push_str(&format!(", {} cores", self.cores));
        if !self.kernel.is_empty() {
            s.push_str(&format!(", Linux {}", self.kernel));
        }
        if let Some(l) = self.load {
            s.push_str(&format!(", load {:.2}", l.one));
        }
        s
    }
}

impl LoadAverage {
    /// `/proc/loadavg`, or `None` if it cannot be read.
    pub fn now() -> Option<LoadAverage> {
        parse_loadavg(&std::fs::read_to_string("/proc/loadavg").ok()?)
    }
}

impl Build {
    /// The build of `exe` (a path to one of the workspace's executables).
    pub fn of(exe: &Path) -> Build {
        let from_path = exe
            .parent()
            .and_then(Path::file_name)
            .and_then(|n| n.to_str())
            .filter(|n| matches!(*n, "release" | "debug"))
            .map(str::to_owned);
        let own = if cfg!(debug_assertions) {
            "debug"
        } else {
            "release"
        };
        let dir = exe.parent().unwrap_or(Path::new("."));
        let commit = git(dir, &["rev-parse", "HEAD"]);
        let dirty = commit.is_some()
            && git(dir, &["status", "--porcelain", "--untracked-files=no"])
                .is_some_and(|s| !s.is_empty());
        Build {
            profile: from_path.unwrap_or_else(|| own.to_owned()),
            commit,
            dirty,
        }
    }
}

/// Runs `git -C dir args…`; its trimmed stdout on success.
fn git(dir: &Path, args: &[&str]) -> Option<String> {
    let out = Command::new("git")
        .arg("-C")
        .arg(dir)
        .args(args)
        .stdin(Stdio::null())
        .stderr(Stdio::null())
        .output()
        .ok()?;
    if !out.status.success() {
        return None;
    }
    Some(String::from_utf8_lossy(&out.stdout).trim().to_owned())
}

/// Which line of `/proc/stat`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Cpus {
    /// The whole machine's (`cpu`, every CPU's times summed).
    All,
    /// One CPU's (`cpuN`).
    One(usize),
}

/// A CPU's times from `/proc/stat`, in clock ticks since boot (`USER_HZ`, [`ticks_per_second`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct CpuTimes {
    /// Every state but idle and iowait: user, nice, system, irq, softirq, steal.
    pub busy: u64,
    /// All eight states.
    pub total: u64,
    /// Time the hypervisor ran something else while this guest's CPU had work (`steal`): a
    /// guest cannot see it as anything but a stall of everything on that CPU. 0 on bare metal.
    pub steal: u64,
}

impl CpuTimes {
    /// The times of `cpus` in the text of `/proc/stat` (its lines `cpu[N] user nice system
    /// idle iowait irq softirq steal ...`); `None` if that line is missing or cut short.
    pub fn parse(text: &str, cpus: Cpus) -> Option<CpuTimes> {
        let line = text.lines().find(|l| {
            let Some((name, _)) = l.split_once(' ') else {
                return false;
            };
            match (name.strip_prefix("cpu"), cpus) {
                (Some(""), Cpus::All) => true,
                (Some(n), Cpus::One(cpu)) => n.parse() == Ok(cpu),
                _ => false,
            }
        })?;
        let mut fields = line.split_ascii_whitespace().skip(1);
        let mut ticks = [0u64; 8];
        for t in &mut ticks {
            *t = fields.next()?.parse().ok()?;
        }
        let [user, nice, system, idle, iowait, irq, softirq, steal] = ticks;
        let busy = user + nice + system + irq + softirq + steal;
        Some(CpuTimes {
            busy,
            total: busy + idle + iowait,
            steal,
        })
    }

    /// The times of `cpus` now; `None` where `/proc/stat` cannot be read or lacks the line.
    pub fn now(cpus: Cpus) -> Option<CpuTimes> {
        CpuTimes::parse(&std::fs::read_to_string("/proc/stat").ok()?, cpus)
    }
}

/// Clock ticks a second in `/proc/stat` (`USER_HZ`: 100 on Linux, whatever the kernel's own
/// tick; asked of `sysconf`).
pub fn ticks_per_second() -> u64 {
    nix::unistd::sysconf(nix::unistd::SysconfVar::CLK_TCK)
        .ok()
        .flatten()
        .and_then(|t| u64::try_from(t).ok())
        .filter(|&t| t > 0)
        .unwrap_or(100)
}

/// Milliseconds in `ticks` of `/proc/stat`.
pub fn ticks_to_ms(ticks: u64) -> u64 {
    ticks * 1000 / ticks_per_second()
}

/// Whether this machine is a virtual machine, as far as the CPU says: x86's `hypervisor` flag
/// in `/proc/cpuinfo` (set by every common hypervisor; absent on bare metal and, as nothing
/// says so, on Arm).
pub fn is_virtual() -> bool {
    use std::io::Read;
    // The first CPU's entry says it (its flags line lies within its first 2 KiB or so). The
    // kernel makes each CPU's entry as it is read, so reading no further keeps this as cheap
    // on a machine of a hundred CPUs as on two.
    let mut first = [0u8; 8192];
    let n = std::fs::File::open("/proc/cpuinfo")
        .and_then(|mut f| f.read(&mut first))
        .unwrap_or(0);
    hypervisor_flag(&String::from_utf8_lossy(&first[..n]))
}

fn hypervisor_flag(cpuinfo: &str) -> bool {
    cpuinfo.lines().any(|l| {
        l.split_once(':').is_some_and(|(k, v)| {
            k.trim() == "flags" && v.split_ascii_whitespace().any(|f| f == "hypervisor")
        })
    })
}

fn cpu_model(cpuinfo: &str) -> String {
    let field = |name: &str| {
        cpuinfo.lines().find_map(|l| {
            let (k, v) = l.split_once(':')?;
            (k.trim() == name).then(|| v.trim().to_owned())
        })
    };
    field("model name")
        .or_else(|| field("Model"))
        .or_else(|| field("CPU part").map(|p| format!("CPU part {p}")))
        .unwrap_or_default()
}

fn parse_loadavg(text: &str) -> Option<LoadAverage> {
    let mut it = text.split_whitespace().map(str::parse::<f64>);
    Some(LoadAverage {
        one: it.next()?.ok()?,
        five: it.next()?.ok()?,
        fifteen: it.next()?.ok()?,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn loadavg_parses() {
        let l = parse_loadavg("0.52 1.03 2.50 2/345 6789\n").unwrap();
        assert_eq!((l.one, l.five, l.fifteen), (0.52, 1.03, 2.5));
        assert!(parse_loadavg("").is_none());
        assert!(parse_loadavg("x y z").is_none());
    }

    #[test]
    fn a_virtual_machine_is_told_by_its_cpu_flags() {
        let vm = "processor\t: 0\nflags\t\t: fpu vme sse2 hypervisor lahf_lm\n";
        assert!(hypervisor_flag(vm));
        let metal = "processor\t: 0\nflags\t\t: fpu vme sse2 lahf_lm\n";
        assert!(!hypervisor_flag(metal));
        // Only the flags line counts, and only the whole word.
        assert!(!hypervisor_flag(
            "model name\t: hypervisor\nflags\t: nohypervisor\n"
        ));
        assert!(!hypervisor_flag(""));
    }

    #[test]
    fn cpu_model_from_x86_and_arm() {
        let x86 = "processor\t: 0\nmodel name\t: AMD EPYC 7B13\nflags\t: fpu\n";
        assert_eq!(cpu_model(x86), "AMD EPYC 7B13");
        let arm = "processor\t: 0\nCPU part\t: 0xd0c\n";
        assert_eq!(cpu_model(arm), "CPU part 0xd0c");
        assert_eq!(cpu_model(""), "");
    }

    #[test]
    fn profile_from_the_target_folder() {
        let b = Build::of(Path::new("/nonexistent/target/release/s3res-bootstrap"));
        assert_eq!(b.profile, "release");
        assert_eq!(b.commit, None);
        let b = Build::of(Path::new("/nonexistent/target/debug/s3res-bootstrap"));
        assert_eq!(b.profile, "debug");
    }

    const STAT: &str = "cpu  2603313 12228 770679 6015948 41130 0 5062 139200 0 0
cpu0 1204561 6115 372188 3126789 11115 0 917 68323 0 0
cpu1 1398752 6112 398491 2889158 30014 0 4145 70876 0 0
cpu10 1 2 3 4 5 6 7 8 0 0
intr 123 4 5
ctxt 99
";

    #[test]
    fn a_cpus_times_are_found_and_counted() {
        assert_eq!(
            CpuTimes::parse(STAT, Cpus::One(1)),
            Some(CpuTimes {
                busy: 1398752 + 6112 + 398491 + 4145 + 70876,
                total: 1398752 + 6112 + 398491 + 2889158 + 30014 + 4145 + 70876,
                steal: 70876,
            })
        );
        // `cpu1` is not `cpu10`, nor the machine's `cpu` line.
        assert_eq!(
            CpuTimes::parse(STAT, Cpus::One(10)),
            Some(CpuTimes {
                busy: 1 + 2 + 3 + 6 + 7 + 8,
                total: 36,
                steal: 8,
            })
        );
        assert_eq!(
            CpuTimes::parse(STAT, Cpus::All).map(|t| t.steal),
            Some(139200)
        );
        assert_eq!(CpuTimes::parse(STAT, Cpus::One(2)), None);
        assert_eq!(
            CpuTimes::parse("cpu0 1 2\n", Cpus::One(0)),
            None,
            "a cut line"
        );
        assert_eq!(CpuTimes::parse("intr 1 2 3 4 5 6 7 8\n", Cpus::All), None);
    }

    #[test]
    fn this_machines_cpu_times_are_read() {
        let all = CpuTimes::now(Cpus::All).expect("/proc/stat has a cpu line");
        let first = CpuTimes::now(Cpus::One(0)).expect("/proc/stat has a cpu0 line");
        assert!(
            all.total >= first.total && first.total > 0,
            "{all:?} {first:?}"
        );
        assert_eq!(ticks_to_ms(38), 380);
    }

    #[test]
    fn this_machine_probes() {
        let m = Machine::probe();
        assert!(m.cores >= 1 && m.usable_cores >= 1, "{m:?}");
        assert!(!m.one_line().is_empty());
    }
}
