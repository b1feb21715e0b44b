//! The injector proper (x86-64 Linux): ptrace session, instruction decoding, candidate
//! registers, the flip. See the crate documentation and `docs/register-injection.md`.

use crate::regs::{self, Operand};
use crate::sys::{self, Stop, Tid};
use crate::{FloatField, OperandRole, RegFlipError, RegFlipRecord, RegFlipSpec};
use iced_x86::{
    Code, Decoder, DecoderOptions, FlowControl, Formatter, Instruction, InstructionInfoFactory,
    IntelFormatter, OpAccess,
};
use rand::seq::SliceRandom;
use rand::Rng;
use std::io;

/// The longest x86 instruction.
const MAX_INSTRUCTION_LEN: u64 = 15;
/// Signal stops tolerated while waiting for one ptrace stop, before giving up.
const MAX_SIGNAL_STOPS: u32 = 64;

/// Maps an error of a ptrace request to the error the caller should see (ESRCH = gone).
fn ptrace_err(op: &'static str, tid: Tid) -> impl FnOnce(io::Error) -> RegFlipError {
    move |source| match source.raw_os_error() {
        Some(libc::ESRCH) | Some(libc::ECHILD) => RegFlipError::Gone { tid },
        _ => RegFlipError::Ptrace { op, tid, source },
    }
}

/// How [`inject_with`] reaches its instant.
#[derive(Clone, Copy, Debug)]
pub(crate) enum Landing {
    /// Where the thread is stopped first (an error if that is inside a blocking call).
    Now,
    /// If the thread is blocked in a system call, wherever it is once a call returns (up to
    /// `patience_ns`), `skip` instructions after it at most (drawn uniformly from `0..=skip`).
    AfterSyscall { patience_ns: u64, skip: u32 },
}

pub(crate) fn inject(
    pid: i32,
    spec: &RegFlipSpec,
    rng: &mut impl Rng,
) -> Result<RegFlipRecord, RegFlipError> {
    inject_with(pid, spec, rng, Landing::Now)
}

pub(crate) fn inject_with(
    pid: i32,
    spec: &RegFlipSpec,
    rng: &mut impl Rng,
    landing: Landing,
) -> Result<RegFlipRecord, RegFlipError> {
    let filter = validate(spec)?;
    let tid = spec.tid.unwrap_or(pid);
    if tid != pid && !std::path::Path::new(&format!("/proc/{pid}/task/{tid}")).exists() {
        return Err(RegFlipError::NotAThreadOf { pid, tid });
    }
    sys::seize(tid).map_err(|source| match source.raw_os_error() {
        // The kernel refuses to attach to a thread that is exiting with EPERM too: a target
        // that an earlier flip crashed, still named by whoever picked it.
        Some(libc::EPERM) if !matches!(replica_rt::sys::process_state(tid), Some(s) if s != 'Z' && s != 'X') => {
            RegFlipError::Gone { tid }
        }
        Some(libc::EPERM) => RegFlipError::Permission { tid, source },
        _ => ptrace_err("SEIZE", tid)(source),
    })?;
    let mut traced = Traced {
        pid,
        tid,
        attached: true,
        deferred: Vec::new(),
        detach_sig: 0,
        saved_sigmask: None,
    };
    let start = replica_rt::sys::monotonic_ns();
    let mut stop_ns = 0;
    let mut syscall_stops = 0;
    let mut skipped = 0;
    let outcome = traced.interrupt().and_then(|()| {
        stop_ns = replica_rt::sys::monotonic_ns().saturating_sub(start);
        if let Landing::AfterSyscall { patience_ns, skip } = landing {
            let regs = sys::get_regs(tid).map_err(ptrace_err("GETREGS", tid))?;
            if restartable_syscall(&regs) {
                syscall_stops = traced.follow_to_syscall_exit(start.saturating_add(patience_ns))?;
                skipped = traced.skip_instructions(rng.gen_range(0..=skip))?;
            }
        }
        traced.flip(spec, &filter, rng)
    });
    let deferred: Vec<i32> = traced.deferred.iter().map(|i| i.si_signo).collect();
    let detached = traced.release();
    let pause_ns = replica_rt::sys::monotonic_ns().saturating_sub(start);
    let mut record = outcome?;
    detached?;
    record.pid = pid;
    record.pause_ns = pause_ns;
    record.stop_ns = stop_ns;
    record.syscall_stops = syscall_stops;
    record.skipped = skipped;
    record.signals_deferred = deferred;
    tracing::debug!(?record, "register flip injected");
    Ok(record)
}

/// The spec's register names, checked and normalised.
pub(crate) fn validate(spec: &RegFlipSpec) -> Result<Option<Vec<String>>, RegFlipError> {
    if spec.bits == 0 || spec.bits > 128 {
        return Err(RegFlipError::InvalidSpec(format!(
            "bits = {}: must be 1 to 128 (at most the width of the chosen register)",
            spec.bits
        )));
    }
    // A field narrower than the flip could never be hit: every attempt would stop the target
    // and single-step it for nothing.
    let field_bits = match spec.field {
        FloatField::Whole => 128,
        FloatField::Sign => 1,
        FloatField::Exponent => 11,
        FloatField::Mantissa => 52,
    };
    if spec.bits > field_bits {
        return Err(RegFlipError::InvalidSpec(format!(
            "bits = {}: the {} field of an f64 has {field_bits} bit{}",
            spec.bits,
            spec.field,
            if field_bits == 1 { "" } else { "s" }
        )));
    }
    if spec.lane > 1 {
        return Err(RegFlipError::InvalidSpec(format!(
            "lane = {}: an XMM register has f64 lanes 0 and 1",
            spec.lane
        )));
    }
    let Some(names) = &spec.registers else {
        return Ok(None);
    };
    if names.is_empty() {
        return Err(RegFlipError::InvalidSpec(
            "registers: the list is empty (leave it out to allow every register)".into(),
        ));
    }
    names
        .iter()
        .map(|n| {
            regs::normalize_name(n).ok_or_else(|| {
                RegFlipError::InvalidSpec(format!(
                    "registers: unknown register `{n}` (general-purpose registers and their \
                     sub-registers, xmm0-xmm15, rflags, rip)"
                ))
            })
        })
        .collect::<Result<Vec<_>, _>>()
        .map(Some)
}

/// One register operand the chosen instruction offers, with the bits a flip may hit.
#[derive(Clone, Debug)]
struct Candidate {
    operand: Operand,
    role: OperandRole,
    positions: Vec<u32>,
}

impl Candidate {
    fn label(&self) -> String {
        format!("{}:{}", self.operand.name, self.role)
    }
}

/// The thread we trace; detaches when dropped, so every error path leaves the thread running.
struct Traced {
    pid: Tid,
    tid: Tid,
    attached: bool,
    /// Signals met in signal-delivery-stops during single-steps, delivered at the end.
    deferred: Vec<sys::siginfo_t>,
    /// A signal to deliver with PTRACE_DETACH (the thread is in its signal-delivery-stop).
    detach_sig: libc::c_int,
    /// The thread's own signal mask, while we hold asynchronous signals back during steps.
    saved_sigmask: Option<sys::SigMask>,
}

impl Traced {
    /// Stops the thread: PTRACE_INTERRUPT, then wait for its event-stop. A signal that
    /// reaches the thread first is passed on at once (as if it came just before the instant).
    fn interrupt(&mut self) -> Result<(), RegFlipError> {
        let tid = self.tid;
        sys::interrupt(tid).map_err(ptrace_err("INTERRUPT", tid))?;
        for _ in 0..MAX_SIGNAL_STOPS {
            match sys::wait_stop(tid).map_err(ptrace_err("waitpid", tid))? {
                Stop::Event { sig } if sig == libc::SIGTRAP => return Ok(()),
                Stop::Event { sig } => return Err(RegFlipError::JobControlStopped { tid, sig }),
                Stop::Signal { sig } => self.pass_on(sig)?,
                Stop::Trap => self.pass_on(libc::SIGTRAP)?,
                // A syscall-stop of `follow_to_syscall_exit`'s, met on the way to the event-stop.
                Stop::OtherEvent { .. } | Stop::Syscall => self.pass_on(0)?,
                Stop::Exited { .. } | Stop::Killed { .. } => {
                    self.attached = false;
                    return Err(RegFlipError::Gone { tid });
                }
            }
        }
        Err(RegFlipError::Ptrace {
            op: "INTERRUPT",
            tid,
            source: io::Error::other("the thread kept receiving signals instead of stopping"),
        })
    }

    fn pass_on(&mut self, sig: libc::c_int) -> Result<(), RegFlipError> {
        let tid = self.tid;
        sys::cont(tid, sig).map_err(ptrace_err("CONT", tid))?;
        sys::interrupt(tid).map_err(ptrace_err("INTERRUPT", tid))
    }

    /// Executes exactly one instruction of the stopped thread.
    ///
    /// Before the first step, asynchronous signals are blocked in the thread (PTRACE_SETSIGMASK)
    /// so that they stay queued in the kernel, with their siginfo and order, until `release`
    /// restores the mask; otherwise every resume would dequeue one into a signal-delivery-stop.
    /// Signals an instruction raises itself (SEGV, BUS, ILL, FPE, TRAP) are left unblocked: a
    /// blocked fault would kill the thread instead of reaching its handler.
    fn step(&mut self, ip: u64) -> Result<(), RegFlipError> {
        let tid = self.tid;
        if self.saved_sigmask.is_none() {
            let own = sys::get_sigmask(tid).map_err(ptrace_err("GETSIGMASK", tid))?;
            let synchronous = [
                libc::SIGSEGV,
                libc::SIGBUS,
                libc::SIGILL,
                libc::SIGFPE,
                libc::SIGTRAP,
            ]
            .iter()
            .fold(0u64, |m, &sig| m | 1 << (sig - 1));
            sys::set_sigmask(tid, own | !synchronous).map_err(ptrace_err("SETSIGMASK", tid))?;
            self.saved_sigmask = Some(own);
        }
        sys::single_step(tid).map_err(ptrace_err("SINGLESTEP", tid))?;
        for _ in 0..MAX_SIGNAL_STOPS {
            match sys::wait_stop(tid).map_err(ptrace_err("waitpid", tid))? {
                Stop::Trap => {
                    let info = sys::get_siginfo(tid).map_err(ptrace_err("GETSIGINFO", tid))?;
                    if info.si_code > 0 {
                        return Ok(()); // the kernel's single-step trap
                    }
                    self.deferred.push(info); // a SIGTRAP someone sent
                }
                Stop::Signal { sig } => {
                    let info = sys::get_siginfo(tid).map_err(ptrace_err("GETSIGINFO", tid))?;
                    let synchronous = matches!(
                        sig,
                        libc::SIGSEGV | libc::SIGBUS | libc::SIGILL | libc::SIGFPE
                    ) && info.si_code > 0;
                    if synchronous {
                        self.detach_sig = sig;
                        return Err(RegFlipError::InstructionFaulted { ip, sig });
                    }
                    self.deferred.push(info);
                }
                // A second PTRACE_INTERRUPT left pending by `interrupt`; the step has not run.
                Stop::Event { sig } if sig == libc::SIGTRAP => {}
                Stop::OtherEvent { .. } | Stop::Syscall => {}
                // Stopped by job control meanwhile (nothing has been flipped yet).
                Stop::Event { sig } => return Err(RegFlipError::JobControlStopped { tid, sig }),
                Stop::Exited { .. } | Stop::Killed { .. } => {
                    self.attached = false;
                    return Err(RegFlipError::Gone { tid });
                }
            }
            sys::single_step(tid).map_err(ptrace_err("SINGLESTEP", tid))?;
        }
        Err(RegFlipError::Ptrace {
            op: "SINGLESTEP",
            tid,
            source: io::Error::other("the thread kept receiving signals instead of stepping"),
        })
    }

    /// The thread is stopped inside a blocking system call, with its registers in kernel
    /// memory: lets it run until a system call returns (that one, once its input comes, or a
    /// later one) and stops it there, before its first user instruction after the call.
    /// Returns how many syscall-stops that took. At `deadline_ns` (monotonic) it gives up,
    /// stops the thread where it is (so it can be detached) and says it stayed in its call.
    fn follow_to_syscall_exit(&mut self, deadline_ns: u64) -> Result<u32, RegFlipError> {
        let tid = self.tid;
        let mut sig = 0;
        let mut stops = 0;
        loop {
            sys::resume_to_syscall(tid, sig).map_err(ptrace_err("SYSCALL", tid))?;
            sig = 0;
            let stop =
                sys::wait_stop_until(tid, deadline_ns).map_err(ptrace_err("waitpid", tid))?;
            let Some(stop) = stop else {
                self.interrupt()?;
                let regs = sys::get_regs(tid).map_err(ptrace_err("GETREGS", tid))?;
                return Err(RegFlipError::InSyscall {
                    tid,
                    ip: regs.rip,
                    syscall: regs.orig_rax,
                });
            };
            match stop {
                Stop::Syscall => {
                    stops += 1;
                    let regs = sys::get_regs(tid).map_err(ptrace_err("GETREGS", tid))?;
                    // At a syscall-entry-stop the kernel has set RAX to -ENOSYS; at an exit it
                    // holds the result. A call that a signal interrupted is restarted: not yet.
                    // Nor is the exit of `rt_sigreturn`, the end of a signal handler that
                    // interrupted the call: it leaves the thread on the `syscall` instruction,
                    // about to restart the call, not in the component's own work.
                    let entry = regs.rax as i64 == -(libc::ENOSYS as i64);
                    let sigreturn = regs.orig_rax == libc::SYS_rt_sigreturn as u64;
                    if !entry && !sigreturn && !restartable_syscall(&regs) {
                        return Ok(stops);
                    }
                }
                // Delivered as the thread resumes, as it would have been untraced.
                Stop::Signal { sig: s } => sig = s,
                Stop::Trap => sig = libc::SIGTRAP,
                // A PTRACE_INTERRUPT of `interrupt` that was still pending.
                Stop::Event { sig } if sig == libc::SIGTRAP => {}
                Stop::Event { sig } => return Err(RegFlipError::JobControlStopped { tid, sig }),
                Stop::OtherEvent { .. } => {}
                Stop::Exited { .. } | Stop::Killed { .. } => {
                    self.attached = false;
                    return Err(RegFlipError::Gone { tid });
                }
            }
        }
    }

    /// Single-steps up to `n` instructions, stopping before one that enters the kernel (a
    /// system call stepped over could block). Returns how many it stepped.
    fn skip_instructions(&mut self, n: u32) -> Result<u32, RegFlipError> {
        let tid = self.tid;
        for done in 0..n {
            let regs = sys::get_regs(tid).map_err(ptrace_err("GETREGS", tid))?;
            let code = read_code(tid, regs.rip)?;
            if enters_kernel(&decode(&code, regs.rip)?) {
                return Ok(done);
            }
            self.step(regs.rip)?;
        }
        Ok(n)
    }

    /// Finds the instruction, chooses register and bits, flips them. The thread is stopped.
    fn flip(
        &mut self,
        spec: &RegFlipSpec,
        filter: &Option<Vec<String>>,
        rng: &mut impl Rng,
    ) -> Result<RegFlipRecord, RegFlipError> {
        let tid = self.tid;
        let mut factory = InstructionInfoFactory::new();
        let mut steps = 0;
        let (instr, code, candidates) = loop {
            let regs = sys::get_regs(tid).map_err(ptrace_err("GETREGS", tid))?;
            if steps == 0 && restartable_syscall(&regs) {
                return Err(RegFlipError::InSyscall {
                    tid,
                    ip: regs.rip,
                    syscall: regs.orig_rax,
                });
            }
            let code = read_code(tid, regs.rip)?;
            let instr = decode(&code, regs.rip)?;
            let candidates = candidates(&instr, &mut factory, spec, filter);
            if !candidates.is_empty() {
                break (instr, code, candidates);
            }
            if steps >= spec.max_steps || enters_kernel(&instr) {
                return Err(RegFlipError::NoCandidate {
                    tid,
                    role: spec.role,
                    steps,
                    ip: regs.rip,
                    instruction: format_instruction(&instr),
                });
            }
            self.step(regs.rip)?;
            steps += 1;
        };
        let chosen = candidates
            .choose(rng)
            .expect("candidates is not empty")
            .clone();
        if chosen.role == OperandRole::Destination {
            self.step(instr.ip())?;
        }

        let mut regs = sys::get_regs(tid).map_err(ptrace_err("GETREGS", tid))?;
        let mut fp = sys::get_fpregs(tid).map_err(ptrace_err("GETFPREGS", tid))?;
        let slot = chosen.operand.slot;
        let before = slot.read(&regs, &fp);
        let mut bits: Vec<u32> = chosen
            .positions
            .choose_multiple(rng, spec.bits as usize)
            .copied()
            .collect();
        bits.sort_unstable();
        let mask = bits.iter().fold(0u128, |m, &b| m | 1u128 << b);
        let wanted = before ^ mask;
        slot.write(&mut regs, &mut fp, wanted);
        if slot.is_fp() {
            sys::set_fpregs(tid, &fp).map_err(ptrace_err("SETFPREGS", tid))?;
        } else {
            sys::set_regs(tid, &regs).map_err(ptrace_err("SETREGS", tid))?;
        }
        let time_ns = replica_rt::sys::monotonic_ns();
        // Read back what the thread will really run with.
        let regs = sys::get_regs(tid).map_err(ptrace_err("GETREGS", tid))?;
        let fp = sys::get_fpregs(tid).map_err(ptrace_err("GETFPREGS", tid))?;
        let after = slot.read(&regs, &fp);
        if after != wanted {
            return Err(RegFlipError::WriteRejected {
                register: slot.name().into(),
                wanted: slot.hex(wanted),
                got: slot.hex(after),
            });
        }
        let len = instr.len();
        Ok(RegFlipRecord {
            seed: None,
            pid: self.pid,
            tid,
            time_ns,
            ip: instr.ip(),
            instruction: format_instruction(&instr),
            instruction_bytes: hex(&code[..len]),
            bytes_read: code.len(),
            steps,
            resume_ip: regs.rip,
            register: slot.name().into(),
            operand: chosen.operand.name.clone(),
            role: chosen.role,
            field: spec.field,
            lane: (slot.is_fp() && spec.field != FloatField::Whole).then_some(spec.lane),
            bits,
            before: slot.hex(before),
            after: slot.hex(after),
            candidates: candidates.iter().map(Candidate::label).collect(),
            pause_ns: 0,
            stop_ns: 0,
            signals_deferred: Vec::new(),
            syscall_stops: 0,
            skipped: 0,
        })
    }

    /// Delivers deferred signals and detaches. Idempotent; `Drop` calls it too.
    fn release(&mut self) -> Result<(), RegFlipError> {
        if !self.attached {
            return Ok(());
        }
        self.attached = false;
        let tid = self.tid;
        if let Some(own) = self.saved_sigmask.take() {
            if let Err(e) = sys::set_sigmask(tid, own) {
                tracing::warn!(tid, "could not restore the signal mask: {e}");
            }
        }
        for info in self.deferred.drain(..) {
            // Re-queue with the original siginfo; the kernel refuses si_code >= 0 (kill,
            // tgkill) from another process, and for those the signal number is all there is.
            if sys::tgsigqueueinfo(self.pid, tid, &info).is_err() {
                if let Err(e) = sys::tgkill(self.pid, tid, info.si_signo) {
                    tracing::warn!(tid, sig = info.si_signo, "could not re-send a signal: {e}");
                }
            }
        }
        match sys::detach(tid, self.detach_sig) {
            Ok(()) => Ok(()),
            Err(e) if e.raw_os_error() == Some(libc::ESRCH) => {
                // ESRCH: dead, or not in a ptrace-stop. Stop it (if alive) and wait: a live
                // thread is then detached, so it is never left traced; a dead one's exit is
                // consumed, which is what lets its real parent (the voter) see the death.
                let _ = sys::interrupt(tid);
                match sys::wait_stop(tid) {
                    Ok(Stop::Exited { .. } | Stop::Killed { .. }) | Err(_) => {
                        Err(RegFlipError::Gone { tid })
                    }
                    Ok(_) => sys::detach(tid, 0).map_err(ptrace_err("DETACH", tid)),
                }
            }
            Err(e) => Err(ptrace_err("DETACH", tid)(e)),
        }
    }
}

impl Drop for Traced {
    fn drop(&mut self) {
        if let Err(e) = self.release() {
            tracing::warn!(tid = self.tid, "detaching after an injection error: {e}");
        }
    }
}

/// The thread was inside a blocking system call that will be restarted when it resumes
/// (`orig_rax` is the call, `rax` one of the kernel's internal -ERESTART* codes).
fn restartable_syscall(regs: &sys::Regs) -> bool {
    (regs.orig_rax as i64) >= 0 && (-516..=-512).contains(&(regs.rax as i64))
}

/// Reads up to 15 code bytes at `ip`, word by aligned word; an aligned word never crosses a
/// page, so the read stops exactly where the mapping ends.
fn read_code(tid: Tid, ip: u64) -> Result<Vec<u8>, RegFlipError> {
    let end = ip.saturating_add(MAX_INSTRUCTION_LEN);
    let mut code = Vec::with_capacity(MAX_INSTRUCTION_LEN as usize + 8);
    let mut word_addr = ip & !7;
    while word_addr < end {
        match sys::peek_word(tid, word_addr) {
            Ok(word) => code.extend_from_slice(&word.to_le_bytes()),
            Err(source) if code.is_empty() => {
                return Err(RegFlipError::ReadCode { tid, ip, source })
            }
            Err(_) => break,
        }
        word_addr += 8;
    }
    let skip = (ip - (ip & !7)) as usize;
    let readable = code.len().saturating_sub(skip);
    let take = readable.min(MAX_INSTRUCTION_LEN as usize);
    Ok(code[skip..skip + take].to_vec())
}

fn decode(code: &[u8], ip: u64) -> Result<Instruction, RegFlipError> {
    let mut decoder = Decoder::with_ip(64, code, ip, DecoderOptions::NONE);
    let instr = decoder.decode();
    if instr.is_invalid() {
        return Err(RegFlipError::Undecodable {
            ip,
            bytes: hex(code),
        });
    }
    Ok(instr)
}

fn format_instruction(instr: &Instruction) -> String {
    let mut text = String::new();
    let mut formatter = IntelFormatter::new();
    formatter
        .options_mut()
        .set_space_after_operand_separator(true);
    formatter.format(instr, &mut text);
    text
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// Instructions that enter the kernel: never single-stepped (a `syscall` may block for good).
fn enters_kernel(instr: &Instruction) -> bool {
    matches!(instr.code(), Code::Syscall | Code::Sysenter)
        || instr.flow_control() == FlowControl::Interrupt
}

/// The register operands of `instr` the spec allows, each with the bits a flip may hit.
fn candidates(
    instr: &Instruction,
    factory: &mut InstructionInfoFactory,
    spec: &RegFlipSpec,
    filter: &Option<Vec<String>>,
) -> Vec<Candidate> {
    let mut offered: Vec<(Operand, OperandRole)> = Vec::new();
    for used in factory.info(instr).used_registers() {
        let Some(operand) = regs::locate(used.register()) else {
            continue;
        };
        let (reads, writes) = match used.access() {
            OpAccess::Read | OpAccess::CondRead => (true, false),
            OpAccess::Write | OpAccess::CondWrite => (false, true),
            OpAccess::ReadWrite | OpAccess::ReadCondWrite => (true, true),
            OpAccess::None | OpAccess::NoMemAccess => (false, false),
        };
        if reads {
            offered.push((operand.clone(), OperandRole::Source));
        }
        if writes {
            offered.push((operand, OperandRole::Destination));
        }
    }
    let named = |name: &str| filter.as_ref().is_some_and(|f| f.iter().any(|n| n == name));
    if named("rflags") {
        if let Some(op) = regs::rflags_operand(instr.rflags_read()) {
            offered.push((op, OperandRole::Source));
        }
        if let Some(op) = regs::rflags_operand(instr.rflags_modified()) {
            offered.push((op, OperandRole::Destination));
        }
    }
    if named("rip") {
        offered.push((regs::rip_operand(), OperandRole::Source));
        offered.push((regs::rip_operand(), OperandRole::Destination));
    }
    let no_step = enters_kernel(instr);
    let mut out: Vec<Candidate> = Vec::new();
    for (operand, role) in offered {
        let admitted = match filter {
            None => true,
            Some(_) => named(&operand.name) || named(operand.slot.name()),
        };
        if !admitted || !regs::role_matches(spec.role, role) {
            continue;
        }
        if no_step && role == OperandRole::Destination {
            continue;
        }
        if out
            .iter()
            .any(|c| c.operand.name == operand.name && c.role == role)
        {
            continue;
        }
        let positions = regs::field_positions(&operand, spec.field, spec.lane);
        if positions.len() < spec.bits as usize {
            continue;
        }
        out.push(Candidate {
            operand,
            role,
            positions,
        });
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn decode_bytes(bytes: &[u8]) -> Instruction {
        decode(bytes, 0x1000).unwrap()
    }

    fn labels(bytes: &[u8], spec: &RegFlipSpec) -> Vec<String> {
        let filter = validate(spec).unwrap();
        let mut factory = InstructionInfoFactory::new();
        candidates(&decode_bytes(bytes), &mut factory, spec, &filter)
            .iter()
            .map(Candidate::label)
            .collect()
    }

    #[test]
    fn sources_and_destinations_come_from_the_decoder() {
        // add rax, rbx
        let any = RegFlipSpec::default();
        assert_eq!(
            labels(&[0x48, 0x01, 0xd8], &any),
            ["rax:source", "rax:destination", "rbx:source"]
        );
        let src = RegFlipSpec {
            role: OperandRole::Source,
            ..Default::default()
        };
        assert_eq!(
            labels(&[0x48, 0x01, 0xd8], &src),
            ["rax:source", "rbx:source"]
        );
        // cmp ah, dl: both read, flags written (RFLAGS not a candidate unless named)
        assert_eq!(labels(&[0x38, 0xd4], &any), ["ah:source", "dl:source"]);
        let flags = RegFlipSpec {
            registers: Some(vec!["rflags".into()]),
            ..Default::default()
        };
        assert_eq!(labels(&[0x38, 0xd4], &flags), ["rflags:destination"]);
        // movdqa xmm3, xmm4
        assert_eq!(
            labels(&[0x66, 0x0f, 0x6f, 0xdc], &any),
            ["xmm3:destination", "xmm4:source"]
        );
    }

    #[test]
    fn memory_operand_registers_are_sources_and_syscall_destinations_are_not_offered() {
        let any = RegFlipSpec::default();
        // mov rax, [rbx+8]
        assert_eq!(
            labels(&[0x48, 0x8b, 0x43, 0x08], &any),
            ["rax:destination", "rbx:source"]
        );
        let dst = RegFlipSpec {
            role: OperandRole::Destination,
            ..Default::default()
        };
        assert!(labels(&[0x0f, 0x05], &dst).is_empty());
        assert!(enters_kernel(&decode_bytes(&[0x0f, 0x05])));
    }

    #[test]
    fn a_float_field_excludes_operands_narrower_than_an_f64() {
        let sign = RegFlipSpec {
            field: FloatField::Sign,
            ..Default::default()
        };
        // add eax, ebx: the 32-bit sources have no binary64 sign bit; the write zero-extends
        // into all of RAX, so the decoder names RAX as the destination.
        assert_eq!(
            labels(&[0x01, 0xd8], &RegFlipSpec::default()),
            ["eax:source", "rax:destination", "ebx:source"]
        );
        assert_eq!(labels(&[0x01, 0xd8], &sign), ["rax:destination"]);
        assert_eq!(labels(&[0x48, 0x01, 0xd8], &sign).len(), 3);
    }

    #[test]
    fn the_filter_admits_sub_registers_of_a_named_full_register() {
        let rax = RegFlipSpec {
            registers: Some(vec!["RAX".into()]),
            ..Default::default()
        };
        assert_eq!(labels(&[0x38, 0xd4], &rax), ["ah:source"]);
        let eax = RegFlipSpec {
            registers: Some(vec!["eax".into()]),
            ..Default::default()
        };
        assert!(labels(&[0x38, 0xd4], &eax).is_empty());
        let bad = RegFlipSpec {
            registers: Some(vec!["xmm16".into()]),
            ..Default::default()
        };
        assert!(matches!(validate(&bad), Err(RegFlipError::InvalidSpec(m)) if m.contains("xmm16")));
    }

    /// A flip wider than the chosen field could never land: refused with the field's width.
    #[test]
    fn a_flip_wider_than_its_field_is_refused() {
        for (field, bits, ok) in [
            (FloatField::Sign, 1, true),
            (FloatField::Sign, 2, false),
            (FloatField::Exponent, 11, true),
            (FloatField::Exponent, 12, false),
            (FloatField::Mantissa, 52, true),
            (FloatField::Mantissa, 53, false),
            (FloatField::Whole, 128, true),
        ] {
            let spec = RegFlipSpec {
                field,
                bits,
                ..Default::default()
            };
            assert_eq!(validate(&spec).is_ok(), ok, "{field} {bits}");
        }
    }

    #[test]
    fn a_truncated_read_still_decodes_what_is_there() {
        // inc r12 followed by nothing (the page ends): 3 bytes are enough
        let instr = decode(&[0x49, 0xff, 0xc4], 0x1ffd).unwrap();
        assert_eq!(format_instruction(&instr), "inc r12");
        assert!(matches!(
            decode(&[0x49, 0xff], 0x1ffe),
            Err(RegFlipError::Undecodable { .. })
        ));
    }
}
