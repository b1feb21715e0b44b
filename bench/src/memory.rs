//! `s3res-bench memory`: resident memory of an idle voter and of replica-rt components beyond
//! their own state, read from `/proc/PID/status` and `/proc/PID/smaps_rollup` after warm-up
//! rounds.
//!
//! Allocations per round are not measured here but checked by the test
//! `bench/tests/allocations.rs` (a counting allocator around an in-process voter).

use std::time::Duration;

use anyhow::{Context, Result};
use serde::Serialize;

use crate::report;
use crate::system::{Spec, System};
use crate::Common;

const ROUNDS: u64 = 1000;
const ROUND_LIMIT: Duration = Duration::from_secs(30);

/// One process's memory. The timing keys of the other benches are present and null, so every
/// line has the same keys.
#[derive(Debug, Clone, Serialize)]
pub struct MemRow {
    pub bench: &'static str,
    /// `voter`, `replica`, or `direct` (the component without a voter).
    pub what: String,
    pub component: String,
    pub replicas: usize,
    /// The component's own state (ballast bytes; 0 for echo).
    pub size: u64,
    pub count: u64,
    pub median_us: Option<f64>,
    pub p99_us: Option<f64>,
    pub max_us: Option<f64>,
    pub rss_kib: u64,
    pub hwm_kib: u64,
    pub pss_kib: u64,
    /// Private_Clean + Private_Dirty: memory no other process shares.
    pub private_kib: u64,
    /// `rss_kib` − the state, for components.
    pub beyond_state_kib: Option<i64>,
    /// `static` for a statically linked component (`--component-dir`; see `report::Row`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub linking: Option<&'static str>,
}

pub fn run(common: &Common, sizes: &[u64]) -> Result<Vec<MemRow>> {
    let voter = common.bins.path("s3res-voter")?;
    let echo = common.bins.component("s3res-echo")?;
    let ballast = common.bins.component("s3res-ballast")?;
    let mut rows = Vec::new();
    let base = |exec: &std::path::Path, args: Vec<String>, replicas| Spec {
        journal: common.journal,
        lock_memory: common.lock_memory,
        cpu_idle: common.cpu_idle,
        spin_us: common.spin_us,
        exec: exec.to_path_buf(),
        args,
        replicas,
        timeout_us: 1_000_000,
        max_frame: replica_rt::frame::DEFAULT_MAX_FRAME,
        voter: Some(voter.clone()),
        setup: crate::system::Setup::Plain,
        preload: None,
    };
    let mut configs = vec![
        ("s3res-echo".to_string(), base(&echo, Vec::new(), 0), 0u64),
        ("s3res-echo".to_string(), base(&echo, Vec::new(), 3), 0),
    ];
    for &s in sizes {
        let args = vec!["--kib".to_string(), (s / 1024).to_string()];
        let name = format!("s3res-ballast --kib {}", s / 1024);
        configs.push((name.clone(), base(&ballast, args.clone(), 0), s));
        configs.push((name, base(&ballast, args, 3), s));
    }
    let bar = common.progress(configs.len() as u64, "memory");
    for (name, spec, state) in configs {
        bar.set_message(name.clone());
        let mut system = System::start(&spec)?;
        let mut frame = [0u8; 64];
        for seq in 0..ROUNDS {
            crate::echo::fill_frame(seq, &mut frame);
            system
                .exchange(&frame, ROUND_LIMIT)
                .with_context(|| format!("{name}: round {seq}"))?;
        }
        // Idle: let the last round close everywhere.
        std::thread::sleep(Duration::from_millis(100));
        let mut measure = |what: &str, pid: i32, state: u64| -> Result<()> {
            let m = read_memory(pid).with_context(|| format!("reading memory of pid {pid}"))?;
            rows.push(MemRow {
                bench: "memory",
                what: what.into(),
                component: name.clone(),
                replicas: spec.replicas,
                size: state,
                count: 1,
                median_us: None,
                p99_us: None,
                max_us: None,
                rss_kib: m.rss_kib,
                hwm_kib: m.hwm_kib,
                pss_kib: m.pss_kib,
                private_kib: m.private_kib,
                beyond_state_kib: (what != "voter")
                    .then(|| m.rss_kib as i64 - (state / 1024) as i64),
                linking: common.linking.filter(|_| what != "voter"),
            });
            Ok(())
        };
        if spec.replicas == 0 {
            measure("direct", system.top_pid, state)?;
        } else {
            measure("voter", system.top_pid, 0)?;
            measure("replica", system.replicas[0], state)?;
        }
        drop(system);
        bar.inc(1);
    }
    bar.finish_and_clear();
    Ok(rows)
}

#[derive(Debug, Default, Clone, Copy)]
struct Memory {
    rss_kib: u64,
    hwm_kib: u64,
    pss_kib: u64,
    private_kib: u64,
}

fn read_memory(pid: i32) -> Result<Memory> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status"))?;
    let rollup = std::fs::read_to_string(format!("/proc/{pid}/smaps_rollup"))?;
    Ok(Memory {
        rss_kib: field_kib(&status, "VmRSS:"),
        hwm_kib: field_kib(&status, "VmHWM:"),
        pss_kib: field_kib(&rollup, "Pss:"),
        private_kib: field_kib(&rollup, "Private_Clean:") + field_kib(&rollup, "Private_Dirty:"),
    })
}

/// The number after `key` on its line (`VmRSS:   1234 kB`), 0 if absent.
fn field_kib(text: &str, key: &str) -> u64 {
    text.lines()
        .find_map(|l| l.strip_prefix(key))
        .and_then(|rest| rest.split_whitespace().next())
        .and_then(|n| n.parse().ok())
        .unwrap_or(0)
}

pub fn emit(rows: &[MemRow], json: bool) {
    if json {
        for r in rows {
            println!(
                "{}",
                serde_json::to_string(r).expect("a row always serializes")
            );
        }
        return;
    }
    let cells: Vec<Vec<String>> = rows
        .iter()
        .map(|r| {
            vec![
                match r.linking {
                    Some(how) => format!("{} ({how})", r.component),
                    None => r.component.clone(),
                },
                report::level_name(r.replicas),
                r.what.clone(),
                r.rss_kib.to_string(),
                r.pss_kib.to_string(),
                r.private_kib.to_string(),
                r.beyond_state_kib
                    .map(|b| b.to_string())
                    .unwrap_or_default(),
            ]
        })
        .collect();
    print!(
        "{}",
        report::table(
            &[
                "component",
                "level",
                "process",
                "RSS KiB",
                "PSS KiB",
                "private KiB",
                "RSS − state KiB",
            ],
            &cells,
        )
    );
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_kib_fields() {
        let t = "Name:\tx\nVmHWM:\t    2048 kB\nVmRSS:\t    1024 kB\n";
        assert_eq!(field_kib(t, "VmRSS:"), 1024);
        assert_eq!(field_kib(t, "VmHWM:"), 2048);
        assert_eq!(field_kib(t, "Pss:"), 0);
    }

    #[test]
    fn reads_this_process() {
        let m = read_memory(std::process::id() as i32).unwrap();
        assert!(m.rss_kib > 0 && m.pss_kib > 0, "{m:?}");
    }
}
