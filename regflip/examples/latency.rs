//! Register-injection latency: how long a thread is held (PTRACE_INTERRUPT → detach) per flip.
//!
//! ```text
//! cargo run --release -p s3res-regflip --example latency -- [INJECTIONS] [SEED]
//! ```
//!
//! Starts a copy of itself that spins on integer and floating-point work, and injects
//! INJECTIONS (default 2000) single-bit flips into any register operand (source or
//! destination, GPR or XMM) at random instants 0–2 ms apart. A target that a flip crashed is
//! restarted. Prints median, p90, p99 and max of the pause per successful injection. This is a
//! measurement, not a test: nothing here passes or fails on speed.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use s3res_regflip::{inject, OperandRole, RegFlipError, RegFlipSpec};
use std::collections::BTreeMap;
use std::hint::black_box;
use std::process::{Child, Command};
use std::time::Duration;

fn spin() -> ! {
    let mut x: u64 = 0x9e37_79b9_7f4a_7c15;
    let mut f: f64 = 1.0;
    loop {
        for i in 0..1000u64 {
            x = black_box(x.rotate_left(5) ^ i).wrapping_mul(0x5851_f42d_4c95_7f2d);
            f = black_box(f * 1.000_001 + (x & 0xff) as f64 * 1e-9);
        }
        if f > 1e300 {
            f = 1.0;
        }
        black_box((x, f));
    }
}

/// The spinning child; killed and reaped on drop unless `inject` reaped it already.
struct Target {
    child: Child,
    reaped: bool,
}

impl Target {
    fn start() -> anyhow::Result<Target> {
        let exe = std::env::current_exe()?;
        let child = Command::new(exe).arg("--spin").spawn()?;
        // Let it get past the dynamic loader into its loop (flipping the loader's registers
        // measures the same pause but restarts the target more often).
        std::thread::sleep(Duration::from_millis(20));
        Ok(Target {
            child,
            reaped: false,
        })
    }

    fn alive(&mut self) -> bool {
        !self.reaped && matches!(self.child.try_wait(), Ok(None))
    }
}

impl Drop for Target {
    fn drop(&mut self) {
        if !self.reaped {
            let _ = self.child.kill();
            let _ = self.child.wait();
        }
    }
}

fn percentile(sorted: &[u64], p: f64) -> u64 {
    let idx = ((sorted.len() as f64 - 1.0) * p).round() as usize;
    sorted[idx]
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.first().map(String::as_str) == Some("--spin") {
        spin();
    }
    let injections: usize = args.first().map(|s| s.parse()).transpose()?.unwrap_or(2000);
    let seed: u64 = args.get(1).map(|s| s.parse()).transpose()?.unwrap_or(42);
    println!("seed {seed}, {injections} injections");
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let spec = RegFlipSpec {
        role: OperandRole::Any,
        bits: 1,
        ..Default::default()
    };

    let mut target = Target::start()?;
    let mut pauses = Vec::with_capacity(injections);
    let mut stops = Vec::with_capacity(injections);
    let mut steps = Vec::with_capacity(injections);
    let mut roles: BTreeMap<String, usize> = BTreeMap::new();
    let mut errors: BTreeMap<String, usize> = BTreeMap::new();
    let mut restarts = 0;
    while pauses.len() < injections {
        // The caller chooses the instant: a random delay, then inject.
        std::thread::sleep(Duration::from_micros(rng.gen_range(0..2000)));
        if !target.alive() {
            restarts += 1;
            target = Target::start()?;
            continue;
        }
        match inject(target.child.id() as i32, &spec, &mut rng) {
            Ok(rec) => {
                pauses.push(rec.pause_ns);
                stops.push(rec.stop_ns);
                steps.push(rec.steps);
                let kind = if rec.register.starts_with("xmm") {
                    "xmm"
                } else {
                    "gpr"
                };
                *roles.entry(format!("{kind} {}", rec.role)).or_default() += 1;
            }
            Err(e) => {
                let kind = match e {
                    RegFlipError::Gone { .. } => {
                        // Reap it here unless `inject` already did (then try_wait fails).
                        let _ = target.child.try_wait();
                        target.reaped = true;
                        "target gone"
                    }
                    RegFlipError::InSyscall { .. } => "in a system call",
                    RegFlipError::NoCandidate { .. } => "no candidate",
                    RegFlipError::InstructionFaulted { .. } => "instruction faulted",
                    _ => return Err(e.into()),
                };
                *errors.entry(kind.into()).or_default() += 1;
            }
        }
    }
    pauses.sort_unstable();
    let us = |ns: u64| ns as f64 / 1000.0;
    println!(
        "pause (interrupt -> detach) over {} injections: median {:.1} us, p90 {:.1} us, \
         p99 {:.1} us, max {:.1} us",
        pauses.len(),
        us(percentile(&pauses, 0.5)),
        us(percentile(&pauses, 0.9)),
        us(percentile(&pauses, 0.99)),
        us(*pauses.last().unwrap()),
    );
    stops.sort_unstable();
    println!(
        "  of which interrupt -> stopped: median {:.1} us, p90 {:.1} us, p99 {:.1} us, max {:.1} us",
        us(percentile(&stops, 0.5)),
        us(percentile(&stops, 0.9)),
        us(percentile(&stops, 0.99)),
        us(*stops.last().unwrap()),
    );
    let stepped = steps.iter().filter(|&&s| s > 0).count();
    println!("operands hit: {roles:?}; injections that single-stepped to find one: {stepped}");
    println!("attempts without injection: {errors:?}; targets restarted after a crash: {restarts}");
    Ok(())
}
