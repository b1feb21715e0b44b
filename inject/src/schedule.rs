//! The schedule: for each run, when to inject, into which component, which replica draw, and
//! exactly what (bit, bytes, seed) — all from the campaign seed, before the run starts.
//!
//! Run `r` of a campaign with seed `S` uses `ChaCha8Rng::seed_from_u64(run_seed(S, r))`, so a
//! run's schedule does not depend on which other runs are done, in which order, or on which
//! machine: that is what makes `--shard` slices add up to the whole campaign.

use std::time::Duration;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use s3res_protocol::campaign::{check_schedule, RateError};

use crate::fault::{Action, FaultKind};

pub use s3res_protocol::campaign::{Arrival, VarField, VarSpec};

/// The bits a variable-level injection flips: `var.bits` if given, else `var.flips` distinct
/// bits of its field drawn from `rng`.
fn choose_bits(var: &VarSpec, rng: &mut ChaCha8Rng) -> Vec<u32> {
    if let Some(bits) = &var.bits {
        return bits.clone();
    }
    let range = var.field.bits();
    let mut bits: Vec<u32> = rand::seq::index::sample(rng, range.len(), var.flips as usize)
        .into_iter()
        .map(|i| range.start + i as u32)
        .collect();
    bits.sort_unstable();
    bits
}

/// Everything the schedule depends on.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ScheduleParams {
    pub fault: FaultKind,
    /// Injections per second while the window is open.
    pub rate_hz: f64,
    pub arrival: Arrival,
    /// Length of the injection window of each run.
    pub window: Duration,
    /// Components to inject into, one chosen uniformly per injection.
    pub components: Vec<String>,
    pub var: VarSpec,
}

/// One planned injection.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Planned {
    /// 0, 1, ... within the run.
    pub index: usize,
    /// When, from the opening of the injection window.
    pub at_ns: u64,
    pub component: String,
    /// Uniform in [0, 1): picks the replica (uniformly over the slots, or by CPU time).
    pub draw: f64,
    pub action: Action,
}

/// SplitMix64 of `seed + run`: well-spread, independent seeds per run.
pub fn run_seed(seed: u64, run: u64) -> u64 {
    s3res_protocol::rng::derive(seed, run)
}

/// The injections of one run, in time order (none for fault kind `none`). Planned whole, so
/// refused beyond `campaign::MAX_PLANNED_PER_RUN` expected in the window.
pub fn plan_run(params: &ScheduleParams, seed: u64, run: u64) -> Result<Vec<Planned>, RateError> {
    let mut rng = ChaCha8Rng::seed_from_u64(run_seed(seed, run));
    let window_ns = params.window.as_nanos() as f64;
    if params.fault == FaultKind::None || params.components.is_empty() {
        return Ok(Vec::new());
    }
    check_schedule(params.rate_hz, params.window)?;
    let mean_ns = 1e9 / params.rate_hz;
    let mut out = Vec::new();
    let mut t = 0.0f64;
    loop {
        t += match params.arrival {
            Arrival::Fixed => mean_ns,
            // 1 - u is in (0, 1]: never ln(0).
            Arrival::Exponential => -(1.0 - rng.gen::<f64>()).ln() * mean_ns,
        };
        if t >= window_ns {
            break;
        }
        match draw_injection(params, &mut rng, out.len(), t as u64) {
            Some(p) => out.push(p),
            None => break,
        }
    }
    Ok(out)
}

/// The single injection of run `run` for `classify`: at a uniform instant of the window.
pub fn plan_single(params: &ScheduleParams, seed: u64, run: u64) -> Option<Planned> {
    let mut rng = ChaCha8Rng::seed_from_u64(run_seed(seed, run));
    let at = rng.gen_range(0..params.window.as_nanos().max(1) as u64);
    draw_injection(params, &mut rng, 0, at)
}

/// Target component, replica draw and action of one injection; `None` for fault `none` or
/// no component.
pub fn draw_injection(
    params: &ScheduleParams,
    rng: &mut ChaCha8Rng,
    index: usize,
    at_ns: u64,
) -> Option<Planned> {
    if params.components.is_empty() {
        return None;
    }
    let component = params.components[rng.gen_range(0..params.components.len())].clone();
    let draw = rng.gen::<f64>();
    // `mixed` is one of exec, sdc and cfe, drawn first; the action is then drawn as for it.
    let kind = match params.fault {
        FaultKind::Mixed => [FaultKind::Exec, FaultKind::Sdc, FaultKind::Cfe][rng.gen_range(0..3)],
        kind => kind,
    };
    let action = match kind {
        FaultKind::Exec => Action::Exec,
        FaultKind::Cfe => Action::Cfe,
        FaultKind::Sdc => Action::Sdc {
            value: rng.gen_range(0..=i32::MAX as u32),
        },
        FaultKind::Var => Action::Var {
            offset: params.var.offset,
            bits: choose_bits(&params.var, rng),
        },
        FaultKind::Reg => Action::Reg { seed: rng.gen() },
        FaultKind::None | FaultKind::Mixed => return None,
    };
    Some(Planned {
        index,
        at_ns,
        component,
        draw,
        action,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn params(fault: FaultKind) -> ScheduleParams {
        ScheduleParams {
            fault,
            rate_hz: 20.0,
            arrival: Arrival::Exponential,
            window: Duration::from_secs(10),
            components: vec!["a".into(), "b".into()],
            var: VarSpec {
                offset: 8,
                field: VarField::Exponent,
                flips: 2,
                bits: None,
            },
        }
    }

    #[test]
    fn same_seed_same_schedule_other_seed_other_schedule() {
        let p = params(FaultKind::Var);
        assert_eq!(plan_run(&p, 7, 3).unwrap(), plan_run(&p, 7, 3).unwrap());
        assert_ne!(plan_run(&p, 7, 3).unwrap(), plan_run(&p, 7, 4).unwrap());
        assert_ne!(plan_run(&p, 7, 3).unwrap(), plan_run(&p, 8, 3).unwrap());
    }

    #[test]
    fn exponential_rate_is_about_right_and_in_window() {
        let p = params(FaultKind::Sdc);
        let n: usize = (0..50).map(|r| plan_run(&p, 1, r).unwrap().len()).sum();
        // 50 runs × 10 s × 20 Hz = 10000 expected; Poisson sd = 100.
        assert!((9500..10500).contains(&n), "{n}");
        for pl in plan_run(&p, 1, 0).unwrap() {
            assert!(pl.at_ns < 10_000_000_000);
            assert!((0.0..1.0).contains(&pl.draw));
        }
    }

    #[test]
    fn fixed_arrival_is_periodic_and_none_injects_nothing() {
        let mut p = params(FaultKind::Exec);
        p.arrival = Arrival::Fixed;
        p.rate_hz = 2.0;
        p.window = Duration::from_millis(2100);
        let at: Vec<u64> = plan_run(&p, 0, 0)
            .unwrap()
            .iter()
            .map(|x| x.at_ns)
            .collect();
        assert_eq!(
            at,
            vec![500_000_000, 1_000_000_000, 1_500_000_000, 2_000_000_000]
        );
        assert!(plan_run(&params(FaultKind::None), 0, 0).unwrap().is_empty());
    }

    /// A run's schedule is planned whole: a rate nobody meant, or a window that would plan
    /// more than a million injections, is refused instead of filling the memory.
    #[test]
    fn a_schedule_too_large_to_plan_is_refused() {
        let mut p = params(FaultKind::Sdc);
        p.rate_hz = 1000.0;
        p.window = Duration::from_secs(1_000_000_000);
        assert!(matches!(
            plan_run(&p, 0, 0),
            Err(RateError::TooMany { planned, .. }) if planned == 1e12
        ));
        for rate in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            p.rate_hz = rate;
            let e = plan_run(&p, 0, 0).unwrap_err();
            assert!(matches!(e, RateError::NotARate(_)), "{rate}: {e}");
        }
        p.rate_hz = 1e9;
        p.window = Duration::from_millis(1);
        assert_eq!(plan_run(&p, 0, 0), Err(RateError::TooHigh(1e9)));
    }

    #[test]
    fn mixed_draws_exec_sdc_and_cfe_about_equally() {
        let p = params(FaultKind::Mixed);
        let mut counts = std::collections::BTreeMap::new();
        for run in 0..30 {
            for pl in plan_run(&p, 9, run).unwrap() {
                *counts.entry(pl.action.kind()).or_insert(0u32) += 1;
            }
        }
        // 30 runs × 10 s × 20 Hz = 6000 injections, about 2000 of each kind.
        let kinds: Vec<FaultKind> = counts.keys().copied().collect();
        assert_eq!(kinds, vec![FaultKind::Exec, FaultKind::Sdc, FaultKind::Cfe]);
        assert!(
            counts.values().all(|&n| (1800..2200).contains(&n)),
            "{counts:?}"
        );
    }

    #[test]
    fn var_bits_stay_in_the_field_and_are_distinct() {
        let p = params(FaultKind::Var);
        for pl in plan_run(&p, 5, 0).unwrap() {
            let Action::Var { offset, bits } = pl.action else {
                panic!()
            };
            assert_eq!(offset, 8);
            assert_eq!(bits.len(), 2);
            assert!(bits[0] < bits[1]);
            assert!(bits.iter().all(|b| (52..63).contains(b)));
        }
        let mut bad = p.var.clone();
        bad.flips = 12;
        assert!(bad.validate().is_err());
    }
}
