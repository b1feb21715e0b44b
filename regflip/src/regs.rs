//! Where a register named by the decoder lives in the state ptrace gives us, and which bits of
//! it an injection may flip.
//!
//! `user_regs_struct` holds the 16 general-purpose registers, RIP and RFLAGS; the FXSAVE image
//! of `user_fpregs_struct` holds XMM0–15 in `xmm_space` (16 registers × 16 bytes, little
//! endian). A sub-register is a bit range of its full register: EAX = bits 0–31 of RAX,
//! AX = 0–15, AL = 0–7, AH = 8–15. YMM/ZMM operands map to the low 128 bits (their XMM part);
//! the upper halves live in the XSAVE area and are not injected. XMM16–31, x87/MMX, mask,
//! segment, control and debug registers are never candidates.

use crate::sys::{FpRegs, Regs};
use crate::{FloatField, OperandRole};
use iced_x86::{Register, RflagsBits};

/// A whole register of the thread's user state.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Slot {
    /// A general-purpose register, in encoding order (RAX, RCX, RDX, RBX, RSP, RBP, RSI, RDI,
    /// R8–R15), as iced's `Register::number` counts them.
    Gpr(usize),
    /// XMM0–15.
    Xmm(usize),
    Rflags,
    Rip,
}

const GPR_NAMES: [&str; 16] = [
    "rax", "rcx", "rdx", "rbx", "rsp", "rbp", "rsi", "rdi", "r8", "r9", "r10", "r11", "r12", "r13",
    "r14", "r15",
];
const XMM_NAMES: [&str; 16] = [
    "xmm0", "xmm1", "xmm2", "xmm3", "xmm4", "xmm5", "xmm6", "xmm7", "xmm8", "xmm9", "xmm10",
    "xmm11", "xmm12", "xmm13", "xmm14", "xmm15",
];

impl Slot {
    pub(crate) fn name(self) -> &'static str {
        match self {
            Slot::Gpr(i) => GPR_NAMES[i],
            Slot::Xmm(i) => XMM_NAMES[i],
            Slot::Rflags => "rflags",
            Slot::Rip => "rip",
        }
    }

    pub(crate) fn is_fp(self) -> bool {
        matches!(self, Slot::Xmm(_))
    }

    pub(crate) fn read(self, regs: &Regs, fp: &FpRegs) -> u128 {
        match self {
            Slot::Gpr(i) => *gpr(regs, i) as u128,
            Slot::Xmm(i) => (0..4).fold(0u128, |acc, k| {
                acc | (fp.xmm_space[4 * i + k] as u128) << (32 * k)
            }),
            Slot::Rflags => regs.eflags as u128,
            Slot::Rip => regs.rip as u128,
        }
    }

    pub(crate) fn write(self, regs: &mut Regs, fp: &mut FpRegs, value: u128) {
        match self {
            Slot::Gpr(i) => *gpr_mut(regs, i) = value as u64,
            Slot::Xmm(i) => {
                for k in 0..4 {
                    fp.xmm_space[4 * i + k] = (value >> (32 * k)) as u32;
                }
            }
            Slot::Rflags => regs.eflags = value as u64,
            Slot::Rip => regs.rip = value as u64,
        }
    }

    /// Formats a value of this register as fixed-width hex.
    pub(crate) fn hex(self, value: u128) -> String {
        match self {
            Slot::Xmm(_) => format!("{value:#034x}"),
            _ => format!("{:#018x}", value as u64),
        }
    }
}

fn gpr(regs: &Regs, i: usize) -> &u64 {
    match i {
        0 => &regs.rax,
        1 => &regs.rcx,
        2 => &regs.rdx,
        3 => &regs.rbx,
        4 => &regs.rsp,
        5 => &regs.rbp,
        6 => &regs.rsi,
        7 => &regs.rdi,
        8 => &regs.r8,
        9 => &regs.r9,
        10 => &regs.r10,
        11 => &regs.r11,
        12 => &regs.r12,
        13 => &regs.r13,
        14 => &regs.r14,
        _ => &regs.r15,
    }
}

fn gpr_mut(regs: &mut Regs, i: usize) -> &mut u64 {
    match i {
        0 => &mut regs.rax,
        1 => &mut regs.rcx,
        2 => &mut regs.rdx,
        3 => &mut regs.rbx,
        4 => &mut regs.rsp,
        5 => &mut regs.rbp,
        6 => &mut regs.rsi,
        7 => &mut regs.rdi,
        8 => &mut regs.r8,
        9 => &mut regs.r9,
        10 => &mut regs.r10,
        11 => &mut regs.r11,
        12 => &mut regs.r12,
        13 => &mut regs.r13,
        14 => &mut regs.r14,
        _ => &mut regs.r15,
    }
}

/// A register operand as the instruction names it, located in its full register.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(crate) struct Operand {
    /// The name the instruction uses (`ah`, `eax`, `xmm3`, `rflags`, `rip`).
    pub name: String,
    pub slot: Slot,
    /// The bit positions of the full register this operand covers.
    pub positions: Vec<u32>,
}

/// The lowercase name of an iced register (iced calls the low byte of R8 `R8L`).
pub(crate) fn iced_name(reg: Register) -> String {
    format!("{reg:?}").to_ascii_lowercase()
}

/// Locates a register the decoder reported, or `None` if it is out of scope.
pub(crate) fn locate(reg: Register) -> Option<Operand> {
    let (slot, offset, width) = if reg.is_gpr() {
        let offset = match reg {
            Register::AH | Register::CH | Register::DH | Register::BH => 8,
            _ => 0,
        };
        (
            Slot::Gpr(reg.full_register().number()),
            offset,
            reg.size() as u32 * 8,
        )
    } else if (reg.is_xmm() || reg.is_ymm() || reg.is_zmm()) && reg.number() < 16 {
        (Slot::Xmm(reg.number()), 0, 128)
    } else {
        return None;
    };
    Some(Operand {
        name: iced_name(reg),
        slot,
        positions: (offset..offset + width).collect(),
    })
}

/// RFLAGS as a pseudo-operand: its positions are the architectural bits of the status flags
/// in iced's `RflagsBits` mask (only those an instruction reads or writes can be candidates,
/// and only user-writable flags, so the kernel accepts the flipped value).
pub(crate) fn rflags_operand(mask: u32) -> Option<Operand> {
    const MAP: [(u32, u32); 7] = [
        (RflagsBits::CF, 0),
        (RflagsBits::PF, 2),
        (RflagsBits::AF, 4),
        (RflagsBits::ZF, 6),
        (RflagsBits::SF, 7),
        (RflagsBits::DF, 10),
        (RflagsBits::OF, 11),
    ];
    let positions: Vec<u32> = MAP
        .iter()
        .filter(|(bit, _)| mask & bit != 0)
        .map(|&(_, pos)| pos)
        .collect();
    (!positions.is_empty()).then(|| Operand {
        name: "rflags".into(),
        slot: Slot::Rflags,
        positions,
    })
}

pub(crate) fn rip_operand() -> Operand {
    Operand {
        name: "rip".into(),
        slot: Slot::Rip,
        positions: (0..64).collect(),
    }
}

/// The bit positions of `field` within `operand` (for XMM, in f64 lane `lane`). A float field
/// needs a 64-bit lane: operands narrower than 64 bits have none.
pub(crate) fn field_positions(operand: &Operand, field: FloatField, lane: u8) -> Vec<u32> {
    let range = match field {
        FloatField::Whole => return operand.positions.clone(),
        FloatField::Sign => 63..64,
        FloatField::Exponent => 52..63,
        FloatField::Mantissa => 0..52,
    };
    if matches!(operand.slot, Slot::Rflags | Slot::Rip) {
        return Vec::new();
    }
    let base = if operand.slot.is_fp() {
        64 * lane as u32
    } else {
        0
    };
    range
        .map(|p| p + base)
        .filter(|p| operand.positions.contains(p) && operand.positions.len() >= 64)
        .collect()
}

/// Every register name the spec's `registers` list may use: full GPRs and their
/// sub-registers (iced names, plus `r8b`-style aliases), xmm0–15, rflags, rip.
pub(crate) fn normalize_name(name: &str) -> Option<String> {
    let lower = name.trim().to_ascii_lowercase();
    // The Intel manuals call the low byte of R8 `R8B`; iced calls it `R8L`.
    let lower = match lower.strip_suffix('b') {
        Some(stem) if stem.starts_with('r') && stem[1..].parse::<u8>().is_ok() => {
            format!("{stem}l")
        }
        _ => lower,
    };
    if lower == "rflags" || lower == "rip" {
        return Some(lower);
    }
    Register::values()
        .filter(|r| r.is_gpr() || (r.is_xmm() && r.number() < 16))
        .any(|r| iced_name(r) == lower)
        .then_some(lower)
}

/// Whether a candidate with this operand and role belongs to the role the spec asked for.
pub(crate) fn role_matches(asked: OperandRole, role: OperandRole) -> bool {
    asked == OperandRole::Any || asked == role
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sub_registers_sit_at_their_place_in_the_full_register() {
        let ah = locate(Register::AH).unwrap();
        assert_eq!(ah.slot, Slot::Gpr(0));
        assert_eq!(ah.positions, (8..16).collect::<Vec<_>>());
        let r12d = locate(Register::R12D).unwrap();
        assert_eq!((r12d.slot.name(), r12d.positions.len()), ("r12", 32));
        let sil = locate(Register::SIL).unwrap();
        assert_eq!((sil.slot.name(), sil.positions.len()), ("rsi", 8));
        let rsp = locate(Register::RSP).unwrap();
        assert_eq!((rsp.slot.name(), rsp.positions.len()), ("rsp", 64));
        let ymm5 = locate(Register::YMM5).unwrap();
        assert_eq!((ymm5.slot, ymm5.positions.len()), (Slot::Xmm(5), 128));
        assert!(locate(Register::XMM16).is_none());
        assert!(locate(Register::ST0).is_none());
        assert!(locate(Register::RIP).is_none());
    }

    #[test]
    fn float_fields_are_the_ieee754_binary64_fields() {
        let rax = locate(Register::RAX).unwrap();
        assert_eq!(field_positions(&rax, FloatField::Sign, 0), vec![63]);
        assert_eq!(
            field_positions(&rax, FloatField::Exponent, 0),
            (52..63).collect::<Vec<_>>()
        );
        assert_eq!(field_positions(&rax, FloatField::Mantissa, 0).len(), 52);
        let xmm = locate(Register::XMM2).unwrap();
        assert_eq!(field_positions(&xmm, FloatField::Sign, 1), vec![127]);
        assert_eq!(
            field_positions(&xmm, FloatField::Exponent, 1),
            (116..127).collect::<Vec<_>>()
        );
        let eax = locate(Register::EAX).unwrap();
        assert!(field_positions(&eax, FloatField::Sign, 0).is_empty());
        assert_eq!(field_positions(&eax, FloatField::Whole, 0).len(), 32);
    }

    #[test]
    fn register_names_are_checked() {
        assert_eq!(normalize_name("RAX").as_deref(), Some("rax"));
        assert_eq!(normalize_name("r8b").as_deref(), Some("r8l"));
        assert_eq!(normalize_name("ah").as_deref(), Some("ah"));
        assert_eq!(normalize_name("xmm15").as_deref(), Some("xmm15"));
        assert_eq!(normalize_name("rflags").as_deref(), Some("rflags"));
        assert_eq!(normalize_name("xmm16"), None);
        assert_eq!(normalize_name("eflagz"), None);
    }

    #[test]
    fn xmm_values_round_trip_through_the_fxsave_image() {
        let (mut regs, mut fp) = crate::sys::zeroed_state();
        let v = 0x0011_2233_4455_6677_8899_aabb_ccdd_eeffu128;
        Slot::Xmm(3).write(&mut regs, &mut fp, v);
        assert_eq!(Slot::Xmm(3).read(&regs, &fp), v);
        assert_eq!(fp.xmm_space[12], 0xccdd_eeff);
        Slot::Gpr(12).write(&mut regs, &mut fp, 0xdead);
        assert_eq!(regs.r12, 0xdead);
    }
}
