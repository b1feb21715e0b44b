//! A measurement, not a check: restart time and round trip of the C running mean against the
//! Rust one, both under TMR in the same system shape (FIFO → `cat` feeder → component →
//! bootstrap's stdout file), the same voter, the same profile. A test target without the test
//! harness and with `test = false` (Cargo.toml), so that `cargo test` leaves it out unless it
//! is named:
//!
//! ```sh
//! cargo test --release -p s3res-replica-c --test c_vs_rust
//! ```
//!
//! - **restart** = the `recovery` event's `ts_ns` − the `crash` event's `ts_ns` after a SIGKILL
//!   of an idle replica: the voter's detection to the replacement's `Ready` (as `s3res-bench
//!   restart` defines it); `recovery_us` is the voter's own figure for the same span.
//! - **round trip** = writing one sample into the FIFO → its answer in bootstrap's stdout file
//!   (polled): it includes the feeder's hop and the polling, the same for both components.

mod common;

use std::io::Write;
use std::path::Path;
use std::time::{Duration, Instant};

use s3res_testkit::{EventKind, Rng, System};

/// The same name for both, so the systems differ only in `exec`.
const COMPONENT: &str = "running-mean";
const KILLS: usize = 30;
const ROUND_TRIPS: usize = 500;

struct Figures {
    restart_us: Vec<u64>,
    recovery_us: Vec<u64>,
    round_trip_us: Vec<u64>,
}

fn percentile(sorted: &[u64], p: f64) -> u64 {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

fn line(what: &str, v: &mut [u64]) -> String {
    v.sort_unstable();
    format!(
        "{what:<28} n={:<4} median {:>7} µs  p90 {:>7} µs  max {:>7} µs",
        v.len(),
        percentile(v, 0.5),
        percentile(v, 0.9),
        v[v.len() - 1]
    )
}

fn measure(exe: &Path) -> Figures {
    let sys = System::new();
    let stdout = sys.path("stdout.txt");
    let (mut run, mut writer) = common::start_fed_system(sys, COMPONENT, exe, 500_000);
    let sample = 8u32
        .to_le_bytes()
        .into_iter()
        .chain(1.5f64.to_le_bytes())
        .collect::<Vec<u8>>();
    let mut answered = 0u64;
    let mut one_round = |writer: &mut std::fs::File| -> u64 {
        let t0 = Instant::now();
        writer.write_all(&sample).unwrap();
        answered += 1;
        while std::fs::metadata(&stdout).map_or(0, |m| m.len()) < answered * 20 {
            assert!(t0.elapsed() < Duration::from_secs(30), "no answer");
            std::thread::yield_now();
        }
        t0.elapsed().as_micros() as u64
    };
    for _ in 0..50 {
        one_round(&mut writer);
    }
    let round_trip_us: Vec<u64> = (0..ROUND_TRIPS).map(|_| one_round(&mut writer)).collect();

    let mut restart_us = Vec::new();
    let mut recovery_us = Vec::new();
    let mut rng = Rng::from_env();
    for _ in 0..KILLS {
        let slot = rng.below(3) as usize;
        let pid = run.replica_pids(COMPONENT)[&slot];
        s3res_testkit::kill_pid(pid, libc::SIGKILL).unwrap();
        let crash = run.wait_for_event(
            |e| e.kind == EventKind::Crash && e.pid == Some(pid),
            Duration::from_secs(30),
        );
        let rec = run.wait_for_recovery(COMPONENT, slot, pid);
        restart_us.push((rec.ts_ns - crash.ts_ns) / 1000);
        recovery_us.push(rec.recovery_us.unwrap_or(0));
        // Two rounds with the new replica before the next kill.
        one_round(&mut writer);
        one_round(&mut writer);
        std::thread::sleep(Duration::from_millis(20));
    }
    drop(writer);
    let out = run.wait(Duration::from_secs(120));
    assert!(
        out.status.success(),
        "{}",
        s3res_testkit::tail(&out.stderr, 20)
    );
    run.assert_nothing_left();
    Figures {
        restart_us,
        recovery_us,
        round_trip_us,
    }
}

/// Restart and round trip of the C and the Rust running mean.
fn main() {
    common::require_compiler("cc");
    let rust = s3res_testkit::bin_path("s3res-running-mean");
    let dir = tempfile::tempdir().unwrap();
    let c = dir.path().join("s3res-c-running-mean");
    common::compile(
        "cc",
        &[common::repo_root().join("examples/c-running-mean/running_mean.c")],
        &c,
        common::Link::Static,
        &["-std=c11"],
    );
    // Alternating, twice each, so that neither profits from going second on a shared machine.
    let mut figures = Vec::new();
    for pass in 1..=2 {
        for (name, exe) in [("C", &c), ("Rust", &rust)] {
            figures.push((
                format!("{name} running mean, TMR, pass {pass}"),
                measure(exe),
            ));
        }
    }
    println!(
        "machine: {}",
        replica_rt::machine::Machine::probe().one_line()
    );
    for (name, f) in &mut figures {
        println!("{name}:");
        println!(
            "  {}",
            line("restart (crash→recovery ts)", &mut f.restart_us)
        );
        println!("  {}", line("recovery_us (voter)", &mut f.recovery_us));
        println!(
            "  {}",
            line("round trip (FIFO→stdout)", &mut f.round_trip_us)
        );
    }
}
