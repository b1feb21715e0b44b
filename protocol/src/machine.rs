//! What machine a measurement ran on: CPU model, cores, kernel, load, and the build that ran.
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

    #[test]
    fn this_machine_probes() {
        let m = Machine::probe();
        assert!(m.cores >= 1 && m.usable_cores >= 1, "{m:?}");
        assert!(!m.one_line().is_empty());
    }
}
