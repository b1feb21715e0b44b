//! MAVFI-style register bit-flip injection into a running Linux thread, by ptrace.
//!
//! [`inject`] stops one thread of a process (PTRACE_SEIZE, PTRACE_INTERRUPT, `waitpid`), reads
//! its registers, decodes the instruction at the instruction pointer with iced-x86 (up to the 15
//! bytes an x86 instruction may have, fewer at the end of a mapping), and lists the registers
//! that instruction reads (source) and writes (destination). It picks one of them with the
//! caller's random generator, flips `bits` distinct bits anywhere in that operand's width (or
//! only in one field of an IEEE-754 binary64 value), writes the register back and detaches.
//! A destination is flipped after single-stepping the instruction, so its write has happened;
//! a source is flipped before the instruction runs. Everything about the injection is returned
//! as a [`RegFlipRecord`]. The caller chooses the instant (it calls `inject` then) and owns the
//! seed of the generator.
//!
//! The target is never sent SIGSTOP: its parent (the voter) sees nothing but a delay. Signals
//! that arrive while it is stopped are delivered after the injection, with their `siginfo`
//! (so a `sigqueue` payload survives). See `docs/register-injection.md`.

#[cfg(all(target_os = "linux", target_arch = "x86_64"))]
mod engine;
#[cfg(all(target_os = "linux", target_arch = "x86_64"))]
mod regs;
/// The ptrace boundary. Public for the test kit, which stops a fork child at a chosen system
/// call with the same wrappers (`s3res_testkit::trace`).
#[cfg(all(target_os = "linux", target_arch = "x86_64"))]
pub mod sys;

use rand::Rng;
use serde::{Deserialize, Serialize};
use std::fmt;
use std::io;
use std::str::FromStr;

/// Which operands of the instruction may be hit.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum OperandRole {
    /// A register the instruction reads; flipped before the instruction runs.
    Source,
    /// A register the instruction writes; flipped after single-stepping it.
    Destination,
    /// Either (one candidate list with both roles, one chosen uniformly).
    #[default]
    Any,
}

/// Which bits of the chosen register may be flipped.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FloatField {
    /// Any bit of the operand (the full width of the register the instruction names:
    /// 64 for RAX, 8 for AH, 128 for XMM3).
    #[default]
    Whole,
    /// Bit 63 of the f64 lane.
    Sign,
    /// Bits 52–62 of the f64 lane.
    Exponent,
    /// Bits 0–51 of the f64 lane.
    Mantissa,
}

impl fmt::Display for OperandRole {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            OperandRole::Source => "source",
            OperandRole::Destination => "destination",
            OperandRole::Any => "any",
        })
    }
}

impl FromStr for OperandRole {
    type Err = RegFlipError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.to_ascii_lowercase().as_str() {
            "source" | "src" => Ok(OperandRole::Source),
            "destination" | "dest" | "dst" => Ok(OperandRole::Destination),
            "any" => Ok(OperandRole::Any),
            _ => Err(RegFlipError::InvalidSpec(format!(
                "role `{s}`: expected source, destination or any"
            ))),
        }
    }
}

impl fmt::Display for FloatField {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            FloatField::Whole => "whole",
            FloatField::Sign => "sign",
            FloatField::Exponent => "exponent",
            FloatField::Mantissa => "mantissa",
        })
    }
}

impl FromStr for FloatField {
    type Err = RegFlipError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.to_ascii_lowercase().as_str() {
            "whole" | "any" => Ok(FloatField::Whole),
            "sign" => Ok(FloatField::Sign),
            "exponent" => Ok(FloatField::Exponent),
            "mantissa" => Ok(FloatField::Mantissa),
            _ => Err(RegFlipError::InvalidSpec(format!(
                "field `{s}`: expected whole, sign, exponent or mantissa"
            ))),
        }
    }
}

/// What to inject. Build it with `RegFlipSpec { role, bits, ..Default::default() }`.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct RegFlipSpec {
    pub role: OperandRole,
    /// How many distinct bits to flip (1 = single-bit upset).
    pub bits: u32,
    pub field: FloatField,
    /// Restrict candidates to these registers: a full register (`rax`, `r12`, `xmm3`) admits
    /// every sub-register of it, a sub-register (`eax`, `ah`, `r8b`) only itself. `rflags` and
    /// `rip` are candidates only when named here. `None`: every general-purpose register
    /// (RSP and RBP included) and XMM0–15, with their sub-registers.
    pub registers: Option<Vec<String>>,
    /// The thread to inject into; `None` = the main thread (tid = pid).
    pub tid: Option<i32>,
    /// For a float field of an XMM register: which f64 lane (0 = bits 0–63, 1 = bits 64–127).
    pub lane: u8,
    /// How many instructions to single-step past when the one at the stop has no candidate.
    pub max_steps: u32,
}

impl Default for RegFlipSpec {
    fn default() -> Self {
        RegFlipSpec {
            role: OperandRole::Any,
            bits: 1,
            field: FloatField::Whole,
            registers: None,
            tid: None,
            lane: 0,
            max_steps: 16,
        }
    }
}

/// Everything about one injection (the seed is the caller's to log).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct RegFlipRecord {
    /// The seed of the caller's generator, if the caller fills it in (`inject` cannot know
    /// it); with it, one record line says everything about the injection.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub seed: Option<u64>,
    pub pid: i32,
    pub tid: i32,
    /// CLOCK_MONOTONIC (ns) when the flipped value was written into the thread.
    pub time_ns: u64,
    /// Address of the instruction whose operand was hit.
    pub ip: u64,
    /// That instruction, Intel syntax.
    pub instruction: String,
    /// Its bytes, hex.
    pub instruction_bytes: String,
    /// How many code bytes at `ip` were readable (15 unless the mapping ends sooner).
    pub bytes_read: usize,
    /// Instructions single-stepped past before one had a candidate (0 = the one at the stop).
    pub steps: u32,
    /// Where the thread resumes (after the single-step for a destination).
    pub resume_ip: u64,
    /// The full register hit (`rax`, `xmm3`, `rflags`, `rip`).
    pub register: String,
    /// The operand as the instruction names it (`ah`, `eax`, `xmm3`).
    pub operand: String,
    pub role: OperandRole,
    pub field: FloatField,
    /// The f64 lane of a float field in an XMM register.
    pub lane: Option<u8>,
    /// The flipped bit positions in the full register, ascending (AH's bits are 8–15).
    pub bits: Vec<u32>,
    /// The full register before and after, hex (16 digits, 32 for XMM).
    pub before: String,
    pub after: String,
    /// Every candidate of the instruction, `operand:role`, that the choice was made from.
    pub candidates: Vec<String>,
    /// Time the thread was held: from PTRACE_INTERRUPT to PTRACE_DETACH returning, ns.
    pub pause_ns: u64,
    /// The part of `pause_ns` until the thread reported its stop (it must be scheduled to
    /// take the interrupt, so this grows with CPU contention), ns.
    pub stop_ns: u64,
    /// Signals that reached the thread during single-steps despite the blocked mask (sent as
    /// SEGV/BUS/ILL/FPE/TRAP by another process) and were re-sent after the injection.
    pub signals_deferred: Vec<i32>,
    /// [`inject_after_syscall`]: the syscall-stops it took for a blocked thread's call to
    /// return (0: the thread was not blocked, and the flip landed where it was stopped).
    #[serde(default)]
    pub syscall_stops: u32,
    /// [`inject_after_syscall`]: instructions single-stepped after that return, before the
    /// instant of the flip (drawn uniformly up to the caller's bound).
    #[serde(default)]
    pub skipped: u32,
}

impl RegFlipRecord {
    /// The XOR mask of the flipped bits, as a full-register value.
    pub fn mask(&self) -> u128 {
        self.bits.iter().fold(0u128, |m, &b| m | 1u128 << b)
    }
}

#[derive(Debug, thiserror::Error)]
pub enum RegFlipError {
    #[error("register injection is built for x86-64 Linux only")]
    Unsupported,
    #[error("invalid register-injection spec: {0}")]
    InvalidSpec(String),
    #[error("thread {tid} is not a thread of process {pid}")]
    NotAThreadOf { pid: i32, tid: i32 },
    #[error(
        "not allowed to trace thread {tid} ({source}): it is traced already (a debugger, \
         another injection), or this user may not trace it (run as root, give the injector \
         CAP_SYS_PTRACE, or set kernel.yama.ptrace_scope=0)"
    )]
    Permission { tid: i32, source: io::Error },
    #[error("thread {tid} does not exist or exited during the injection")]
    Gone { tid: i32 },
    #[error("thread {tid} is stopped by job control (signal {sig}); not injecting")]
    JobControlStopped { tid: i32, sig: i32 },
    #[error(
        "thread {tid} was blocked in system call {syscall} (resumes at {ip:#x}): its registers \
         were in kernel memory, not in the CPU, so no fault is injected at this instant"
    )]
    InSyscall { tid: i32, ip: u64, syscall: u64 },
    #[error(
        "no register operand matching the spec (role {role}) in {steps} single-steps \
         (stopped at {ip:#x}: {instruction})"
    )]
    NoCandidate {
        tid: i32,
        role: OperandRole,
        steps: u32,
        ip: u64,
        instruction: String,
    },
    #[error("cannot read the instruction at {ip:#x} of thread {tid}: {source}")]
    ReadCode {
        tid: i32,
        ip: u64,
        source: io::Error,
    },
    #[error("undecodable instruction at {ip:#x} (bytes {bytes})")]
    Undecodable { ip: u64, bytes: String },
    #[error(
        "the instruction at {ip:#x} raised signal {sig} while being single-stepped; \
         it is delivered as it would have been without injection"
    )]
    InstructionFaulted { ip: u64, sig: i32 },
    #[error("the kernel did not keep the flipped {register}: wrote {wanted}, reads back {got}")]
    WriteRejected {
        register: String,
        wanted: String,
        got: String,
    },
    #[error("ptrace {op} on thread {tid}: {source}")]
    Ptrace {
        op: &'static str,
        tid: i32,
        source: io::Error,
    },
}

/// Checks `spec` without touching any process: what [`inject`] would refuse for the spec
/// itself (bits out of range or wider than the chosen field, an unknown register name), so a
/// campaign can refuse it once before its first run.
pub fn check_spec(spec: &RegFlipSpec) -> Result<(), RegFlipError> {
    #[cfg(all(target_os = "linux", target_arch = "x86_64"))]
    return engine::validate(spec).map(|_| ());
    #[cfg(not(all(target_os = "linux", target_arch = "x86_64")))]
    {
        let _ = spec;
        Err(RegFlipError::Unsupported)
    }
}

/// Injects one register bit-flip into thread `spec.tid` (default: `pid`) of process `pid`, now.
///
/// Blocks only for the injection itself (the pause is reported in the record). If the thread
/// dies meanwhile, its exit is consumed by `waitpid` as ptrace requires (so that the real
/// parent is told); a caller that is itself the target's parent must then treat the child as
/// reaped ([`RegFlipError::Gone`]) and not kill or wait for it again.
pub fn inject(
    pid: i32,
    spec: &RegFlipSpec,
    rng: &mut impl Rng,
) -> Result<RegFlipRecord, RegFlipError> {
    #[cfg(all(target_os = "linux", target_arch = "x86_64"))]
    return engine::inject(pid, spec, rng);
    #[cfg(not(all(target_os = "linux", target_arch = "x86_64")))]
    {
        let _ = (pid, spec, rng);
        Err(RegFlipError::Unsupported)
    }
}

/// Injects one register bit-flip into thread `spec.tid` (default: `pid`) of process `pid` at
/// the next instant it runs its own code.
///
/// A thread blocked in a system call has its registers in kernel memory, and most components
/// spend most of their time so, waiting for input. Then the thread is let run until a system
/// call returns (its input came; up to `patience`), and is stopped there; a number of its
/// instructions drawn uniformly from `0..=skip` is single-stepped (never into a system call),
/// and the flip lands at the next candidate instruction. `syscall_stops` and `skipped` in the
/// record say how it got there. A thread that is running when stopped is flipped where it is,
/// as [`inject`] does. [`RegFlipError::InSyscall`] if no call returned within `patience`.
pub fn inject_after_syscall(
    pid: i32,
    spec: &RegFlipSpec,
    rng: &mut impl Rng,
    patience: std::time::Duration,
    skip: u32,
) -> Result<RegFlipRecord, RegFlipError> {
    #[cfg(all(target_os = "linux", target_arch = "x86_64"))]
    return engine::inject_with(
        pid,
        spec,
        rng,
        engine::Landing::AfterSyscall {
            patience_ns: patience.as_nanos().min(u64::MAX as u128) as u64,
            skip,
        },
    );
    #[cfg(not(all(target_os = "linux", target_arch = "x86_64")))]
    {
        let _ = (pid, spec, rng, patience, skip);
        Err(RegFlipError::Unsupported)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The role reads as a role ("no any register matching …" before).
    #[test]
    fn no_candidate_names_the_role_as_a_role() {
        let e = RegFlipError::NoCandidate {
            tid: 1,
            role: OperandRole::Any,
            steps: 16,
            ip: 0x10,
            instruction: "nop".into(),
        };
        assert_eq!(
            e.to_string(),
            "no register operand matching the spec (role any) in 16 single-steps (stopped at \
             0x10: nop)"
        );
    }
}
