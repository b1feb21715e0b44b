//! The fault kinds and how each one is delivered to one process.
//!
//! An [`Action`] is decided completely in advance by the schedule (which bit, which bytes,
//! which seed); [`fire`] only delivers it. That is what makes a campaign reproducible: the same
//! seed gives the same actions, whatever the timing of the run.

use thiserror::Error;

use replica_rt::contract::signals::{self, VarRequest};

pub use s3res_protocol::campaign::{Action, FaultKind, RegOptions};

#[derive(Debug, Error)]
pub enum FireError {
    /// The target is gone (ESRCH): it died or was replaced before the instant came.
    #[error("process {0} no longer exists")]
    Gone(i32),
    #[error("cannot signal process {pid}: {source}")]
    Signal { pid: i32, source: std::io::Error },
    #[error("variable flip at offset {offset} is beyond what the hook can address ({max})")]
    OffsetTooLarge { offset: u32, max: u32 },
    #[error("register injection: {0}")]
    Reg(#[from] s3res_regflip::RegFlipError),
    #[error("register injection: {0}")]
    RegOptions(String),
    #[error(
        "register injection: process {pid} was not seen running outside a system call, nor did \
         a system call of it return, within {patience_ms} ms ({attempts} attempts; a process \
         blocked in a system call has its registers in kernel memory, not in the CPU)"
    )]
    RegAlwaysInSyscall {
        pid: i32,
        attempts: u32,
        patience_ms: u64,
    },
    #[error(
        "process {pid} does not catch signal {signal} within {patience_ms} ms: no s3res runtime \
         installed its injection hooks (not a replica-rt program, or its init never came); \
         the signal was not sent, as its default action would kill it"
    )]
    NoHook {
        pid: i32,
        signal: i32,
        patience_ms: u64,
    },
}

/// How long a signal injection waits for its target to catch the signal. replica-rt's `init`
/// installs the hooks; a target signalled before that dies of the signal's default action, and
/// the campaign would count a `crash` that depends only on how soon after its start the
/// injection came (`inject/tests/classify.rs` saw one run classify `sdc` and the next `crash`
/// for one schedule).
const HOOK_PATIENCE: std::time::Duration = std::time::Duration::from_secs(1);
/// How often a target is looked at while the injection waits for its hook.
const HOOK_POLL: std::time::Duration = std::time::Duration::from_millis(1);

/// How long a register flip waits for its target to be seen running: a component waiting on
/// its input spends most of its time blocked in a system call, with its registers in kernel
/// memory. The flip lands at the first instant within this time at which the target is seen
/// running. A component that runs only in short bursts may never be seen so (a C filter that
/// adds one number per frame): then the flip follows it out of its next system call instead
/// (see [`REG_FOLLOW_PATIENCE`]).
const REG_PATIENCE: std::time::Duration = std::time::Duration::from_millis(200);
/// How long a flip that follows its target to a system call's return waits for one.
const REG_FOLLOW_PATIENCE: std::time::Duration = std::time::Duration::from_secs(1);
/// At most this many instructions after that return are single-stepped before the flip
/// (drawn uniformly): the instant falls in the component's burst, not always on the first
/// instruction after the call.
const REG_FOLLOW_SKIP: u32 = 64;
/// How often the target's state is looked at meanwhile (`/proc/PID/stat`, no ptrace): only a
/// target seen running (`R`) is stopped for an attempt. Stopping a blocked target every 500 µs
/// instead (the way before) held a robot's navigator, which runs for about 1 % of the time,
/// through ~2,000 stops over more than a second, and its voter rightly called that a hang.
const REG_POLL: std::time::Duration = std::time::Duration::from_micros(50);

/// The register injector's spec from `reg`'s options, or a clear error naming the bad option.
pub fn reg_spec(reg: &RegOptions) -> Result<s3res_regflip::RegFlipSpec, FireError> {
    let role = match reg.role.as_str() {
        "" => s3res_regflip::OperandRole::Any,
        r => r
            .parse()
            .map_err(|e| FireError::RegOptions(format!("--reg-role {r}: {e}")))?,
    };
    let field = match reg.field.as_str() {
        "" => s3res_regflip::FloatField::Whole,
        f => f
            .parse()
            .map_err(|e| FireError::RegOptions(format!("--reg-field {f}: {e}")))?,
    };
    Ok(s3res_regflip::RegFlipSpec {
        role,
        bits: reg.bits,
        field,
        registers: reg.registers.clone(),
        ..Default::default()
    })
}

/// The register options checked as a whole before anything is injected (the same refusal
/// every injection would meet: `--reg-bits 0`, a field narrower than the flip, an unknown
/// register), naming the option.
pub fn check_reg_options(reg: &RegOptions) -> Result<(), FireError> {
    let spec = reg_spec(reg)?;
    s3res_regflip::check_spec(&spec).map_err(|e| match e {
        s3res_regflip::RegFlipError::InvalidSpec(why) => {
            FireError::RegOptions(format!("--reg-{}", why.replacen(" = ", " ", 1)))
        }
        other => FireError::Reg(other),
    })
}

/// When an injection happened: for a register flip, when the injector says it flipped (it
/// waits for its target to run, up to a second); for the rest, `asked` (just before the
/// signal). Every log that records an injection uses this: a storm's and a one-off `inject`'s
/// said when the register injector began to wait, up to 200 ms early.
pub fn injected_at(asked: u64, injector: Option<&serde_json::Value>) -> u64 {
    injector
        .and_then(|r| r.get("time_ns"))
        .and_then(serde_json::Value::as_u64)
        .unwrap_or(asked)
}

/// Whether this build can deliver `kind` (checked before a campaign starts, so that a kind
/// that cannot be delivered is one clear error, not N runs of missed injections).
pub fn check_available(kind: FaultKind) -> Result<(), FireError> {
    match kind {
        // ptrace register access is implemented for x86-64 Linux only.
        FaultKind::Reg if !cfg!(all(target_os = "linux", target_arch = "x86_64")) => {
            Err(FireError::Reg(s3res_regflip::RegFlipError::Unsupported))
        }
        _ => Ok(()),
    }
}

/// Delivers `action` to `pid`. Returns what the injector itself reports (for `reg`), else
/// `None`.
pub fn fire(
    action: &Action,
    pid: i32,
    reg: &RegOptions,
) -> Result<Option<serde_json::Value>, FireError> {
    let check = |r: std::io::Result<()>| match r {
        Ok(()) => Ok(()),
        Err(e) if e.raw_os_error() == Some(libc::ESRCH) => Err(FireError::Gone(pid)),
        Err(source) => Err(FireError::Signal { pid, source }),
    };
    // kill(0) is our own process group, kill(-1) every process we may signal: never a target.
    if pid <= 0 {
        return Err(FireError::Signal {
            pid,
            source: std::io::Error::from_raw_os_error(libc::EINVAL),
        });
    }
    let hook = match action {
        Action::Sdc { .. } => Some(signals::INJECT_SDC),
        Action::Cfe => Some(signals::inject_cfe()),
        Action::Var { .. } => Some(signals::inject_var()),
        Action::Exec | Action::Reg { .. } => None,
    };
    let waited = match hook {
        Some(signal) => wait_for_hook(pid, signal)?,
        None => None,
    };
    match action {
        Action::Exec => check(replica_rt::sys::kill(pid, libc::SIGKILL))?,
        Action::Sdc { value } => check(replica_rt::sys::sigqueue(
            pid,
            signals::INJECT_SDC,
            (*value & i32::MAX as u32) as i32,
        ))?,
        Action::Cfe => check(replica_rt::sys::kill(pid, signals::inject_cfe()))?,
        Action::Var { offset, bits } => {
            for req in VarRequest::for_bits(*offset, bits) {
                let value = req.to_value().ok_or(FireError::OffsetTooLarge {
                    offset: req.offset,
                    max: VarRequest::MAX_OFFSET,
                })?;
                check(replica_rt::sys::sigqueue(pid, signals::inject_var(), value))?;
            }
        }
        Action::Reg { seed } => return fire_reg(pid, *seed, reg).map(Some),
    }
    // An injection that had to wait for its hook happened when it was sent, not when it was
    // due (the campaign records `time_ns` as the injection's time, as for a register flip).
    Ok(waited.map(|waited| {
        serde_json::json!({
            "time_ns": replica_rt::sys::monotonic_ns(),
            "hook_waited_us": waited.as_micros() as u64,
        })
    }))
}

/// Waits until `pid` catches `signal` (its runtime installed the hook: see [`HOOK_PATIENCE`]);
/// how long it waited, if it had to.
fn wait_for_hook(pid: i32, signal: i32) -> Result<Option<std::time::Duration>, FireError> {
    let started = std::time::Instant::now();
    let deadline = started + HOOK_PATIENCE;
    loop {
        let caught = replica_rt::sys::caught_signals(pid)
            .map(|mask| mask & replica_rt::sys::signal_bit(signal) != 0);
        match caught {
            None => return Err(FireError::Gone(pid)),
            Some(true) if started.elapsed() < HOOK_POLL => return Ok(None),
            Some(true) => return Ok(Some(started.elapsed())),
            Some(false) if std::time::Instant::now() >= deadline => {
                return Err(FireError::NoHook {
                    pid,
                    signal,
                    patience_ms: HOOK_PATIENCE.as_millis() as u64,
                })
            }
            Some(false) => std::thread::sleep(HOOK_POLL),
        }
    }
}

/// One register flip into `pid` (s3res-regflip), the register and bits drawn from `seed`. A
/// target blocked in a system call has its registers in kernel memory: the flip waits (up to
/// [`REG_PATIENCE`]) until the target is seen running, so that it lands while the component
/// computes, and stops the target only then; a target never seen so is followed out of its
/// next system call instead (up to [`REG_FOLLOW_PATIENCE`]). Returns the injector's record,
/// with the seed, the attempts (stops), the looks at its state and how long it waited.
fn fire_reg(pid: i32, seed: u64, reg: &RegOptions) -> Result<serde_json::Value, FireError> {
    use rand::SeedableRng;
    use s3res_regflip::RegFlipError;
    let spec = reg_spec(reg)?;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let started = std::time::Instant::now();
    let mut attempts = 0u32;
    let mut looks = 0u64;
    loop {
        looks += 1;
        match replica_rt::sys::process_state(pid) {
            // Dead and reaped, or a zombie: nothing runs there any more.
            Some('Z' | 'X') => return Err(FireError::Gone(pid)),
            None if matches!(replica_rt::sys::kill(pid, 0),
                Err(e) if e.raw_os_error() == Some(libc::ESRCH)) =>
            {
                return Err(FireError::Gone(pid))
            }
            // `/proc` did not say, but the process is there: stop it and see (as before this
            // look existed).
            None | Some('R') => {
                attempts += 1;
                match s3res_regflip::inject(pid, &spec, &mut rng) {
                    Ok(record) => return with_wait(record, seed, attempts, looks, started),
                    // It blocked again between the look and the stop.
                    Err(RegFlipError::InSyscall { .. }) => {}
                    Err(RegFlipError::Gone { .. }) => return Err(FireError::Gone(pid)),
                    Err(e) => return Err(e.into()),
                }
            }
            // Asleep or stopped: not running its code now.
            Some(_) => {}
        }
        if started.elapsed() >= REG_PATIENCE {
            break;
        }
        std::thread::sleep(REG_POLL);
    }
    // Never seen running between its system calls: follow it out of the next one.
    attempts += 1;
    match s3res_regflip::inject_after_syscall(
        pid,
        &spec,
        &mut rng,
        REG_FOLLOW_PATIENCE,
        REG_FOLLOW_SKIP,
    ) {
        Ok(record) => with_wait(record, seed, attempts, looks, started),
        Err(RegFlipError::InSyscall { .. }) => Err(FireError::RegAlwaysInSyscall {
            pid,
            attempts,
            patience_ms: (REG_PATIENCE + REG_FOLLOW_PATIENCE).as_millis() as u64,
        }),
        Err(RegFlipError::Gone { .. }) => Err(FireError::Gone(pid)),
        Err(e) => Err(e.into()),
    }
}

/// The injector's record as JSON, with the seed, the attempts (stops), the looks at the
/// target's state and how long the flip waited.
fn with_wait(
    mut record: s3res_regflip::RegFlipRecord,
    seed: u64,
    attempts: u32,
    looks: u64,
    started: std::time::Instant,
) -> Result<serde_json::Value, FireError> {
    record.seed = Some(seed);
    let mut value = serde_json::to_value(&record)
        .map_err(|e| FireError::RegOptions(format!("cannot serialise the record: {e}")))?;
    if let Some(obj) = value.as_object_mut() {
        obj.insert("attempts".to_owned(), attempts.into());
        obj.insert("looks".to_owned(), looks.into());
        obj.insert(
            "waited_us".to_owned(),
            (started.elapsed().as_micros() as u64).into(),
        );
    }
    Ok(value)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An injection happened when the register injector says it flipped, else when asked.
    #[test]
    fn an_injection_happened_when_the_injector_says_it_flipped() {
        let flip = serde_json::json!({"time_ns": 7});
        assert_eq!(injected_at(3, Some(&flip)), 7);
        assert_eq!(injected_at(3, Some(&serde_json::json!({}))), 3);
        assert_eq!(injected_at(3, None), 3);
    }

    /// A target without the hooks (a plain program) is not signalled: the default action of
    /// the injection signals would kill it, and a campaign would count a crash.
    #[test]
    fn a_signal_injection_never_kills_a_target_without_its_hook() {
        let mut child = std::process::Command::new("sleep")
            .arg("30")
            .spawn()
            .expect("spawn sleep");
        let pid = child.id() as i32;
        let err = fire(&Action::Sdc { value: 1 }, pid, &RegOptions::default()).unwrap_err();
        assert!(matches!(err, FireError::NoHook { .. }), "{err}");
        assert!(
            child.try_wait().unwrap().is_none(),
            "the target was killed by the injection signal"
        );
        child.kill().unwrap();
        child.wait().unwrap();
    }

    #[test]
    fn actions_serialise_with_their_kind() {
        let a = Action::Var {
            offset: 8,
            bits: vec![63],
        };
        let v = serde_json::to_value(&a).unwrap();
        assert_eq!(v["kind"], "var");
        assert_eq!(v["offset"], 8);
        assert_eq!(serde_json::from_value::<Action>(v).unwrap(), a);
        assert_eq!(a.kind(), FaultKind::Var);
    }

    /// Found by fuzzing the live-view reader: a pid of 0 or -1 reached `kill`, which takes
    /// them as the injector's own process group and as every process it may signal.
    #[test]
    fn a_pid_that_is_no_process_is_never_signalled() {
        for pid in [0, -1, i32::MIN] {
            for action in [Action::Exec, Action::Cfe, Action::Sdc { value: 3 }] {
                let e = fire(&action, pid, &RegOptions::default()).unwrap_err();
                assert!(
                    matches!(e, FireError::Signal { pid: p, .. } if p == pid),
                    "{e}"
                );
            }
        }
    }
}
