//! Missions in one process with seeded late plans, to find the delay sequences that strand the
//! robot (its own control logic, without any s3res process):
//!
//!     cargo run --release -p s3res-robot --example delay_sweep -- MAZE RUNS DELAY [BURSTS]
//!
//! flies the 8 × 8 maze of seed MAZE RUNS times (time limit 240 s, as the campaign robot), plans
//! reaching the navigator up to DELAY periods late (delay seed 7919·run + 1), and with BURSTS per
//! mille of periods starting a burst of up to 10 late commands; prints every failed mission and
//! the count.

use s3res_robot::mission::{run_in_process, Controllers};
use s3res_robot::sim::SimConfig;

fn main() {
    let args: Result<Vec<u64>, _> = std::env::args().skip(1).map(|a| a.parse()).collect();
    let (maze, runs, delay, bursts) = match args.as_deref() {
        Ok([m, r, d]) => (*m, *r, *d, 0),
        Ok([m, r, d, b]) => (*m, *r, *d, *b),
        _ => {
            eprintln!(
                "usage: delay_sweep MAZE RUNS DELAY [BURSTS] (whole numbers; see the source)"
            );
            std::process::exit(2);
        }
    };
    let mut failed = 0;
    let mut times = Vec::new();
    let mut replans = Vec::new();
    for run in 0..runs {
        let mut cfg = SimConfig::new(maze);
        cfg.time_limit_s = 240.0;
        let ctl = Controllers {
            plan_delay_max: delay.try_into().unwrap_or(u32::MAX),
            plan_delay_seed: run * 7919 + 1,
            burst_per_mille: bursts.try_into().unwrap_or(u32::MAX),
            burst_max: 10,
            ..Controllers::default()
        };
        let s = run_in_process(cfg, ctl);
        times.push(s.mission_time_s);
        replans.push(s.replans);
        if !s.success {
            failed += 1;
            println!("run {run}: {}", s.line());
        }
    }
    times.sort_by(f64::total_cmp);
    replans.sort_unstable();
    let median = |n: usize| n / 2;
    println!(
        "maze {maze}, plans up to {delay} periods late, bursts {bursts}‰: {failed} of {runs} missions failed; \
         mission time median {:.1} s, max {:.1} s; replans median {}, max {}",
        times.get(median(times.len())).copied().unwrap_or(0.0),
        times.last().copied().unwrap_or(0.0),
        replans.get(median(replans.len())).copied().unwrap_or(0),
        replans.last().copied().unwrap_or(0),
    );
}
