//! A test program whose register contents are known, for the register injector's tests.
//!
//! ```text
//! regflip-target gpr PATTERN      r12 = PATTERN each round; reports r12 (8 bytes) when it differs
//! regflip-target ah PATTERN       rax = PATTERN; compares AH with byte 1; reports rax (8 bytes)
//! regflip-target xmm LO HI        xmm3 = HI:LO each round; reports xmm3 (16 bytes) when it differs
//! regflip-target gpr-signals PATTERN
//!                                 as `gpr`, and writes the sigqueue value (4 bytes) of every
//!                                 SIGRTMIN it receives to stderr
//! regflip-target gpr-thread PATTERN
//!                                 as `gpr`, in a second thread; the main thread waits in join
//! regflip-target page-end         loops on `inc r12; jmp` in the last 5 bytes of a page whose
//!                                 next page is unmapped; reports that page's end address
//! ```
//!
//! Each mode writes `R` to stdout once its registers are loaded, then spins in a short loop of
//! inline assembly that re-loads the pattern, compares, and on a difference writes the register
//! it saw to stdout (raw little-endian bytes) and goes on. The whole loop, including the
//! `write` system calls, is one `asm!` block, so no compiler-generated code touches the
//! registers under test. The loops never end: the test kills the program.
//!
//! This is a test fixture: its `unsafe` is the inline assembly itself (and, in `page-end`, the
//! mmap that places code at a page end), which is what the fixture exists for.

#[cfg(target_arch = "x86_64")]
use std::convert::Infallible;
use std::process::ExitCode;

#[cfg(target_arch = "x86_64")]
use x86::{ah, gpr, page_end, report_rt_signals, xmm};

#[cfg(target_arch = "x86_64")]
fn parse_u64(s: &str) -> Result<u64, String> {
    let t = s.trim_start_matches("0x");
    u64::from_str_radix(t, 16).map_err(|e| format!("`{s}` is not a hex u64: {e}"))
}

const USAGE: &str = "usage: regflip-target gpr PATTERN | gpr-signals PATTERN | gpr-thread \
                     PATTERN | ah PATTERN | xmm LO HI | page-end";

/// `--help` and `--version` (exit 0), before anything else.
fn help_or_version() -> Option<ExitCode> {
    match std::env::args().nth(1).as_deref() {
        Some("-h" | "--help") => {
            println!("regflip-target: a program with known register contents, for the register injector's tests (x86-64)\n\n{USAGE}");
            Some(ExitCode::SUCCESS)
        }
        Some("-V" | "--version") => {
            println!("regflip-target {}", env!("CARGO_PKG_VERSION"));
            Some(ExitCode::SUCCESS)
        }
        _ => None,
    }
}

#[cfg(not(target_arch = "x86_64"))]
fn main() -> ExitCode {
    if let Some(code) = help_or_version() {
        return code;
    }
    eprintln!("regflip-target: x86-64 only");
    ExitCode::from(2)
}

#[cfg(target_arch = "x86_64")]
fn main() -> ExitCode {
    if let Some(code) = help_or_version() {
        return code;
    }
    let args: Vec<String> = std::env::args().skip(1).collect();
    let result: Result<Infallible, String> =
        match args.iter().map(String::as_str).collect::<Vec<_>>()[..] {
            ["gpr", p] => parse_u64(p).map(|p| gpr(p)),
            ["ah", p] => parse_u64(p).map(|p| ah(p)),
            ["xmm", lo, hi] => parse_u64(lo).and_then(|lo| parse_u64(hi).map(|hi| xmm(lo, hi))),
            ["gpr-signals", p] => parse_u64(p).and_then(|p| report_rt_signals().map(|()| gpr(p))),
            ["gpr-thread", p] => parse_u64(p).and_then(|p| {
                let worker = std::thread::spawn(move || -> Infallible { gpr(p) });
                match worker.join() {
                    Ok(never) => match never {},
                    Err(_) => Err("the worker thread panicked".to_string()),
                }
            }),
            ["page-end"] => page_end(),
            _ => Err(USAGE.into()),
        };
    match result {
        Ok(never) => match never {},
        Err(e) => {
            eprintln!("regflip-target: {e}");
            ExitCode::from(2)
        }
    }
}

/// The fixture's loops, x86-64 inline assembly.
#[cfg(target_arch = "x86_64")]
mod x86 {
    use std::arch::asm;
    use std::convert::Infallible;

    /// Assembly for `write(1, REG, LEN)`; clobbers rax, rdi, rsi, rdx, rcx, r11.
    macro_rules! write_stdout {
        ($reg:literal, $len:literal) => {
            concat!(
                "mov eax, 1\n",
                "mov edi, 1\n",
                "mov rsi, ",
                $reg,
                "\n",
                "mov edx, ",
                $len,
                "\n",
                "syscall"
            )
        };
    }

    /// r12 is written by `mov r12, r14` (destination) and read by `cmp r12, r15` (source).
    pub fn gpr(pattern: u64) -> ! {
        let ready = b'R';
        let mut report = [0u8; 8];
        // SAFETY: the block only writes the 8 bytes of `report` (through r9) and reads `ready`
        // (through r8), both live for ever since the block never returns; it issues write(2) on
        // fd 1 only; it does not touch the stack.
        unsafe {
            asm!(
                write_stdout!("r8", "1"),
                "2:",
                "mov r12, r14",
                "cmp r12, r15",
                "je 2b",
                "mov [r9], r12",
                write_stdout!("r9", "8"),
                "jmp 2b",
                in("r8") &ready as *const u8,
                in("r9") report.as_mut_ptr(),
                in("r14") pattern,
                in("r15") pattern,
                options(noreturn, nostack),
            )
        }
    }

    /// Writes the value of each SIGRTMIN to fd 2 (-1 if it came without one).
    extern "C" fn on_rt_signal(_: libc::c_int, info: *mut libc::siginfo_t, _: *mut libc::c_void) {
        // SAFETY: for an SA_SIGINFO handler the kernel passes a valid siginfo; si_value is only
        // read when si_code says a sigqueue filled it in.
        let value = unsafe {
            match (*info).si_code {
                libc::SI_QUEUE => (*info).si_value().sival_ptr as isize as i32,
                _ => -1,
            }
        };
        let bytes = value.to_le_bytes();
        // SAFETY: write(2) is async-signal-safe; `bytes` is a live local of 4 bytes.
        unsafe { libc::write(2, bytes.as_ptr().cast(), bytes.len()) };
    }

    pub fn report_rt_signals() -> Result<(), String> {
        // SAFETY: sigaction is plain old data; all-zero is a valid value (empty mask, no flags).
        let mut sa: libc::sigaction = unsafe { std::mem::zeroed() };
        sa.sa_sigaction = on_rt_signal as *const () as usize;
        sa.sa_flags = libc::SA_SIGINFO | libc::SA_RESTART;
        // SAFETY: `sa` is initialised and outlives the call; the handler only calls write(2).
        if unsafe { libc::sigaction(libc::SIGRTMIN(), &sa, std::ptr::null_mut()) } != 0 {
            return Err(format!("sigaction: {}", std::io::Error::last_os_error()));
        }
        Ok(())
    }

    /// AH (bits 8–15 of RAX) is read by `cmp ah, dl` with DL = byte 1 of the pattern.
    pub fn ah(pattern: u64) -> ! {
        let ready = b'R';
        let mut report = [0u8; 8];
        // SAFETY: as in `gpr`.
        unsafe {
            asm!(
                write_stdout!("r8", "1"),
                "3:",
                "mov rdx, r14",
                "shr rdx, 8",
                "2:",
                "mov rax, r14",
                "cmp ah, dl",
                "je 2b",
                "mov [r9], rax",
                write_stdout!("r9", "8"),
                "jmp 3b",
                in("r8") &ready as *const u8,
                in("r9") report.as_mut_ptr(),
                in("r14") pattern,
                options(noreturn, nostack),
            )
        }
    }

    /// xmm3 is written by `movdqa xmm3, xmm4` and read by `movdqa xmm5, xmm3`; all 128 bits are
    /// compared.
    pub fn xmm(lo: u64, hi: u64) -> ! {
        let ready = b'R';
        let pattern: [u64; 2] = [lo, hi];
        let mut report = [0u8; 16];
        // SAFETY: as in `gpr`; it also reads the 16 bytes of `pattern` through r10.
        unsafe {
            asm!(
                "movdqu xmm4, [r10]",
                write_stdout!("r8", "1"),
                "2:",
                "movdqa xmm3, xmm4",
                "movdqa xmm5, xmm3",
                "pcmpeqb xmm5, xmm4",
                "pmovmskb eax, xmm5",
                "cmp eax, 0xffff",
                "je 2b",
                "movdqu [r9], xmm3",
                write_stdout!("r9", "16"),
                "jmp 2b",
                in("r8") &ready as *const u8,
                in("r9") report.as_mut_ptr(),
                in("r10") pattern.as_ptr(),
                options(noreturn, nostack),
            )
        }
    }

    /// `inc r12; jmp -5` in the last 5 bytes of an executable page whose successor is unmapped:
    /// an injector that insists on reading 15 bytes at the instruction pointer fails here.
    pub fn page_end() -> Result<Infallible, String> {
        const LOOP: [u8; 5] = [0x49, 0xff, 0xc4, 0xeb, 0xfb]; // inc r12; jmp -5
        let page = 4096usize;
        // SAFETY: an anonymous private mapping of two fresh pages; nothing else refers to them.
        let base = unsafe {
            libc::mmap(
                std::ptr::null_mut(),
                2 * page,
                libc::PROT_READ | libc::PROT_WRITE,
                libc::MAP_PRIVATE | libc::MAP_ANONYMOUS,
                -1,
                0,
            )
        };
        if base == libc::MAP_FAILED {
            return Err(format!("mmap: {}", std::io::Error::last_os_error()));
        }
        let base = base.cast::<u8>();
        // SAFETY: the second page is ours (mapped above) and unused.
        if unsafe { libc::munmap(base.add(page).cast(), page) } != 0 {
            return Err(format!("munmap: {}", std::io::Error::last_os_error()));
        }
        // SAFETY: the first page is mapped writable; the 5 bytes end exactly at its end.
        let entry = unsafe {
            let entry = base.add(page - LOOP.len());
            std::ptr::copy_nonoverlapping(LOOP.as_ptr(), entry, LOOP.len());
            entry
        };
        // SAFETY: changes the protection of our own first page only.
        if unsafe { libc::mprotect(base.cast(), page, libc::PROT_READ | libc::PROT_EXEC) } != 0 {
            return Err(format!("mprotect: {}", std::io::Error::last_os_error()));
        }
        let mut ready = [0u8; 9];
        ready[0] = b'R';
        ready[1..].copy_from_slice(&(base as u64 + page as u64).to_le_bytes());
        // SAFETY: writes the 9 bytes of `ready` to fd 1, then jumps into the page prepared above,
        // whose loop touches only r12 and never returns.
        unsafe {
            asm!(
                write_stdout!("r8", "9"),
                "jmp r9",
                in("r8") ready.as_ptr(),
                in("r9") entry,
                options(noreturn, nostack),
            )
        }
    }
}
