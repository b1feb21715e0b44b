//! The scheduling wrappers of `sys`, on a real child process (`sleep`), read back from the
//! kernel. SCHED_RR is checked where this process may grant it (root, CAP_SYS_NICE); else the
//! refusal itself is checked.

use std::process::{Child, Command};

use replica_rt::sys;

/// A `sleep` child, killed and reaped on drop (also when the test fails).
struct Sleeper(Child);

impl Sleeper {
    fn start() -> Sleeper {
        Sleeper(
            Command::new("sleep")
                .arg("30")
                .spawn()
                .expect("spawning sleep"),
        )
    }
    fn pid(&self) -> i32 {
        self.0.id() as i32
    }
}

impl Drop for Sleeper {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

#[test]
fn affinity_is_set_and_read_back() {
    let child = Sleeper::start();
    let mine = sys::cpu_affinity(0).unwrap();
    assert!(!mine.is_empty());
    let last = *mine.last().unwrap();
    sys::set_cpu_affinity(child.pid(), &[last]).unwrap();
    assert_eq!(sys::cpu_affinity(child.pid()).unwrap(), [last]);
    sys::set_cpu_affinity(child.pid(), &mine).unwrap();
    assert_eq!(sys::cpu_affinity(child.pid()).unwrap(), mine);
}

#[test]
fn nice_value_goes_up_and_reads_back() {
    let child = Sleeper::start();
    let base = sys::nice_of(child.pid()).unwrap();
    let weaker = (base + 3).min(19);
    sys::set_nice(child.pid(), weaker).unwrap();
    assert_eq!(sys::nice_of(child.pid()).unwrap(), weaker);
}

#[test]
fn round_robin_is_granted_or_refused_with_eperm() {
    let child = Sleeper::start();
    let pid = child.pid();
    assert!(!sys::sched_policy(pid).unwrap().is_round_robin());
    match sys::set_round_robin(pid, 10) {
        Ok(()) => {
            let p = sys::sched_policy(pid).unwrap();
            assert!(p.is_round_robin(), "{p:?}");
            assert_eq!(p.priority, 10);
            sys::set_rt_priority(pid, 12).unwrap();
            assert_eq!(sys::sched_policy(pid).unwrap().priority, 12);
            sys::set_normal_policy(pid).unwrap();
            let p = sys::sched_policy(pid).unwrap();
            assert_eq!((p.policy, p.priority), (libc::SCHED_OTHER, 0));
        }
        Err(e) => {
            eprintln!("SCHED_RR refused here ({e}); checking the refusal only");
            assert_eq!(e.raw_os_error(), Some(libc::EPERM), "{e}");
        }
    }
}

/// A process whose policy carries `SCHED_RESET_ON_FORK` (`chrt -R`) reads as SCHED_RR, not as
/// the flag's bit OR'ed into it.
#[test]
fn round_robin_with_reset_on_fork_reads_as_round_robin() {
    let child = Sleeper::start();
    let pid = child.pid();
    let param = libc::sched_param { sched_priority: 10 };
    // SAFETY: `param` is a valid sched_param that the kernel reads during the call only.
    let r = unsafe {
        libc::sched_setscheduler(pid, libc::SCHED_RR | libc::SCHED_RESET_ON_FORK, &param)
    };
    if r != 0 {
        let e = std::io::Error::last_os_error();
        eprintln!("SCHED_RR refused here ({e}); checking the refusal only");
        assert_eq!(e.raw_os_error(), Some(libc::EPERM), "{e}");
        return;
    }
    let p = sys::sched_policy(pid).unwrap();
    assert!(p.is_round_robin(), "{p:?}");
    assert_eq!((p.policy, p.priority), (libc::SCHED_RR, 10));
}

#[test]
fn a_gone_process_is_esrch() {
    let mut child = Sleeper::start();
    let pid = child.pid();
    child.0.kill().unwrap();
    child.0.wait().unwrap();
    let e = sys::set_cpu_affinity(pid, &[0]).unwrap_err();
    assert_eq!(e.raw_os_error(), Some(libc::ESRCH), "{e}");
    let e = sys::set_round_robin(pid, 1).unwrap_err();
    assert_eq!(e.raw_os_error(), Some(libc::ESRCH), "{e}");
}
