//! A short spin before the voter sleeps for an answer from another CPU.
//!
//! Where the voter is pinned to a CPU of its own and its replicas run on others, a replica
//! answers a few µs after its input (an echo: 3–10 µs on the 2-core VM of docs/results.md),
//! while the voter, after its writes, is still on its way into `epoll_wait`. An answer that
//! meets the voter there wakes a task that is still on its CPU: the kernel queues that wake-up
//! on the voter's CPU and sends it an interrupt, and on a VM the interrupt takes ~13 µs to be
//! handled (stop 52: 0.84–0.95 such interrupts a round in SMR across CPUs, and S³RES's voter,
//! asleep in `select` before the answer came, 0.03). An answer that finds the voter already
//! asleep on an idle CPU is cheap, and one that finds it awake costs nothing at all.
//!
//! So before it sleeps for such an answer the voter looks again and again, for at most the
//! component's `spin_us`: `epoll_wait` with no timeout on the very set it would sleep on (an
//! answer, a death, a signal or the timer each end the spin as they would end the sleep),
//! with a `sched_yield` between looks, so that a task of the voter's own priority on its CPU
//! (a downstream component, a benchmark's client) still runs when it wants to. Only then does
//! it sleep.
//!
//! **Where.** Only while a round waits for replicas when none of them runs on the voter's CPU
//! (`sched::voter_apart`). A replica on the voter's own CPU can run only when the voter sleeps
//! (the voter outranks it): spinning there would only delay the answer. Unpinned replicas may
//! be anywhere, so there is no spin either. Never while the voter waits for input: what sends
//! it may be waiting for the voter's CPU.
//!
//! **How much.** A spin is real-time CPU time, and the kernel throttles real-time tasks that
//! use more than 95 % of a CPU (`sched_rt_runtime_us`, per second): they stop for the rest of
//! that second. A spin without bound was tried in stop 30 and met it; this one too, with a
//! budget of a quarter of the time, in stop 53: a back-to-back round-trip benchmark keeps the
//! voter's CPU 70–90 % busy without any spin, and the budget's quarter brought it to 950 ms in
//! a second, throttled. So the voter spins only while its CPU has been busy less than
//! [`BUSY_LIMIT_PERCENT`] of the last second ([`Headroom`]: `/proc/stat`'s counts of that
//! CPU, read every [`SAMPLE_EVERY`]); busier, it sleeps at once, as without the spin, until
//! the second's share comes down. A control loop at some kHz leaves its CPU mostly idle and
//! always spins; back-to-back rounds spin until their CPU's last second is that busy.

use std::fs::File;
use std::os::unix::fs::FileExt;
use std::time::Duration;

use s3res_protocol::machine::{CpuTimes, Cpus};

use crate::clock::Instant;

/// How busy the voter's CPU may have been over the last second for the voter to spin.
pub const BUSY_LIMIT_PERCENT: u64 = 85;

/// How often the CPU's counts are read.
pub const SAMPLE_EVERY: Duration = Duration::from_millis(100);

/// Samples kept: the last second (the kernel's real-time period) between the oldest and the
/// newest.
const SAMPLES: usize = 11;

/// Enough of `/proc/stat` for the `cpuN` lines of a few hundred CPUs (they come first).
const STAT_BYTES: usize = 32 * 1024;

/// The spin of one voter: how long a spin may last, and whether its CPU has room for one.
#[derive(Debug)]
pub struct Spin {
    /// The longest single spin (the component's `spin_us`); zero: never.
    limit: Duration,
    /// The voter's CPU's recent load; `None`: the voter has no CPU of its own, or its load
    /// cannot be read, and does not spin.
    headroom: Option<Headroom>,
}

impl Spin {
    /// The spin of a voter pinned to `cpu` (`None`: not pinned to a CPU of its own).
    pub fn new(spin_us: u32, cpu: Option<usize>) -> Spin {
        let limit = Duration::from_micros(u64::from(spin_us));
        let headroom = match cpu {
            Some(cpu) if !limit.is_zero() => Headroom::open(cpu)
                .inspect_err(|e| {
                    tracing::info!(
                        error = %e,
                        "/proc/stat cannot be read: the voter does not spin for answers \
                         (spin_us), it sleeps for them"
                    );
                })
                .ok(),
            _ => None,
        };
        Spin { limit, headroom }
    }

    /// How long the wait about to begin may spin, at `now`; `None`: it sleeps at once.
    pub fn grant(&mut self, now: Instant) -> Option<Duration> {
        let headroom = self.headroom.as_mut()?;
        headroom.sample_if_due(now);
        headroom.room().then_some(self.limit)
    }
}

/// A CPU's busy share over the last second, from its `/proc/stat` line.
#[derive(Debug)]
pub struct Headroom {
    cpu: usize,
    stat: File,
    buf: Box<[u8]>,
    load: Load,
    next_sample: Option<Instant>,
}

impl Headroom {
    fn open(cpu: usize) -> std::io::Result<Headroom> {
        let mut headroom = Headroom {
            cpu,
            stat: File::open("/proc/stat")?,
            buf: vec![0; STAT_BYTES].into_boxed_slice(),
            load: Load::default(),
            next_sample: None,
        };
        let ticks = headroom.read()?;
        headroom.load.observe(ticks);
        Ok(headroom)
    }

    fn read(&mut self) -> std::io::Result<CpuTimes> {
        let n = self.stat.read_at(&mut self.buf, 0)?;
        std::str::from_utf8(&self.buf[..n])
            .ok()
            .and_then(|text| CpuTimes::parse(text, Cpus::One(self.cpu)))
            .ok_or_else(|| {
                std::io::Error::new(
                    std::io::ErrorKind::InvalidData,
                    format!("no line for CPU {} in /proc/stat", self.cpu),
                )
            })
    }

    fn sample_if_due(&mut self, now: Instant) {
        if self.next_sample.is_some_and(|at| now < at) {
            return;
        }
        self.next_sample = Some(now + SAMPLE_EVERY);
        // A failed read leaves the last verdict: the file was read at the start.
        if let Ok(ticks) = self.read() {
            self.load.observe(ticks);
        }
    }

    fn room(&self) -> bool {
        self.load.room()
    }
}

/// The last [`SAMPLES`] counts of a CPU, oldest first, and what they say.
#[derive(Debug, Default)]
pub struct Load {
    samples: [CpuTimes; SAMPLES],
    len: usize,
}

impl Load {
    pub fn observe(&mut self, ticks: CpuTimes) {
        if self.len == SAMPLES {
            self.samples.copy_within(1.., 0);
            self.len -= 1;
        }
        self.samples[self.len] = ticks;
        self.len += 1;
    }

    /// Whether the CPU was busy less than [`BUSY_LIMIT_PERCENT`] of the span the samples
    /// cover (a single sample, or no tick between them: nothing says otherwise).
    pub fn room(&self) -> bool {
        if self.len < 2 {
            return true;
        }
        let (first, last) = (self.samples[0], self.samples[self.len - 1]);
        let busy = last.busy.saturating_sub(first.busy);
        let total = last.total.saturating_sub(first.total);
        total == 0 || busy * 100 < BUSY_LIMIT_PERCENT * total
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ticks(busy: u64, idle: u64) -> CpuTimes {
        CpuTimes {
            busy,
            total: busy + idle,
            steal: 0,
        }
    }

    #[test]
    fn a_cpu_busy_less_than_the_limit_has_room() {
        let mut load = Load::default();
        assert!(load.room(), "nothing known yet");
        load.observe(ticks(0, 0));
        assert!(load.room(), "one sample");
        load.observe(ticks(0, 0));
        assert!(load.room(), "no tick between the samples");
        // 10 ticks a sample, 7 of them busy: 70 %.
        for k in 1..=20 {
            load.observe(ticks(7 * k, 3 * k));
            assert!(load.room(), "sample {k}");
        }
    }

    #[test]
    fn a_busy_second_stops_the_spin_until_it_has_passed() {
        let mut load = Load::default();
        let (mut busy, mut idle) = (0, 0);
        let mut step = |load: &mut Load, b: u64, i: u64| {
            busy += b;
            idle += i;
            load.observe(ticks(busy, idle));
            load.room()
        };
        for _ in 0..SAMPLES {
            assert!(step(&mut load, 5, 5));
        }
        // Back to back with the spin: 10 of 10 ticks busy. The second's share reaches 85 % at
        // the seventh such sample.
        let spun: Vec<bool> = (0..SAMPLES - 1).map(|_| step(&mut load, 10, 0)).collect();
        assert_eq!(
            spun,
            [true, true, true, true, true, true, false, false, false, false]
        );
        // Without the spin the CPU is 70 % busy: the share comes down, and the spin resumes.
        let resumed = (0..SAMPLES - 1).position(|_| step(&mut load, 7, 3));
        assert!(resumed.is_some(), "never resumed");
    }

    #[test]
    fn zero_or_no_cpu_of_its_own_never_spins() {
        assert_eq!(Spin::new(0, Some(0)).grant(Instant::now()), None);
        assert_eq!(Spin::new(50, None).grant(Instant::now()), None);
        // A CPU `/proc/stat` has no line for (not online, or a number past the machine's):
        // its load cannot be known, so the voter sleeps at once.
        assert_eq!(Spin::new(50, Some(1 << 20)).grant(Instant::now()), None);
    }

    #[test]
    fn this_machines_first_cpu_is_read() {
        let mut spin = Spin::new(50, Some(0));
        assert!(spin.headroom.is_some(), "/proc/stat has a cpu0 line");
        // Whether it grants depends on how busy CPU 0 is; when it does, its limit.
        if let Some(d) = spin.grant(Instant::now()) {
            assert_eq!(d, Duration::from_micros(50));
        }
    }
}
