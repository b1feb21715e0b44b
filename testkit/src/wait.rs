//! Bounded waits on observable state, instead of fixed sleeps: a test that needs the system to
//! be in some state polls for that state (a process's `/proc` state, a file, the event log) and
//! fails, naming what it waited for, when it does not come in time.

use std::time::{Duration, Instant};

/// How often the waits here look again.
pub const POLL: Duration = Duration::from_millis(2);

/// Polls `probe` every [`POLL`] until it returns `Some`, and returns that value. Panics with
/// `what` (and how long it waited) if it has not within `timeout`. `probe` is called at least
/// once, also with a zero timeout.
pub fn wait_until<T>(what: &str, timeout: Duration, mut probe: impl FnMut() -> Option<T>) -> T {
    let deadline = Instant::now() + timeout;
    loop {
        if let Some(v) = probe() {
            return v;
        }
        assert!(
            Instant::now() < deadline,
            "timed out after {timeout:?} waiting for {what}"
        );
        std::thread::sleep(POLL);
    }
}

/// What `/proc` says about how a process has been running: time on a CPU (`schedstat`),
/// voluntary context switches (`status`: it blocked) and its state letter (`stat`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RunSample {
    pub cpu_ns: u64,
    pub blocked: u64,
    pub state: char,
}

impl RunSample {
    /// `None` if the process is gone.
    pub fn take(pid: i32) -> Option<RunSample> {
        Some(RunSample {
            cpu_ns: crate::procs::cpu_time_ns(pid)?,
            blocked: crate::procs::voluntary_switches(pid)?,
            state: replica_rt::sys::process_state(pid)?,
        })
    }
}

/// Whether `pid` spins over `window`: running at both ends, it never blocked in between, and it
/// was on a CPU for at least a tenth of the window (a loaded machine shares the CPUs). (A healthy replica waits for its input within
/// microseconds of getting it; one that took a control-flow injection never waits again.)
/// `false` if the process is gone.
pub fn spins_over(pid: i32, window: Duration) -> bool {
    let Some(a) = RunSample::take(pid) else {
        return false;
    };
    std::thread::sleep(window);
    let Some(b) = RunSample::take(pid) else {
        return false;
    };
    let ran = b.cpu_ns.saturating_sub(a.cpu_ns);
    a.state == 'R'
        && b.state == 'R'
        && a.blocked == b.blocked
        && u128::from(ran) * 10 >= window.as_nanos()
}

/// Waits (at most `timeout`) until `pid` spins (see [`spins_over`], 50 ms windows): after a
/// control-flow injection, the proof that the replica took the signal.
pub fn wait_spinning(pid: i32, timeout: Duration) {
    wait_until(&format!("pid {pid} to spin"), timeout, || {
        spins_over(pid, Duration::from_millis(50)).then_some(())
    });
}

/// Waits (at most `timeout`) until `pid`'s state letter (`/proc/PID/stat`) is one of `states`
/// (e.g. "T" stopped, "S" asleep); returns it. Panics if the process is gone.
pub fn wait_state(pid: i32, states: &str, timeout: Duration) -> char {
    wait_until(
        &format!("pid {pid} to be in a state of {states:?}"),
        timeout,
        || {
            let s = replica_rt::sys::process_state(pid)
                .unwrap_or_else(|| panic!("pid {pid} is gone (waiting for state {states:?})"));
            states.contains(s).then_some(s)
        },
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wait_until_returns_the_first_value() {
        let mut n = 0;
        let v = wait_until("n to reach 3", Duration::from_secs(5), || {
            n += 1;
            (n >= 3).then_some(n * 10)
        });
        assert_eq!(v, 30);
    }

    #[test]
    #[should_panic(expected = "timed out after 10ms waiting for nothing")]
    fn wait_until_names_what_did_not_come() {
        wait_until::<()>("nothing", Duration::from_millis(10), || None);
    }

    /// Kills and reaps the child on drop, also when the test panics.
    struct Reaped(std::process::Child);

    impl Drop for Reaped {
        fn drop(&mut self) {
            let _ = self.0.kill();
            let _ = self.0.wait();
        }
    }

    fn spawn(program: &str, args: &[&str]) -> Reaped {
        Reaped(
            std::process::Command::new(program)
                .args(args)
                .spawn()
                .unwrap(),
        )
    }

    #[test]
    fn a_sleeping_process_does_not_spin_and_a_busy_loop_does() {
        let sleeper = spawn("sleep", &["30"]);
        let pid = sleeper.0.id() as i32;
        assert_eq!(wait_state(pid, "S", Duration::from_secs(10)), 'S');
        assert!(!spins_over(pid, Duration::from_millis(20)));
        let busy = spawn("sh", &["-c", "while :; do :; done"]);
        wait_spinning(busy.0.id() as i32, Duration::from_secs(20));
    }
}
