//! Deadlines on the CPU's own counter.
//!
//! The voter measures round deadlines and grace timers with the CPU's cycle counter — the
//! invariant TSC on x86-64 (`rdtsc`), the generic timer's virtual count on aarch64
//! (`CNTVCT_EL0`) — calibrated once at start-up against `CLOCK_MONOTONIC`. Reading the counter
//! is a single instruction, no system call, and it never jumps. Where the CPU offers no usable
//! counter (no invariant TSC, a kernel that marked the TSC unstable, a calibration that does not
//! settle, another architecture) the clock is `CLOCK_MONOTONIC` itself, and the reason is
//! logged. `S3RES_CLOCK=monotonic` forces that fallback (to compare the two).
//!
//! [`Instant`] is a point on that counter and is a drop-in for `std::time::Instant` in the
//! ways the voter uses it (`now`, `+ Duration`, ordering, `saturating_duration_since`,
//! `elapsed`). A duration read off the counter is rounded *down* against the highest rate the
//! calibration allows, so a `ppoll` timeout taken from it never outlasts the deadline: the loop
//! wakes at or before it, re-checks the counter, and waits again for what is left.
//!
//! Events keep `CLOCK_MONOTONIC` timestamps (`ts_ns`): they are compared across processes.

mod deadlines;
mod sys;

pub use deadlines::{Deadlines, Timer};

use std::fmt;
use std::ops::{Add, AddAssign, Sub};
use std::sync::OnceLock;
use std::time::Duration;

use replica_rt::sys::monotonic_ns;
use thiserror::Error;

/// Environment variable that chooses the clock: `counter` (the default) or `monotonic`.
pub const CLOCK_ENV: &str = "S3RES_CLOCK";

/// How long calibration lets the counter run against `CLOCK_MONOTONIC`.
const CALIBRATION_WINDOW: Duration = Duration::from_millis(10);
/// Readings taken at each end of the window; the tightest bracket wins (preemption between the
/// two clock reads only widens a bracket, it cannot make it lie).
const BRACKET_TRIES: usize = 16;
/// Calibrations tried before giving up on the counter (a busy machine can spoil one).
const CALIBRATION_ATTEMPTS: usize = 3;
/// A calibration less certain than this is not used.
const MAX_ERROR_PPM: f64 = 200.0;
/// `CLOCK_MONOTONIC`, which `ppoll` times out on, may be slewed by NTP after calibration by up
/// to 500 ppm (adjtimex's limit). Durations read off the counter allow for it, so a timeout can
/// still not overshoot; the price is waking up to 0.05 % early and waiting once more.
const SLEW_MARGIN_PPM: f64 = 500.0;
/// Rates outside this range are not a cycle counter.
const PLAUSIBLE_HZ: std::ops::RangeInclusive<f64> = 1.0e6..=1.0e11;
/// An aarch64 counter may disagree this much with its advertised frequency.
const MAX_ADVERTISED_DEVIATION_PPM: f64 = 1000.0;

/// Where the ticks come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Source {
    /// x86-64 invariant time-stamp counter.
    Tsc,
    /// aarch64 generic timer, `CNTVCT_EL0`.
    Cntvct,
    /// `CLOCK_MONOTONIC` (one tick per nanosecond).
    Monotonic,
}

impl fmt::Display for Source {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Source::Tsc => "tsc",
            Source::Cntvct => "cntvct",
            Source::Monotonic => "monotonic",
        })
    }
}

/// Which clock the user asked for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Choice {
    /// The CPU's counter where usable, else `CLOCK_MONOTONIC`.
    Counter,
    /// `CLOCK_MONOTONIC`, whatever the CPU offers.
    Monotonic,
}

#[derive(Debug, Error, PartialEq, Eq)]
#[error("{CLOCK_ENV}={value:?} is not a clock: use `counter` (the CPU's cycle counter, the default) or `monotonic`")]
pub struct ClockError {
    pub value: String,
}

impl Choice {
    /// Reads [`CLOCK_ENV`]; unset or empty means [`Choice::Counter`].
    pub fn from_env() -> Result<Choice, ClockError> {
        match std::env::var(CLOCK_ENV) {
            Err(_) => Ok(Choice::Counter),
            Ok(v) => Choice::parse(&v),
        }
    }

    pub fn parse(value: &str) -> Result<Choice, ClockError> {
        match value.trim() {
            "" | "counter" => Ok(Choice::Counter),
            "monotonic" => Ok(Choice::Monotonic),
            _ => Err(ClockError {
                value: value.to_owned(),
            }),
        }
    }
}

/// A calibrated tick source with its conversions.
#[derive(Debug, Clone)]
pub struct Clock {
    source: Source,
    counter: Option<sys::Counter>,
    /// Measured ticks per second.
    hz: f64,
    /// Half-width of the calibration's confidence interval, relative (ppm).
    error_ppm: f64,
    /// Nominal ticks per nanosecond, 32.32 fixed point: `Duration` → ticks.
    ticks_per_ns_q32: u64,
    /// Nanoseconds per tick at the highest rate the calibration (plus slew margin) allows,
    /// 32.32 fixed point, rounded down: ticks → `Duration`, never longer than the truth.
    ns_per_tick_floor_q32: u64,
    /// Why the counter is not used (`None` when it is).
    fallback: Option<String>,
}

impl Clock {
    /// `CLOCK_MONOTONIC`, one tick per nanosecond; `why` says why not the counter.
    pub fn monotonic(why: impl Into<String>) -> Clock {
        Clock {
            source: Source::Monotonic,
            counter: None,
            hz: 1e9,
            error_ppm: 0.0,
            ticks_per_ns_q32: 1 << 32,
            ns_per_tick_floor_q32: 1 << 32,
            fallback: Some(why.into()),
        }
    }

    /// A counter clock from a measured rate and its uncertainty.
    fn from_rate(source: Source, counter: Option<sys::Counter>, hz: f64, error_ppm: f64) -> Clock {
        const Q32: f64 = (1u64 << 32) as f64;
        let hz_high = hz * (1.0 + (error_ppm + SLEW_MARGIN_PPM) * 1e-6);
        Clock {
            source,
            counter,
            hz,
            error_ppm,
            ticks_per_ns_q32: (hz / 1e9 * Q32).round() as u64,
            // One below the floor: the float division may itself have rounded up.
            ns_per_tick_floor_q32: ((1e9 / hz_high * Q32).floor() as u64).saturating_sub(1),
            fallback: None,
        }
    }

    /// The clock a predecessor calibrated (`source`, `hz`, `error_ppm`), when the CPU's counter
    /// is still the one it measured and still trusted; else calibrated afresh. A voter that
    /// succeeds one that died saves the calibration's window (10 ms) this way.
    pub fn inherit(choice: Choice, source: Source, hz: f64, error_ppm: f64) -> Clock {
        let usable = choice == Choice::Counter
            && source != Source::Monotonic
            && PLAUSIBLE_HZ.contains(&hz)
            && error_ppm.is_finite()
            && (0.0..=MAX_ERROR_PPM).contains(&error_ppm);
        if let (true, Ok(counter)) = (usable, sys::probe()) {
            let same = matches!(
                (counter, source),
                (sys::Counter::Tsc, Source::Tsc) | (sys::Counter::Cntvct { .. }, Source::Cntvct)
            );
            if same && kernel_trusts(counter).is_ok() {
                return Clock::from_rate(source, Some(counter), hz, error_ppm);
            }
        }
        Clock::detect(choice)
    }

    /// Picks and calibrates the clock (a few tens of milliseconds with the counter).
    pub fn detect(choice: Choice) -> Clock {
        if choice == Choice::Monotonic {
            return Clock::monotonic(format!("{CLOCK_ENV}=monotonic"));
        }
        let counter = match sys::probe() {
            Ok(c) => c,
            Err(why) => return Clock::monotonic(why),
        };
        if let Err(why) = kernel_trusts(counter) {
            return Clock::monotonic(why);
        }
        let mut last = String::new();
        for _ in 0..CALIBRATION_ATTEMPTS {
            match calibrate(counter, CALIBRATION_WINDOW) {
                Ok((hz, error_ppm)) => {
                    let source = match counter {
                        sys::Counter::Tsc => Source::Tsc,
                        sys::Counter::Cntvct { .. } => Source::Cntvct,
                    };
                    return Clock::from_rate(source, Some(counter), hz, error_ppm);
                }
                Err(why) => last = why,
            }
        }
        Clock::monotonic(format!(
            "calibration failed {CALIBRATION_ATTEMPTS} times, last: {last}"
        ))
    }

    pub fn source(&self) -> Source {
        self.source
    }

    /// Measured ticks per second.
    pub fn hz(&self) -> f64 {
        self.hz
    }

    /// Calibration uncertainty (ppm, half-width).
    pub fn error_ppm(&self) -> f64 {
        self.error_ppm
    }

    /// Why the CPU's counter is not used, if it is not.
    pub fn fallback_reason(&self) -> Option<&str> {
        self.fallback.as_deref()
    }

    /// Logs what was chosen and, for the counter, the calibration.
    pub fn log(&self) {
        match &self.fallback {
            None => tracing::info!(
                source = %self.source,
                ticks_per_us = format_args!("{:.3}", self.hz / 1e6),
                error_ppm = format_args!("{:.2}", self.error_ppm),
                window_ms = CALIBRATION_WINDOW.as_millis() as u64,
                "deadline clock calibrated against CLOCK_MONOTONIC"
            ),
            Some(why) => tracing::info!(
                source = %self.source,
                reason = %why,
                "deadline clock: CLOCK_MONOTONIC (the CPU's counter is not used)"
            ),
        }
    }

    /// The current tick.
    #[inline]
    pub fn ticks(&self) -> u64 {
        match self.counter {
            Some(c) => sys::read(c),
            None => monotonic_ns(),
        }
    }

    /// Ticks in `d` at the measured rate (saturating).
    pub fn ticks_in(&self, d: Duration) -> u64 {
        let t = (d.as_nanos() * u128::from(self.ticks_per_ns_q32)) >> 32;
        u64::try_from(t).unwrap_or(u64::MAX)
    }

    /// The time `ticks` take, never longer than the truth: rounded down, at the highest rate
    /// the calibration (and a possible NTP slew of `CLOCK_MONOTONIC`) allows.
    pub fn duration_floor(&self, ticks: u64) -> Duration {
        let ns = (u128::from(ticks) * u128::from(self.ns_per_tick_floor_q32)) >> 32;
        Duration::from_nanos(u64::try_from(ns).unwrap_or(u64::MAX))
    }
}

/// Whether the kernel still offers the TSC as a clocksource: it withdraws it when it finds the
/// TSC unsynchronised between CPUs or unstable, and then so do we. (No answer is no objection.)
fn kernel_trusts(counter: sys::Counter) -> Result<(), String> {
    if counter != sys::Counter::Tsc {
        return Ok(());
    }
    let path = "/sys/devices/system/clocksource/clocksource0/available_clocksource";
    match std::fs::read_to_string(path) {
        Ok(list) if !list.split_whitespace().any(|c| c == "tsc") => Err(format!(
            "the kernel does not offer tsc as a clocksource ({path}: {}), so it found the TSC \
             unstable or unsynchronised between CPUs",
            list.trim()
        )),
        _ => Ok(()),
    }
}

/// One reading of the counter between two readings of `CLOCK_MONOTONIC`: the counter was read
/// at some monotonic time in `[before, after]`.
#[derive(Debug, Clone, Copy)]
struct Bracket {
    before: u64,
    ticks: u64,
    after: u64,
}

fn bracket(counter: sys::Counter) -> Bracket {
    let mut best: Option<Bracket> = None;
    for _ in 0..BRACKET_TRIES {
        let before = monotonic_ns();
        let ticks = sys::read(counter);
        let after = monotonic_ns();
        let b = Bracket {
            before,
            ticks,
            after,
        };
        best = match best {
            Some(x) if x.after - x.before <= b.after - b.before => Some(x),
            _ => Some(b),
        };
    }
    best.expect("BRACKET_TRIES > 0")
}

/// Measures the counter's rate against `CLOCK_MONOTONIC` over `window`: (Hz, error in ppm).
fn calibrate(counter: sys::Counter, window: Duration) -> Result<(f64, f64), String> {
    let start = bracket(counter);
    std::thread::sleep(window);
    let end = bracket(counter);
    let ticks = end
        .ticks
        .checked_sub(start.ticks)
        .filter(|&t| t > 0)
        .ok_or_else(|| {
            format!(
                "the counter did not advance ({} then {})",
                start.ticks, end.ticks
            )
        })? as f64;
    let mid = |b: Bracket| (b.before as f64 + b.after as f64) / 2.0;
    let elapsed_ns = mid(end) - mid(start);
    let shortest_ns = end.before.saturating_sub(start.after) as f64;
    let longest_ns = end.after.saturating_sub(start.before) as f64;
    if shortest_ns <= 0.0 {
        return Err("the calibration window was not measurable".into());
    }
    let hz = ticks * 1e9 / elapsed_ns;
    let hz_high = ticks * 1e9 / shortest_ns;
    let hz_low = ticks * 1e9 / longest_ns;
    let error_ppm = (hz_high - hz_low) / 2.0 / hz * 1e6;
    if !PLAUSIBLE_HZ.contains(&hz) {
        return Err(format!(
            "measured rate {hz:.0} Hz is not a plausible counter rate"
        ));
    }
    if error_ppm > MAX_ERROR_PPM {
        return Err(format!(
            "calibration too uncertain: ±{error_ppm:.1} ppm (limit {MAX_ERROR_PPM} ppm)"
        ));
    }
    if let sys::Counter::Cntvct { advertised_hz } = counter {
        let off_ppm = (hz - advertised_hz as f64).abs() / advertised_hz as f64 * 1e6;
        if off_ppm > MAX_ADVERTISED_DEVIATION_PPM {
            return Err(format!(
                "CNTVCT_EL0 runs at {hz:.0} Hz but CNTFRQ_EL0 says {advertised_hz} Hz"
            ));
        }
    }
    Ok((hz, error_ppm))
}

static CLOCK: OnceLock<Clock> = OnceLock::new();

/// Chooses (from [`CLOCK_ENV`]), calibrates and logs the process's clock, and sets the calling
/// thread's timer slack to 1 ns. Call once at start, from the thread that waits,
/// before any [`Instant`] is taken, so that a bad setting is an error and calibration does not
/// fall into the first round.
pub fn init() -> Result<&'static Clock, ClockError> {
    init_from(None)
}

/// [`init`], taking over a predecessor's calibration (source, Hz, ppm) where it still holds
/// (see [`Clock::inherit`]).
pub fn init_from(inherited: Option<(Source, f64, f64)>) -> Result<&'static Clock, ClockError> {
    let choice = Choice::from_env()?;
    let mut fresh = false;
    let clock = CLOCK.get_or_init(|| {
        fresh = true;
        match inherited {
            Some((source, hz, error_ppm)) => Clock::inherit(choice, source, hz, error_ppm),
            None => Clock::detect(choice),
        }
    });
    if fresh {
        clock.log();
        // A deadline should end a wait when it is due, not up to 50 µs later (the default
        // slack of a normal thread; a SCHED_RR voter has none anyway).
        if let Err(e) = sys::set_timer_slack(1) {
            tracing::warn!(error = %e, "cannot lower the timer slack; waits may end up to 50 µs late");
        }
    }
    Ok(clock)
}

/// The process's clock; detected on first use if [`init`] was not called (a bad
/// [`CLOCK_ENV`] then means the default).
pub fn clock() -> &'static Clock {
    CLOCK.get_or_init(|| {
        let choice = Choice::from_env().unwrap_or_else(|e| {
            tracing::warn!(error = %e, "using the counter");
            Choice::Counter
        });
        let clock = Clock::detect(choice);
        clock.log();
        clock
    })
}

/// A point in time on the process's [`Clock`]: a drop-in for `std::time::Instant` in deadline
/// arithmetic. Durations taken from it are rounded down (see [`Clock::duration_floor`]).
#[derive(Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct Instant(u64);

impl Instant {
    #[inline]
    pub fn now() -> Instant {
        Instant(clock().ticks())
    }

    /// The raw tick.
    pub fn ticks(self) -> u64 {
        self.0
    }

    /// Time from `earlier` to `self`, zero if `earlier` is later; never longer than the truth.
    pub fn saturating_duration_since(self, earlier: Instant) -> Duration {
        clock().duration_floor(self.0.saturating_sub(earlier.0))
    }

    pub fn checked_duration_since(self, earlier: Instant) -> Option<Duration> {
        (self >= earlier).then(|| self.saturating_duration_since(earlier))
    }

    /// Time since `self`, rounded down. To ask whether a deadline has passed, compare instants
    /// (`Instant::now() >= start + limit`): that is exact on the counter.
    pub fn elapsed(self) -> Duration {
        Instant::now().saturating_duration_since(self)
    }
}

impl Add<Duration> for Instant {
    type Output = Instant;
    fn add(self, d: Duration) -> Instant {
        Instant(self.0.saturating_add(clock().ticks_in(d)))
    }
}

impl AddAssign<Duration> for Instant {
    fn add_assign(&mut self, d: Duration) {
        *self = *self + d;
    }
}

impl Sub<Duration> for Instant {
    type Output = Instant;
    fn sub(self, d: Duration) -> Instant {
        Instant(self.0.saturating_sub(clock().ticks_in(d)))
    }
}

/// Saturating, like `std::time::Instant` since Rust 1.60.
impl Sub<Instant> for Instant {
    type Output = Duration;
    fn sub(self, earlier: Instant) -> Duration {
        self.saturating_duration_since(earlier)
    }
}

impl fmt::Debug for Instant {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "Instant({} ticks)", self.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn choice_parses_and_rejects_clearly() {
        assert_eq!(Choice::parse(""), Ok(Choice::Counter));
        assert_eq!(Choice::parse("counter"), Ok(Choice::Counter));
        assert_eq!(Choice::parse(" monotonic\n"), Ok(Choice::Monotonic));
        let e = Choice::parse("tsc").unwrap_err();
        assert!(e.to_string().contains("S3RES_CLOCK=\"tsc\""), "{e}");
    }

    #[test]
    fn monotonic_clock_is_the_identity() {
        let c = Clock::monotonic("test");
        assert_eq!(c.source(), Source::Monotonic);
        for ns in [0u64, 1, 999, 1_000_000_007, u64::MAX / 2] {
            assert_eq!(c.ticks_in(Duration::from_nanos(ns)), ns);
            assert_eq!(c.duration_floor(ns), Duration::from_nanos(ns));
        }
    }

    /// Calibration on this machine's counter (or the reason there is none): the rate is
    /// plausible, the counter runs forward, and it agrees with CLOCK_MONOTONIC over a sleep.
    #[test]
    fn calibration_is_monotonic_and_sane() {
        let c = Clock::detect(Choice::Counter);
        eprintln!(
            "clock: source {} ticks/us {:.3} error {:.2} ppm fallback {:?}",
            c.source(),
            c.hz() / 1e6,
            c.error_ppm(),
            c.fallback_reason()
        );
        if c.source() == Source::Monotonic {
            assert!(c.fallback_reason().is_some());
        } else {
            assert!(PLAUSIBLE_HZ.contains(&c.hz()));
            assert!(c.error_ppm() <= MAX_ERROR_PPM);
        }
        let mut last = c.ticks();
        for _ in 0..10_000 {
            let t = c.ticks();
            assert!(t >= last, "counter went backwards: {last} then {t}");
            last = t;
        }
        // Over 20 ms the counter and CLOCK_MONOTONIC agree to well within 1 %. The monotonic
        // reads bracket the counter's, so preemption between them only makes the monotonic
        // span longer: the counter's never exceeds it, and the closest of a few tries (on a
        // shared machine one may be preempted for longer than 1 % of 20 ms) is within 1 %.
        let mut closest = 0.0f64;
        for _ in 0..5 {
            let (m0, t0) = (monotonic_ns(), c.ticks());
            std::thread::sleep(Duration::from_millis(20));
            let (t1, m1) = (c.ticks(), monotonic_ns());
            let by_counter = c.duration_floor(t1 - t0).as_nanos() as f64;
            let by_monotonic = (m1 - m0) as f64;
            assert!(by_counter <= by_monotonic, "{by_counter} > {by_monotonic}");
            closest = closest.max(by_counter / by_monotonic);
        }
        assert!(closest > 0.99, "counter/monotonic at best {closest}");
    }

    #[test]
    fn forced_monotonic_says_why() {
        let c = Clock::detect(Choice::Monotonic);
        assert_eq!(c.source(), Source::Monotonic);
        assert!(c.fallback_reason().unwrap().contains("S3RES_CLOCK"));
    }

    #[test]
    fn instant_arithmetic_behaves_like_std() {
        let a = Instant::now();
        let b = a + Duration::from_millis(5);
        assert!(b > a);
        assert_eq!(a.saturating_duration_since(b), Duration::ZERO);
        assert_eq!(a.checked_duration_since(b), None);
        let d = b.saturating_duration_since(a);
        assert!(d <= Duration::from_millis(5), "{d:?}");
        assert!(d >= Duration::from_micros(4990), "{d:?}");
        assert_eq!(b - a, d);
        assert!(b - Duration::from_millis(5) <= a);
        let mut c = a;
        c += Duration::from_millis(5);
        assert_eq!(c, b);
    }

    proptest! {
        /// Duration → ticks → duration never grows, and loses no more than the error margin
        /// and rounding allow.
        #[test]
        fn conversions_round_trip(
            hz in 1.0e6f64..1.0e11,
            error_ppm in 0.0f64..MAX_ERROR_PPM,
            ns in 0u64..10_000_000_000_000,
        ) {
            let c = Clock::from_rate(Source::Tsc, None, hz, error_ppm);
            let d = Duration::from_nanos(ns);
            let back = c.duration_floor(c.ticks_in(d));
            prop_assert!(back <= d, "{back:?} > {d:?}");
            let margin = (error_ppm + SLEW_MARGIN_PPM + 1.0) * 1e-6;
            let tick_ns = 1e9 / hz;
            let lowest = ns as f64 * (1.0 - margin) - 2.0 * tick_ns - 2.0;
            prop_assert!(back.as_nanos() as f64 >= lowest, "{back:?} from {d:?}");
        }

        /// A wait of `duration_floor(remaining)` nanoseconds, at any true counter rate the
        /// calibration allows, lets at most `remaining` ticks pass: it never overshoots.
        #[test]
        fn a_wait_never_overshoots_the_deadline(
            hz in 1.0e6f64..1.0e11,
            error_ppm in 0.0f64..MAX_ERROR_PPM,
            slew in -1.0f64..=1.0,
            remaining in 0u64..u64::MAX / 1024,
        ) {
            let c = Clock::from_rate(Source::Tsc, None, hz, error_ppm);
            // The true rate: anywhere in the calibrated interval widened by the slew margin.
            let true_hz = (hz * (1.0 + slew * (error_ppm + SLEW_MARGIN_PPM) * 1e-6)).floor() as u128;
            let wait_ns = c.duration_floor(remaining).as_nanos();
            // Ticks elapsed during the wait = wait_ns * true_hz / 1e9, exactly.
            prop_assert!(wait_ns * true_hz <= u128::from(remaining) * 1_000_000_000,
                "waiting {wait_ns} ns at {true_hz} Hz passes more than {remaining} ticks");
        }
    }
}
