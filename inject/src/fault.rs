//! The fault kinds and how each one is delivered to one process.
//!
//! An [`Action`] is decided completely in advance by the schedule (which bit, which bytes,
//! which seed); [`fire`] only delivers it. That is what makes a campaign reproducible: the same
//! seed gives the same actions, whatever the timing of the run.

use serde::{Deserialize, Serialize};
use thiserror::Error;

use replica_rt::contract::signals::{self, VarRequest};

/// What kind of fault a campaign injects.
#[derive(
    Debug,
    Clone,
    Copy,
    PartialEq,
    Eq,
    Hash,
    PartialOrd,
    Ord,
    Serialize,
    Deserialize,
    clap::ValueEnum,
)]
#[serde(rename_all = "lowercase")]
pub enum FaultKind {
    /// Nothing is injected: a baseline that counts false positives and task success.
    None,
    /// Execution error: SIGKILL.
    Exec,
    /// Silent data corruption: replica-rt flips one bit of the next outgoing frame (SIGUSR2).
    Sdc,
    /// Control-flow error: replica-rt spins forever (SIGRTMIN+2).
    Cfe,
    /// Variable-level flip: chosen bits at a chosen byte offset of the next frame (SIGRTMIN+3).
    Var,
    /// Register bit flip through ptrace (the s3res-regflip crate).
    Reg,
}

impl FaultKind {
    pub fn name(self) -> &'static str {
        match self {
            FaultKind::None => "none",
            FaultKind::Exec => "exec",
            FaultKind::Sdc => "sdc",
            FaultKind::Cfe => "cfe",
            FaultKind::Var => "var",
            FaultKind::Reg => "reg",
        }
    }
}

impl std::fmt::Display for FaultKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// One injection, fully decided.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum Action {
    Exec,
    /// `value` is the `sigqueue` value: the bit to flip, reduced by the replica modulo the
    /// frame's bit count (bit 0 = lowest bit of the first payload byte).
    Sdc {
        value: u32,
    },
    Cfe,
    /// Flip `bits` (bit 0 = lowest bit of byte `offset`, little-endian) of the next frame.
    Var {
        offset: u32,
        bits: Vec<u32>,
    },
    /// A register flip; `seed` seeds the ChaCha8 generator handed to the register injector.
    Reg {
        seed: u64,
    },
}

impl Action {
    pub fn kind(&self) -> FaultKind {
        match self {
            Action::Exec => FaultKind::Exec,
            Action::Sdc { .. } => FaultKind::Sdc,
            Action::Cfe => FaultKind::Cfe,
            Action::Var { .. } => FaultKind::Var,
            Action::Reg { .. } => FaultKind::Reg,
        }
    }
}

/// Options of the register injector, as given on the command line (see
/// `s3res-regflip`'s `RegFlipSpec`).
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct RegOptions {
    /// `source`, `destination` or `any` operand.
    pub role: String,
    /// Bits flipped per injection.
    pub bits: u32,
    /// `whole`, `sign`, `exponent` or `mantissa`.
    pub field: String,
    /// Only these registers (names as the injector spells them); all if `None`.
    pub registers: Option<Vec<String>>,
}

#[derive(Debug, Error)]
pub enum FireError {
    /// The target is gone (ESRCH): it died or was replaced before the instant came.
    #[error("process {0} no longer exists")]
    Gone(i32),
    #[error("cannot signal process {pid}: {source}")]
    Signal { pid: i32, source: std::io::Error },
    #[error("variable flip at offset {offset} is beyond what the hook can address ({max})")]
    OffsetTooLarge { offset: u32, max: u32 },
    #[error("register injection (--fault reg) is provided by the s3res-regflip crate, which this build does not include")]
    RegNotBuilt,
}

/// Whether this build can deliver `kind` (checked before a campaign starts, so that a kind
/// that cannot be delivered is one clear error, not N runs of missed injections).
pub fn check_available(kind: FaultKind) -> Result<(), FireError> {
    match kind {
        // The register injector is the s3res-regflip crate; see the `Reg` arm of `fire`.
        FaultKind::Reg => Err(FireError::RegNotBuilt),
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
        Action::Reg { .. } => {
            // Wired to s3res_regflip::inject(pid, &spec, &mut ChaCha8Rng::seed_from_u64(seed))
            // once that crate is part of the workspace.
            let _ = reg;
            return Err(FireError::RegNotBuilt);
        }
    }
    Ok(None)
}

#[cfg(test)]
mod tests {
    use super::*;

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
}
