//! The clock's hardware boundary: reading the CPU's own counter. Every `unsafe` of the clock is
//! here, one small function each, with its safety argument. Only the architecture being built
//! is compiled; the others are cfg-gated out.

/// What the CPU offers as a deadline counter.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Counter {
    /// x86-64 time-stamp counter, invariant (constant rate in every P-, C- and T-state).
    #[cfg_attr(not(target_arch = "x86_64"), allow(dead_code))]
    Tsc,
    /// aarch64 generic timer virtual count, with its advertised frequency (`CNTFRQ_EL0`, Hz).
    #[cfg_attr(not(target_arch = "aarch64"), allow(dead_code))]
    Cntvct { advertised_hz: u64 },
}

/// The counter this CPU offers for deadlines, or why there is none.
#[cfg(target_arch = "x86_64")]
pub fn probe() -> Result<Counter, String> {
    use core::arch::x86_64::__cpuid;
    // SAFETY: CPUID exists on every x86-64 CPU and only reads identification registers. (It is
    // a safe function on newer compilers, hence the allow.)
    #[allow(unused_unsafe)]
    let max_extended = unsafe { __cpuid(0x8000_0000) }.eax;
    if max_extended < 0x8000_0007 {
        return Err(format!(
            "CPUID has no leaf 80000007H (highest extended leaf {max_extended:#x}), so the TSC \
             cannot be shown to be invariant"
        ));
    }
    // SAFETY: as above; the leaf was just checked to exist.
    #[allow(unused_unsafe)]
    let edx = unsafe { __cpuid(0x8000_0007) }.edx;
    if edx & (1 << 8) == 0 {
        return Err(
            "CPUID.80000007H:EDX[8] (invariant TSC) is clear: the TSC may change rate \
                    or stop with the CPU's power state"
                .into(),
        );
    }
    Ok(Counter::Tsc)
}

/// Reads the counter. Not serialising: a deadline does not need instruction-exact ordering.
#[cfg(target_arch = "x86_64")]
#[inline]
pub fn read(_counter: Counter) -> u64 {
    // SAFETY: RDTSC is available on every x86-64 CPU and reads a register; the kernel does not
    // disable it for user space on Linux unless asked to per process (PR_SET_TSC), which s3res
    // never does.
    unsafe { core::arch::x86_64::_rdtsc() }
}

#[cfg(target_arch = "aarch64")]
pub fn probe() -> Result<Counter, String> {
    let freq: u64;
    // SAFETY: Linux enables EL0 access to CNTFRQ_EL0 and CNTVCT_EL0 (CNTKCTL_EL1.EL0VCTEN); the
    // instruction reads a system register into a general one and touches no memory.
    unsafe { core::arch::asm!("mrs {}, cntfrq_el0", out(reg) freq, options(nomem, nostack)) };
    if freq == 0 {
        return Err(
            "CNTFRQ_EL0 reads 0: the firmware did not set the generic timer's frequency".into(),
        );
    }
    Ok(Counter::Cntvct {
        advertised_hz: freq,
    })
}

#[cfg(target_arch = "aarch64")]
#[inline]
pub fn read(_counter: Counter) -> u64 {
    let ticks: u64;
    // SAFETY: as in `probe`; the ISB orders the read after earlier instructions, so a counter
    // value is never older than the code that asked for it.
    unsafe {
        core::arch::asm!("isb", "mrs {}, cntvct_el0", out(reg) ticks, options(nomem, nostack))
    };
    ticks
}

#[cfg(not(any(target_arch = "x86_64", target_arch = "aarch64")))]
pub fn probe() -> Result<Counter, String> {
    Err(format!(
        "no cycle counter support for {}",
        std::env::consts::ARCH
    ))
}

#[cfg(not(any(target_arch = "x86_64", target_arch = "aarch64")))]
#[inline]
pub fn read(_counter: Counter) -> u64 {
    unreachable!("probe() never offers a counter on this architecture")
}

/// Sets this thread's timer slack (`PR_SET_TIMERSLACK`): how much later than asked the kernel
/// may end a `ppoll` timeout to batch wake-ups. The default is 50 µs for normal threads; real-
/// time threads get none whatever this says.
pub fn set_timer_slack(ns: u64) -> std::io::Result<()> {
    // SAFETY: prctl with PR_SET_TIMERSLACK takes an integer and touches no memory of ours.
    let r = unsafe { libc::prctl(libc::PR_SET_TIMERSLACK, ns as libc::c_ulong, 0, 0, 0) };
    if r < 0 {
        return Err(std::io::Error::last_os_error());
    }
    Ok(())
}
