//! Could a late replica have answered? A deadline measures wall-clock time, but a replica
//! only computes while it has a CPU. When the machine stalls (the kernel's real-time
//! throttling stops every SCHED_RR task for tens of ms; a busier process of higher priority
//! holds the replica's CPU; the voter itself is held up), a healthy replica misses its
//! deadline without being at fault, and blaming it costs a recovery and, when all of them
//! miss it together, the round.
//!
//! So a window before a round's deadline (a tenth of `timeout_us`) the voter reads, for each
//! replica that has not answered yet, how long it has run (a perf task clock, exact to the
//! read: `/proc`'s counts and the process CPU clock move on only at scheduler ticks,
//! milliseconds apart, so a spinning replica would look idle for a whole window) and how long
//! it has waited for a CPU (`/proc/PID/schedstat`). It reads again just before the deadline (a
//! quarter of the window before it), so that the reads do not delay the decision. Over that
//! window a late replica:
//!
//! * **had its chance**: it ran at least a quarter of it on a CPU (spinning, perhaps preempted
//!   now and then), or ran less and is not waiting for a CPU (asleep, stopped, blocked). It is
//!   late, blamed at the deadline exactly as without the looks;
//! * **starved**: it ran less than a quarter of the window and finished waiting for a CPU for
//!   at least a quarter of it; or it is waiting for a CPU right now (state `R`) and ran less
//!   than a quarter of the time its clock was read over. (The kernel adds a wait to
//!   `schedstat` only when the wait ends, so a replica kept off its CPU for the whole window
//!   shows no wait yet; its state says that it is runnable.) The deadline moves on by one
//!   window, and it is judged again then. The extensions of one round are bounded
//!   ([`MAX_EXTENSION`]), so a replica that never gets a CPU is still blamed in the end.
//!   So is a replica waiting for a CPU now whose two samples say it ran more than twice the
//!   window: one of them was not its time when it was read, and the pair says nothing of the
//!   window (seen once, in the hog test: "ran 2816 µs" in 211).
//!
//! *The time its clock was read over* is shorter than the window: the first look opens the
//! replica's task clock, which takes 20–260 µs (`perf_event_open`, measured), and the clock
//! counts from its opening only. (It counts as at least half the window: over a shorter span
//! the share run says little, as for a replica preempted just after it got its CPU.) A spinner on another CPU ran the whole window, but its clock
//! saw only the part after the open: measured against the whole window it ran "less than a
//! quarter" (48 of 218 µs) and, being `R`, looked starved, so every such hang got one window
//! more (the hang p99 of `s3res-bench detect` 2–3 times its median). Its run time is measured
//! against its clock's own span instead. The booked wait keeps the whole window: a replica
//! that got its CPU back just before the second look after milliseconds without one ran a
//! large part of a short clock span ("in the last 55 µs it ran 23 µs and waited 4926 µs"),
//! and is starved by its wait. So is one whose wait, ended in the window, was longer than the
//! whole window, however long it ran since: a CPU held from a replica for 30 ms gave it back
//! with 200–300 µs of work that was not the replica's round (`real_time.rs`'s hog test failed
//! on it about one run in twenty). That backlog can outlast a window, so the windows after the
//! one it came back in are starved too, however it ran, one for every thirtieth of its wait
//! ([`after_coming_back`], [`windows_after_coming_back`]: five after 30 ms at a 2 ms deadline;
//! one window was too few on the AMD host, stop 42); a spinner that came back so is blamed
//! that many windows later. A replica comes back so, too, when it has its chance in a window
//! right after windows in which it was found starved, whatever wait the kernel booked
//! ([`after_starving`]): a replica whose vCPU the host took books no wait at all.
//!
//! A CPU can also be lost in a way no wait shows (traced on the Intel host, stop 61): a
//! replica that the guest has on a CPU the host took books no wait at all, and its task clock
//! counts the stolen time as run. Only a read of that clock shows it, since the read waits for
//! that CPU to take an interrupt: a look whose read waited a quarter of the window starves the
//! window ([`cpu_held`]).
//!
//! A voter that itself woke up past the first look (it was held up too) did not see the
//! window: the deadline moves on by one window, with a fresh look. One that woke up past the
//! second looks then, and reads the late replicas' pipes after that look, not before. So
//! does one that took either look a whole window or more after it was due
//! ([`voter_held_up`]): what held the voter up held the machine, and the window it judged is
//! not the one before the deadline.
//!
//!
//! What was seen goes into the `hang` event's detail ("in the last 180 µs it ran 0 µs (of 175
//! µs on its clock) and waited 0 µs for a CPU; state R (runnable: a wait for a CPU is counted
//! only when it ends)"), and so does how far the round's deadline had been moved on: a
//! replica still starved when the extensions are used up is blamed with "after its deadline
//! was moved on 100000 µs for want of a CPU".
//!
//! The cost: nothing in a round where every replica answers before the first look; per late
//! replica otherwise, a task-clock read and a `pread` at each look (the task clock and the
//! file are opened at its first look), and a read of its state if it ran less than a quarter
//! of the window.

use std::cell::OnceCell;
use std::fs::File;
use std::os::unix::fs::FileExt;
use std::time::Duration;

use replica_rt::sys::TaskClock;

/// How long the deadlines of one round may be moved on in all, at most: longer than the
/// kernel's real-time throttling holds tasks (50 ms of every second by default).
pub const MAX_EXTENSION: Duration = Duration::from_millis(100);

/// The shortest window looked at: below this, one scheduler tick decides.
const MIN_WINDOW: Duration = Duration::from_micros(100);

/// The window for a round deadline of `timeout`: a tenth of it, at least [`MIN_WINDOW`], at
/// most the timeout itself.
pub fn window(timeout: Duration) -> Duration {
    (timeout / 10).max(MIN_WINDOW).min(timeout)
}

/// How long before the deadline the second look is taken: long enough for its reads (a
/// remote task clock is read through an interrupt to the replica's CPU), so that the
/// decision is ready at the deadline and a hang is reported as soon as without the looks.
pub fn second_look(window: Duration) -> Duration {
    (window / 4).max(Duration::from_micros(25))
}

/// A process's time on a CPU and waiting for one, so far.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SchedTimes {
    pub run_ns: u64,
    pub wait_ns: u64,
}

impl SchedTimes {
    /// `/proc/PID/schedstat`: "run_ns wait_ns timeslices".
    pub fn parse(text: &str) -> Option<SchedTimes> {
        let mut fields = text.split_ascii_whitespace().map(|f| f.parse::<u64>().ok());
        Some(SchedTimes {
            run_ns: fields.next()??,
            wait_ns: fields.next()??,
        })
    }
}

/// Where a replica's times are read: its `/proc/PID/schedstat` (a read is one `pread`) and
/// its task clock (`replica_rt::sys::TaskClock`), each opened at the first look, so that
/// starting or recovering a replica costs nothing more.
#[derive(Debug)]
pub struct SchedStat {
    pid: libc::pid_t,
    file: OnceCell<Option<File>>,
    clock: OnceCell<Option<TaskClock>>,
}

impl SchedStat {
    pub fn new(pid: libc::pid_t) -> SchedStat {
        SchedStat {
            pid,
            file: OnceCell::new(),
            clock: OnceCell::new(),
        }
    }

    /// Whether the run [`SchedStat::read`] gives comes from the replica's task clock (not
    /// yet known before the first read).
    pub fn on_clock(&self) -> bool {
        matches!(self.clock.get(), Some(Some(_)))
    }

    /// `None` where `/proc` does not say: the replica is then judged as without the look.
    pub fn read(&self) -> Option<Sample> {
        let file = self
            .file
            .get_or_init(|| File::open(format!("/proc/{}/schedstat", self.pid)).ok())
            .as_ref()?;
        let mut buf = [0u8; 96];
        let n = file.read_at(&mut buf, 0).ok()?;
        let booked = SchedTimes::parse(std::str::from_utf8(&buf[..n]).ok()?)?;
        // Only a read of a clock already open is timed: the open is slow by itself.
        let was_open = self.clock.get().is_some();
        let clock = self.clock.get_or_init(|| match TaskClock::open(self.pid) {
            Ok(c) => Some(c),
            Err(e) => {
                static SAID: std::sync::Once = std::sync::Once::new();
                SAID.call_once(|| {
                    tracing::info!(
                        error = %e,
                        "no task clock (perf_event_open); a late replica's time on a CPU is \
                         known to a scheduler tick only"
                    );
                });
                None
            }
        });
        let (run_ns, held) = match clock {
            Some(c) => {
                let asked = crate::clock::Instant::now();
                let run_ns = c.read()?;
                let held = if was_open {
                    crate::clock::Instant::now().saturating_duration_since(asked)
                } else {
                    Duration::ZERO
                };
                (run_ns, held)
            }
            None => (booked.run_ns, Duration::ZERO),
        };
        Some(Sample {
            times: SchedTimes {
                run_ns,
                wait_ns: booked.wait_ns,
            },
            held,
        })
    }
}

/// One look at a replica: its times so far, and how long reading its task clock took.
///
/// The read of a replica that is on a CPU right now is an interrupt to that CPU, answered
/// within microseconds while the CPU runs. A read that takes a quarter of a window was
/// waiting for a CPU that did not run: a virtual CPU the host took (steal time) while the
/// replica was on it, which the guest's clocks count as the replica's run (see
/// [`cpu_held`]), or the voter's own CPU taken in the middle of its read.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Sample {
    pub times: SchedTimes,
    pub held: Duration,
}

/// What the looks saw a late replica do over the window before its deadline (for the `hang`
/// event's detail).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Seen {
    pub window_us: u64,
    /// The part of the window the replica's clock was read over (see the module's comment).
    pub clocked_us: u64,
    /// Whether its run comes from its task clock (exact to the read) or, where the clock could
    /// not be opened, from what the kernel has booked (at scheduler ticks and switches only).
    pub on_clock: bool,
    pub ran_us: u64,
    pub waited_us: u64,
    /// Its state at the second look, where it was read.
    pub state: Option<char>,
    /// Asleep: the kernel function it sleeps in (`/proc/PID/wchan`).
    pub wchan: Option<replica_rt::sys::Wchan>,
    /// The longest a read of its task clock waited for its CPU at the looks (see [`Sample`]).
    pub held_us: u64,
}

impl Seen {
    pub fn between(
        before: SchedTimes,
        after: SchedTimes,
        window: Duration,
        clocked: Duration,
    ) -> Seen {
        Seen {
            window_us: window.as_micros() as u64,
            clocked_us: clocked.min(window).as_micros() as u64,
            on_clock: true,
            ran_us: after.run_ns.saturating_sub(before.run_ns) / 1000,
            waited_us: after.wait_ns.saturating_sub(before.wait_ns) / 1000,
            state: None,
            wchan: None,
            held_us: 0,
        }
    }
}

impl std::fmt::Display for Seen {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let clock = if self.on_clock {
            "on its clock"
        } else {
            "as the kernel booked it, at its ticks: no task clock"
        };
        write!(
            f,
            "in the last {} µs it ran {} µs (of {} µs {clock}) and waited {} µs for a CPU",
            self.window_us, self.ran_us, self.clocked_us, self.waited_us
        )?;
        match self.state {
            // Read only for a replica that ran less than a quarter of its clock's span: `R` is
            // then most likely one queued for a CPU, whose wait so far is not in the figure
            // above (the kernel adds a wait to it only when the wait ends).
            Some('R') => write!(
                f,
                "; state R (runnable: a wait for a CPU is counted only when it ends)"
            )?,
            Some(s) => write!(f, "; state {s}")?,
            None => {}
        }
        if let Some(w) = self.wchan {
            write!(f, ", asleep in {}", w.as_str())?;
        }
        // Said when it decides (`cpu_held`): below that, an interrupt's ordinary latency.
        if held_long(
            Duration::from_micros(self.held_us),
            Duration::from_micros(self.window_us),
        ) {
            write!(
                f,
                "; a read of its clock waited {} µs for its CPU (the host held that CPU)",
                self.held_us
            )?;
        }
        Ok(())
    }
}

/// Whether a look taken `late` after it was due says that the voter itself was held up over
/// a window of `window`: a whole window or more. Its window is then not the one the rule
/// needs (the look's span stretches over the stall), and the deadline moves on by one window
/// with a fresh look, as for a voter that missed its look altogether (but the window does not
/// count as one its replicas went without a CPU: their looks saw them run).
///
/// Why: the looks before a 2 ms deadline are due 150 µs apart, and of the 50 false `hang`s
/// of fault-free TMR rounds at 2 ms whose details docs/results keeps (stops 52–64), 17 had
/// been judged over 233–8171 µs: the second look came after a stall of the voter, and the
/// host that held the voter up had held the replicas too (what their clocks counted as run
/// was not theirs: steal). Why not less than a window: this VM wakes the voter for a look
/// 48–126 µs late as a rule (traced in `s3res-bench detect`'s hang rounds, stop 65), the
/// very lateness of the 11 others (68–99 µs spans); a quarter of a window moved the deadline
/// on in most hang rounds and took the hang median from 150 to 392 µs (results.md, stop 65).
pub fn voter_held_up(late: Duration, window: Duration) -> bool {
    late >= window
}

/// What a late replica did over the window before its deadline.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Window {
    /// It had a CPU for at least a quarter of the window, or was not waiting for one: its
    /// lateness is its own.
    HadItsChance,
    /// It ran less than a quarter of the window and was kept waiting for a CPU.
    Starved,
    /// It has just got its CPU back after a wait longer than the window: starved, and the
    /// next window is its own too ([`after_coming_back`]).
    CameBack,
}

impl Window {
    /// Whether the deadline moves on for it.
    pub fn starved(self) -> bool {
        self != Window::HadItsChance
    }
}

/// The verdict on a window that follows one in which the replica came back from a long wait
/// (`came_back_before`: within [`windows_after_coming_back`] windows of it): starved again,
/// however it ran. What a replica runs right after a CPU held from it for tens of ms is that
/// CPU's backlog, not its round, and it can outlast a window: the hog test once saw a replica
/// that came back, then "ran 124 µs (of 123 µs on its clock) and waited 0 µs" in the next
/// window and answered 121 µs after that deadline; on the AMD host of docs/results.md (stop
/// 42) one "ran 71 µs (of 70 µs on its clock) and waited 0 µs" a window later still. A
/// spinner that came back so is blamed that many windows later.
pub fn after_coming_back(verdict: Window, came_back_before: bool) -> Window {
    match verdict {
        Window::HadItsChance if came_back_before => Window::Starved,
        v => v,
    }
}

/// The verdict on a window that follows `starved_before` of windows found starved in a row
/// (by [`judge`], or passed over because the voter itself woke too late to look; zero: the
/// last one was neither): a replica that had its chance now, right after such a
/// stretch, has come back ([`Window::CameBack`]), as from a long wait for a CPU that ended in
/// this window, and its backlog gets the same windows ([`windows_after_coming_back`] of the
/// stretch). The kernel books a wait only for a replica the guest's scheduler kept off its
/// CPU; a replica whose vCPU the host took (steal time: to the guest it was running) or that
/// interrupts held books none, and comes back from milliseconds without a CPU with no wait to
/// show for them. Seen in the hog test on the AMD host (stop 49), long after its hogs: "after
/// its deadline was moved on 3000 µs for want of a CPU … ran 81 µs (of 237 µs on its clock)
/// and waited 30 µs", blamed, with its answer in the pipe 111 µs after the deadline.
pub fn after_starving(verdict: Window, starved_before: Duration) -> Window {
    match verdict {
        Window::HadItsChance if !starved_before.is_zero() => Window::CameBack,
        v => v,
    }
}

/// The verdict on a window in which reading the replica's task clock, at either look, waited
/// `held` for its CPU (see [`Sample`]): starved if that was a quarter of the window or more,
/// however it ran. A CPU the host takes from a replica leaves no trace the guest can read at
/// this scale (no wait is booked: to the guest the replica is running; its task clock counts
/// the stolen time as run; the steal the kernel books comes at its ticks, 4 ms apart, in
/// 10 ms units): only the interrupt that waits for that CPU shows it. Traced on the Intel host
/// (stop 61): a look's read of a replica's clock took 1030 µs, while the replica, on its CPU
/// the whole time to the guest, made no system call.
pub fn cpu_held(verdict: Window, held: Duration, window: Duration) -> Window {
    match verdict {
        Window::HadItsChance if held_long(held, window) => Window::Starved,
        v => v,
    }
}

/// Whether a clock read that waited `held` for the replica's CPU says that CPU was held from
/// it over a window of `window`: a quarter of it or more, as for a wait.
fn held_long(held: Duration, window: Duration) -> bool {
    held * 4 >= window
}

/// How many windows after the one it came back in a replica's run still counts as backlog:
/// one for every [`BACKLOG_SHARE`]th of its wait, at least one (a wait of 30 ms, the hog
/// test's, against a 200 µs window: five). `window` is the span the verdict was judged over:
/// the window, or longer when the voter itself came late to its look (then fewer, longer
/// windows). The backlog grows with the wait: 200–300 µs after
/// 30 ms on the Intel host of stop 40, longer on the AMD host, where every system call costs
/// three times as much. The round's extensions stay bounded by [`MAX_EXTENSION`].
pub fn windows_after_coming_back(waited: Duration, window: Duration) -> u32 {
    let backlog = waited / BACKLOG_SHARE;
    let window = window.max(MIN_WINDOW).as_nanos();
    let windows = backlog.as_nanos().div_ceil(window);
    u32::try_from(windows).unwrap_or(u32::MAX).max(1)
}

/// The part of a long wait for a CPU that a replica may spend, once back, on that CPU's
/// backlog before its lateness is its own again (see [`windows_after_coming_back`]).
pub const BACKLOG_SHARE: u32 = 30;

/// The rule of the module's comment, from the samples at both ends of a window of `window`,
/// of which the replica's clock was read over `clocked` (from its first sample to its
/// second); `runnable` tells whether the replica is waiting for a CPU now (read only when it
/// ran less than a quarter of that: a spinning replica costs no extra read).
pub fn judge(
    before: SchedTimes,
    after: SchedTimes,
    window: Duration,
    clocked: Duration,
    runnable: impl FnOnce() -> bool,
) -> Window {
    let ran = u128::from(after.run_ns.saturating_sub(before.run_ns));
    let waited = u128::from(after.wait_ns.saturating_sub(before.wait_ns));
    let w = window.as_nanos();
    // Over a very short clock span the share run says little (a replica preempted just
    // after it got its CPU): at least half the window.
    let clocked = clocked.as_nanos().clamp(w / 2, w);
    // A wait longer than the whole window ended inside it: the replica has just got its CPU
    // back, and what it ran since is the backlog of a CPU held for that long, not a round's
    // work (measured: a replica kept off its CPU for 30 ms then ran 200–300 µs without
    // answering; a stateful echo answers in well under 50 µs). It gets a window of its own.
    let came_back = waited >= w;
    let kept_waiting = ran * 4 < w && waited * 4 >= w;
    // More run than twice the window (a read's own time, µs, can add a little to a spinner's
    // run, never a window): one sample was not the replica's time at the moment it was read
    // (measured: "in the last 211 µs it ran 2816 µs (of 211 µs on its clock)", the hog test,
    // stop 59). Such a pair says nothing of what the replica did in the window; whether it is
    // waiting for a CPU now does.
    let booked_late = ran > 2 * w;
    if came_back {
        Window::CameBack
    } else if kept_waiting || ((ran * 4 < clocked || booked_late) && runnable()) {
        Window::Starved
    } else {
        Window::HadItsChance
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const W: Duration = Duration::from_micros(200);

    fn t(run_us: u64, wait_us: u64) -> SchedTimes {
        SchedTimes {
            run_ns: run_us * 1000,
            wait_ns: wait_us * 1000,
        }
    }

    const RUNNABLE: fn() -> bool = || true;
    const ASLEEP: fn() -> bool = || false;

    #[test]
    fn a_spinning_replica_had_its_chance() {
        assert_eq!(
            judge(t(50, 10), t(245, 15), W, W, RUNNABLE),
            Window::HadItsChance
        );
    }

    #[test]
    fn a_stopped_or_sleeping_replica_had_its_chance() {
        // Neither ran nor waited, and is not runnable: SIGSTOP, a blocking read, a deadlock.
        assert_eq!(
            judge(t(50, 10), t(50, 10), W, W, ASLEEP),
            Window::HadItsChance
        );
    }

    #[test]
    fn a_replica_kept_off_its_cpu_was_starved() {
        // Kept off its CPU for the whole window and still waiting: no wait is booked yet.
        assert_eq!(judge(t(50, 10), t(50, 10), W, W, RUNNABLE), Window::Starved);
        // Throttled for the whole window, then ran a little just now: the wait is booked,
        // and it came back.
        assert_eq!(judge(t(50, 10), t(60, 210), W, W, ASLEEP), Window::CameBack);
        // Ran a little, waited most.
        assert_eq!(judge(t(50, 10), t(90, 140), W, W, ASLEEP), Window::Starved);
    }

    #[test]
    fn a_spinner_whose_clock_opened_late_in_the_window_had_its_chance() {
        // Measured: the first look's open took most of the window; the clock then saw 60 µs,
        // and the replica, running on another CPU (state R), ran 48 of them.
        let clocked = Duration::from_micros(60);
        assert_eq!(
            judge(t(20, 100), t(68, 100), W, clocked, RUNNABLE),
            Window::HadItsChance
        );
        // Kept off its CPU over the whole of its clock's span: starved.
        assert_eq!(
            judge(t(20, 100), t(25, 100), W, clocked, RUNNABLE),
            Window::Starved
        );
    }

    #[test]
    fn a_window_whose_clock_read_waited_for_the_cpu_is_starved() {
        // Traced (stop 61): a look's read of a replica's clock waited 1030 µs for the CPU the
        // replica was on, which the host had taken; to the guest the replica ran.
        let held = Duration::from_micros(1030);
        assert_eq!(cpu_held(Window::HadItsChance, held, W), Window::Starved);
        // An interrupt's ordinary latency decides nothing.
        let quick = Duration::from_micros(20);
        assert_eq!(
            cpu_held(Window::HadItsChance, quick, W),
            Window::HadItsChance
        );
        // A quarter of the window is the bound, as for a wait.
        assert_eq!(cpu_held(Window::HadItsChance, W / 4, W), Window::Starved);
        // A verdict that already moves the deadline on stays what it is.
        assert_eq!(cpu_held(Window::CameBack, held, W), Window::CameBack);
    }

    #[test]
    fn a_voter_that_took_its_look_a_window_late_was_held_up() {
        // Kept in docs/results/stop65: "in the last 203 µs it ran …" at a 2 ms deadline
        // (window 200 µs, looks due 150 µs apart): the second look came 53 µs late; and
        // stop 64's worst, "in the last 8171 µs": 8 ms late.
        let window = window(Duration::from_micros(2000));
        assert!(voter_held_up(Duration::from_micros(8021), window));
        // This VM's ordinary lateness for a look (48–126 µs, traced) decides nothing.
        assert!(!voter_held_up(Duration::from_micros(126), window));
        assert!(!voter_held_up(window - Duration::from_micros(1), window));
        assert!(voter_held_up(window, window));
    }

    #[test]
    fn a_clock_span_shorter_than_half_the_window_counts_as_half() {
        // Its clock read over 60 µs of 200: it ran 20 µs, then lost its CPU and waits.
        let clocked = Duration::from_micros(60);
        assert_eq!(
            judge(t(0, 0), t(20, 0), W, clocked, RUNNABLE),
            Window::Starved
        );
    }

    #[test]
    fn a_replica_back_on_its_cpu_after_a_long_wait_is_starved_by_its_wait() {
        // CI, 24e10d2: "in the last 55 µs it ran 23 µs and waited 4926 µs for a CPU".
        let clocked = Duration::from_micros(55);
        assert_eq!(
            judge(t(0, 0), t(23, 4926), W, clocked, ASLEEP),
            Window::CameBack
        );
    }

    #[test]
    fn a_replica_back_from_a_wait_longer_than_the_window_gets_a_window_of_its_own() {
        // Measured (the hog test): "in the last 361 µs it ran 198 µs (of 257 µs on its clock)
        // and waited 30150 µs for a CPU".
        let w = Duration::from_micros(361);
        let clocked = Duration::from_micros(257);
        assert_eq!(
            judge(t(0, 0), t(198, 30150), w, clocked, ASLEEP),
            Window::CameBack
        );
        assert!(Window::CameBack.starved());
        // The next window, running all of it: starved once more after coming back ...
        let next = judge(t(198, 30150), t(450, 30150), w, w, RUNNABLE);
        assert_eq!(next, Window::HadItsChance);
        assert_eq!(after_coming_back(next, true), Window::Starved);
        // ... and blamed the window after, spinning on.
        assert_eq!(after_coming_back(next, false), Window::HadItsChance);
        // What starved or came back stays so.
        assert_eq!(after_coming_back(Window::CameBack, true), Window::CameBack);
        assert_eq!(after_coming_back(Window::Starved, false), Window::Starved);
    }

    #[test]
    fn a_replica_back_from_windows_starved_without_a_booked_wait_has_come_back() {
        // Measured (the hog test, stop 49): fifteen windows in which the replica ran nothing
        // while runnable (its vCPU taken, no wait booked), then "in the last 243 µs it ran
        // 81 µs (of 237 µs on its clock) and waited 30 µs for a CPU": blamed before, with its
        // answer 111 µs after the deadline.
        let w = Duration::from_micros(243);
        let own = judge(t(0, 0), t(81, 30), w, Duration::from_micros(237), RUNNABLE);
        assert_eq!(own, Window::HadItsChance);
        let stretch = Duration::from_micros(3000);
        assert_eq!(after_starving(own, stretch), Window::CameBack);
        // Its backlog: a thirtieth of the stretch, at least one window more.
        assert_eq!(windows_after_coming_back(stretch, w), 1);
        // Not after a window that was not starved ...
        assert_eq!(after_starving(own, Duration::ZERO), Window::HadItsChance);
        // ... and what is starved stays so.
        assert_eq!(after_starving(Window::Starved, stretch), Window::Starved);
        assert_eq!(after_starving(Window::CameBack, stretch), Window::CameBack);
    }

    #[test]
    fn the_backlog_after_a_long_wait_counts_in_proportion_to_it() {
        let w = Duration::from_micros(200);
        // The hog test's 30 ms: a thirtieth is 1 ms, five windows.
        assert_eq!(windows_after_coming_back(Duration::from_millis(30), w), 5);
        // A wait just over a window still gets one.
        assert_eq!(windows_after_coming_back(Duration::from_micros(250), w), 1);
        assert_eq!(windows_after_coming_back(Duration::ZERO, w), 1);
        // Real-time throttling's 50 ms against a 2 ms deadline's 200 µs window: 9.
        assert_eq!(windows_after_coming_back(Duration::from_millis(50), w), 9);
    }

    #[test]
    fn more_run_than_the_window_says_nothing_of_it_and_the_state_tells() {
        // Measured (the hog test, stop 59): "in the last 211 µs it ran 2816 µs (of 211 µs on
        // its clock) and waited 0 µs for a CPU", blamed while the hog held its CPU. Runnable,
        // it is starved; asleep or stopped, its lateness is its own; and a spinner whose
        // second read came a little late ran a little more than the window: blamed as before.
        let w = Duration::from_micros(211);
        for (ran_us, runnable, verdict) in [
            (2816, RUNNABLE, Window::Starved),
            (2816, ASLEEP, Window::HadItsChance),
            (240, RUNNABLE, Window::HadItsChance),
        ] {
            let seen = judge(t(0, 0), t(ran_us, 0), w, w, runnable);
            assert_eq!(seen, verdict, "ran {ran_us} µs, runnable: {}", runnable());
        }
    }

    #[test]
    fn a_quarter_of_the_window_on_a_cpu_is_a_chance_even_if_it_also_waited() {
        assert_eq!(
            judge(t(0, 0), t(100, 100), W, W, RUNNABLE),
            Window::HadItsChance
        );
    }

    #[test]
    fn schedstat_parses_and_this_process_reads() {
        let parsed = SchedTimes::parse("123 456 7\n");
        assert_eq!(
            parsed,
            Some(SchedTimes {
                run_ns: 123,
                wait_ns: 456
            })
        );
        assert_eq!(SchedTimes::parse("garbage"), None);
        let mut child = std::process::Command::new("sh")
            .args(["-c", "while :; do :; done"])
            .spawn()
            .unwrap();
        let stat = SchedStat::new(child.id() as libc::pid_t);
        let a = stat.read();
        std::thread::sleep(Duration::from_millis(5));
        let b = stat.read();
        // Reaped before anything can fail.
        child.kill().unwrap();
        child.wait().unwrap();
        let (a, b) = (a.expect("readable").times, b.expect("readable").times);
        assert!(b.run_ns > a.run_ns, "{a:?} {b:?}");
    }

    #[test]
    fn the_evidence_says_that_a_runnable_replica_s_wait_is_not_counted_yet() {
        // Kept off its CPU for the whole window: no wait booked, since the wait has not ended.
        let seen = Seen {
            state: Some('R'),
            ..Seen::between(t(0, 0), t(0, 0), W, W)
        };
        assert_eq!(
            seen.to_string(),
            "in the last 200 µs it ran 0 µs (of 200 µs on its clock) and waited 0 µs for a \
             CPU; state R (runnable: a wait for a CPU is counted only when it ends)"
        );
    }

    #[test]
    fn the_evidence_says_when_the_run_is_only_what_the_kernel_booked() {
        let seen = Seen {
            on_clock: false,
            state: Some('R'),
            ..Seen::between(t(0, 0), t(2816, 0), W, W)
        };
        assert_eq!(
            seen.to_string(),
            "in the last 200 µs it ran 2816 µs (of 200 µs as the kernel booked it, at its \
             ticks: no task clock) and waited 0 µs for a CPU; state R (runnable: a wait for a \
             CPU is counted only when it ends)"
        );
    }

    #[test]
    fn the_evidence_says_where_an_asleep_replica_waits() {
        let seen = Seen {
            state: Some('S'),
            wchan: Some(replica_rt::sys::Wchan::new("pipe_read")),
            ..Seen::between(t(0, 0), t(16, 0), W, W)
        };
        assert_eq!(
            seen.to_string(),
            "in the last 200 µs it ran 16 µs (of 200 µs on its clock) and waited 0 µs for a \
             CPU; state S, asleep in pipe_read"
        );
        // A child of ours asleep: the kernel names where (this crate's tests run as the
        // child's owner, who may read it).
        let mut sleeper = crate::test_support::Sleeper::start();
        let pid = sleeper.pid();
        let mut wchan = None;
        for _ in 0..100 {
            std::thread::sleep(Duration::from_millis(10));
            wchan = replica_rt::sys::wchan(pid);
            if wchan.is_some() {
                break;
            }
        }
        sleeper.0.kill().unwrap();
        sleeper.0.wait().unwrap();
        let wchan = wchan.expect("a sleeping child's /proc/PID/wchan names a function");
        assert!(
            wchan.as_str().contains("sleep"),
            "sleep(1) sleeps in {wchan:?}"
        );
    }

    #[test]
    fn the_window_is_a_tenth_of_the_timeout_within_bounds() {
        assert_eq!(window(Duration::from_millis(2)), Duration::from_micros(200));
        assert_eq!(
            window(Duration::from_micros(500)),
            Duration::from_micros(100)
        );
        assert_eq!(window(Duration::from_micros(50)), Duration::from_micros(50));
    }
}
