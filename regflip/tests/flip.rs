//! Register flips against `regflip-target`, a program whose register contents are known: every
//! flip must change exactly the logged bits of the logged register, as the program itself
//! observes and reports them. Each test kills and reaps its target on every path.
#![cfg(all(target_os = "linux", target_arch = "x86_64"))]

use anyhow::{bail, Context, Result};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use s3res_regflip::{inject, FloatField, OperandRole, RegFlipError, RegFlipRecord, RegFlipSpec};
use std::collections::BTreeMap;
use std::io::Read;
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{mpsc, Arc};
use std::time::{Duration, Instant};

const GPR_PATTERN: u64 = 0xa5c3_0f1e_7b2d_9468;
const XMM_LO: u64 = 0x3ff8_0000_0000_0000; // 1.5
const XMM_HI: u64 = 0xc00c_cccc_cccc_cccd; // -3.6
const REPORT_TIMEOUT: Duration = Duration::from_secs(10);

/// The running fixture; killed and reaped on drop.
struct Target {
    child: Child,
    /// The full-register value the target holds in the register under test.
    pattern: u128,
    /// Bytes per report: 8 for a GPR, 16 for xmm3.
    report_len: usize,
    bytes: mpsc::Receiver<Vec<u8>>,
    pending: Vec<u8>,
    /// Everything the target wrote to stderr.
    stderr: mpsc::Receiver<Vec<u8>>,
}

/// Forwards everything read from `from` to a channel, from a thread that ends at EOF.
fn forward(mut from: impl Read + Send + 'static) -> mpsc::Receiver<Vec<u8>> {
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        let mut buf = [0u8; 4096];
        while let Ok(n @ 1..) = from.read(&mut buf) {
            if tx.send(buf[..n].to_vec()).is_err() {
                break;
            }
        }
    });
    rx
}

impl Target {
    /// `regflip-target MODE GPR_PATTERN` (gpr, ah, gpr-signals, gpr-thread).
    fn gpr(mode: &str) -> Result<Target> {
        Target::start(&[mode, &format!("{GPR_PATTERN:x}")], GPR_PATTERN as u128, 8)
    }

    fn xmm() -> Result<Target> {
        let (lo, hi) = (format!("{XMM_LO:x}"), format!("{XMM_HI:x}"));
        let pattern = (XMM_HI as u128) << 64 | XMM_LO as u128;
        Target::start(&["xmm", &lo, &hi], pattern, 16)
    }

    fn start(args: &[&str], pattern: u128, report_len: usize) -> Result<Target> {
        let mut child = Command::new(env!("CARGO_BIN_EXE_regflip-target"))
            .args(args)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .context("starting regflip-target")?;
        let bytes = forward(child.stdout.take().expect("piped"));
        let stderr = forward(child.stderr.take().expect("piped"));
        let mut target = Target {
            child,
            pattern,
            report_len,
            bytes,
            pending: Vec::new(),
            stderr,
        };
        let ready = target.read(1)?;
        if ready != b"R" {
            bail!("regflip-target said {ready:?} instead of R");
        }
        Ok(target)
    }

    fn pid(&self) -> i32 {
        self.child.id() as i32
    }

    /// Exactly `n` bytes of the target's output, or an error after [`REPORT_TIMEOUT`].
    fn read(&mut self, n: usize) -> Result<Vec<u8>> {
        let deadline = Instant::now() + REPORT_TIMEOUT;
        while self.pending.len() < n {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.bytes.recv_timeout(left) {
                Ok(chunk) => self.pending.extend_from_slice(&chunk),
                Err(e) => bail!("no report from regflip-target within {REPORT_TIMEOUT:?}: {e}"),
            }
        }
        Ok(self.pending.drain(..n).collect())
    }

    /// Injects, checks the record against itself, and checks that the target saw exactly
    /// `pattern XOR logged bits` in the register under test.
    fn flip(&mut self, spec: &RegFlipSpec, rng: &mut ChaCha8Rng) -> Result<RegFlipRecord> {
        let rec = inject(self.pid(), spec, rng)?;
        check_record(&rec, spec.bits);
        assert_eq!(hex_value(&rec.before), self.pattern, "{rec:?}");
        self.check_report(&rec)?;
        Ok(rec)
    }

    /// Reads the target's next report and compares it with what the record says.
    fn check_report(&mut self, rec: &RegFlipRecord) -> Result<()> {
        let mut bytes = [0u8; 16];
        bytes[..self.report_len].copy_from_slice(&self.read(self.report_len)?);
        let seen = u128::from_le_bytes(bytes);
        assert_eq!(
            seen,
            self.pattern ^ rec.mask(),
            "the target saw {seen:#x}: {rec:?}"
        );
        Ok(())
    }
}

impl Drop for Target {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Kills and reaps a helper process (not a `Target`) on every path.
struct KillOnDrop(Child);

impl Drop for KillOnDrop {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// The state letter of /proc/PID/stat (`R`, `S`, `T`, `t`…).
fn proc_state(pid: i32) -> Option<char> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    stat.rsplit(')').next()?.trim().chars().next()
}

/// /proc/PID/syscall: the number of the system call the process is blocked in, first.
fn proc_syscall(pid: i32) -> String {
    std::fs::read_to_string(format!("/proc/{pid}/syscall")).unwrap_or_default()
}

/// Polls `cond` until it holds (true) or [`REPORT_TIMEOUT`] passes (false).
fn wait_for(mut cond: impl FnMut() -> bool) -> bool {
    let deadline = Instant::now() + REPORT_TIMEOUT;
    while !cond() {
        if Instant::now() > deadline {
            return false;
        }
        std::thread::yield_now();
    }
    true
}

fn rng(test: &str, default_seed: u64) -> ChaCha8Rng {
    let seed = std::env::var("REGFLIP_SEED")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(default_seed);
    eprintln!("{test}: seed {seed} (set REGFLIP_SEED to change)");
    ChaCha8Rng::seed_from_u64(seed)
}

fn hex_value(s: &str) -> u128 {
    u128::from_str_radix(s.trim_start_matches("0x"), 16).expect("record holds hex")
}

fn spec(role: OperandRole, bits: u32, registers: &[&str]) -> RegFlipSpec {
    RegFlipSpec {
        role,
        bits,
        registers: Some(registers.iter().map(|s| s.to_string()).collect()),
        ..Default::default()
    }
}

/// Checks the record against itself: the logged before/after differ in exactly the logged bits.
fn check_record(rec: &RegFlipRecord, bits: u32) {
    assert_eq!(rec.bits.len(), bits as usize, "{rec:?}");
    assert!(
        rec.bits.windows(2).all(|w| w[0] < w[1]),
        "distinct: {rec:?}"
    );
    assert_eq!(
        hex_value(&rec.before) ^ hex_value(&rec.after),
        rec.mask(),
        "{rec:?}"
    );
}

#[test]
fn a_source_flip_of_r12_changes_exactly_the_logged_bits() -> Result<()> {
    let mut rng = rng("source r12", 1);
    let mut target = Target::gpr("gpr")?;
    for round in 0..60 {
        let bits = 1 + round % 4;
        let rec = target.flip(&spec(OperandRole::Source, bits, &["r12"]), &mut rng)?;
        assert_eq!(
            (rec.register.as_str(), rec.operand.as_str()),
            ("r12", "r12")
        );
        assert_eq!(rec.role, OperandRole::Source);
        assert_eq!(rec.instruction, "cmp r12, r15");
        assert_eq!(
            rec.resume_ip, rec.ip,
            "a source flip happens before the instruction"
        );
        assert_eq!(rec.tid, target.pid());
        let line = serde_json::to_string(&rec)?;
        let back: RegFlipRecord = serde_json::from_str(&line)?;
        assert_eq!(back, rec, "the record survives a JSON round trip");
    }
    Ok(())
}

#[test]
fn a_destination_flip_of_r12_lands_after_the_write() -> Result<()> {
    let mut rng = rng("destination r12", 2);
    let mut target = Target::gpr("gpr")?;
    for _ in 0..40 {
        let rec = target.flip(&spec(OperandRole::Destination, 2, &["r12"]), &mut rng)?;
        assert_eq!(rec.role, OperandRole::Destination);
        assert_eq!(rec.instruction, "mov r12, r14");
        assert_eq!(rec.resume_ip, rec.ip + 3, "stepped past the 3-byte mov");
    }
    Ok(())
}

#[test]
fn a_flip_of_ah_hits_bits_8_to_15_of_rax() -> Result<()> {
    let mut rng = rng("ah", 3);
    let mut target = Target::gpr("ah")?;
    let mut hit = [false; 64];
    for _ in 0..100 {
        let rec = target.flip(&spec(OperandRole::Source, 1, &["ah"]), &mut rng)?;
        assert_eq!((rec.register.as_str(), rec.operand.as_str()), ("rax", "ah"));
        assert_eq!(rec.instruction, "cmp ah, dl");
        assert!(rec.bits.iter().all(|b| (8..16).contains(b)), "{rec:?}");
        rec.bits.iter().for_each(|&b| hit[b as usize] = true);
    }
    assert!(hit[8..16].iter().all(|&h| h), "all 8 bits of AH: {hit:?}");
    Ok(())
}

#[test]
fn xmm3_flips_change_exactly_the_logged_bits_in_all_128() -> Result<()> {
    let mut rng = rng("xmm3", 4);
    let mut target = Target::xmm()?;
    let mut high_lane_hit = false;
    for round in 0..80 {
        let bits = 1 + round % 3;
        let rec = target.flip(&spec(OperandRole::Any, bits, &["xmm3"]), &mut rng)?;
        assert_eq!(rec.register, "xmm3");
        let expected_instruction = match rec.role {
            OperandRole::Source => "movdqa xmm5, xmm3",
            _ => "movdqa xmm3, xmm4",
        };
        assert_eq!(rec.instruction, expected_instruction, "{rec:?}");
        high_lane_hit |= rec.bits.iter().any(|&b| b >= 64);
    }
    assert!(high_lane_hit, "flips reach the upper 64 bits of xmm3");
    Ok(())
}

#[test]
fn float_field_flips_stay_in_their_field_and_lane() -> Result<()> {
    let mut rng = rng("float fields", 5);
    let mut target = Target::xmm()?;
    let cases = [
        (FloatField::Sign, 0u8, 63..64u32),
        (FloatField::Sign, 1, 127..128),
        (FloatField::Exponent, 0, 52..63),
        (FloatField::Exponent, 1, 116..127),
        (FloatField::Mantissa, 0, 0..52),
        (FloatField::Mantissa, 1, 64..116),
    ];
    for (field, lane, range) in cases {
        for _ in 0..8 {
            let spec = RegFlipSpec {
                field,
                lane,
                ..spec(OperandRole::Source, 1, &["xmm3"])
            };
            let rec = target.flip(&spec, &mut rng)?;
            assert_eq!((rec.field, rec.lane), (field, Some(lane)));
            assert!(
                rec.bits.iter().all(|b| range.contains(b)),
                "{field} lane {lane}: {rec:?}"
            );
        }
    }
    Ok(())
}

#[test]
fn flipped_positions_cover_the_whole_64_bit_width() -> Result<()> {
    let mut rng = rng("coverage", 6);
    let mut target = Target::gpr("gpr")?;
    let mut count = [0u32; 64];
    let flips = 1000;
    for _ in 0..flips {
        let rec = target.flip(&spec(OperandRole::Any, 1, &["r12"]), &mut rng)?;
        count[rec.bits[0] as usize] += 1;
    }
    let (min, max) = (count.iter().min().unwrap(), count.iter().max().unwrap());
    eprintln!("{flips} single-bit flips of r12: every bit hit between {min} and {max} times");
    assert!(
        count.iter().all(|&c| c > 0),
        "positions never hit: {count:?}"
    );
    assert!(
        count[8..].iter().sum::<u32>() > flips / 2,
        "not just the low byte"
    );
    Ok(())
}

#[test]
fn code_at_the_end_of_a_mapping_is_read_up_to_the_page_end() -> Result<()> {
    let mut rng = rng("page end", 7);
    let mut target = Target::start(&["page-end"], 0, 8)?;
    let page_end = u64::from_le_bytes(target.read(8)?.try_into().unwrap());
    for _ in 0..10 {
        let rec = inject(
            target.pid(),
            &spec(OperandRole::Source, 1, &["r12"]),
            &mut rng,
        )?;
        check_record(&rec, 1);
        assert_eq!(rec.instruction, "inc r12");
        assert_eq!(rec.instruction_bytes, "49ffc4");
        assert_eq!(rec.ip, page_end - 5);
        assert_eq!(rec.bytes_read, 5, "only the 5 mapped bytes are read");
    }
    Ok(())
}

#[test]
fn a_thread_blocked_in_a_system_call_is_left_untouched() -> Result<()> {
    let mut rng = rng("blocked", 8);
    let sleeper = KillOnDrop(Command::new("sleep").arg("30").spawn()?);
    let pid = sleeper.0.id() as i32;
    // The system call it blocks in: clock_nanosleep (230) or, with older libcs, nanosleep (35).
    let blocked_in = || {
        let call: Option<u64> = proc_syscall(pid).split(' ').next()?.parse().ok();
        call.filter(|_| proc_state(pid) == Some('S'))
    };
    let sleeping = || matches!(blocked_in(), Some(230 | 35));
    assert!(wait_for(sleeping), "sleep never blocked in its sleep");
    let call = blocked_in().context("sleep woke up")?;
    let result = inject(pid, &RegFlipSpec::default(), &mut rng);
    // Detached, it resumes its sleep (the same call, or restart_syscall = 219): it must get
    // back to sleeping, not stay stopped (`t`). Right after the detach it may briefly run.
    assert!(
        wait_for(|| matches!(blocked_in(), Some(c) if c == call || c == 219)),
        "not back asleep: {:?}",
        proc_state(pid)
    );
    match result {
        Err(RegFlipError::InSyscall { syscall, .. }) => assert_eq!(syscall, call),
        other => panic!("expected InSyscall, got {other:?}"),
    }
    Ok(())
}

/// `inject_after_syscall` follows a thread blocked in `read` out of it once its input comes,
/// and flips a register of its own code; the process is left running, not traced.
#[test]
fn a_blocked_thread_is_followed_out_of_its_system_call() -> Result<()> {
    use std::io::Write;
    let mut rng = rng("follow", 9);
    let mut cat = KillOnDrop(
        Command::new("cat")
            .stdin(Stdio::piped())
            .stdout(Stdio::null())
            .spawn()?,
    );
    let pid = cat.0.id() as i32;
    let reading =
        || proc_syscall(pid).split(' ').next() == Some("0") && proc_state(pid) == Some('S');
    assert!(wait_for(reading), "cat never blocked in read");
    let mut stdin = cat.0.stdin.take().expect("piped");
    // Its input comes 150 ms after the injection begins, from another thread.
    let writer = std::thread::spawn(move || {
        std::thread::sleep(Duration::from_millis(150));
        let _ = stdin.write_all(b"line\n");
        stdin
    });
    let rec = s3res_regflip::inject_after_syscall(
        pid,
        &RegFlipSpec::default(),
        &mut rng,
        Duration::from_secs(5),
        32,
    )?;
    let _stdin = writer.join().expect("writer thread");
    check_record(&rec, 1);
    assert!(rec.syscall_stops >= 1, "it was followed: {rec:?}");
    assert!(rec.skipped <= 32, "{rec:?}");
    assert!(
        rec.pause_ns >= 100_000_000,
        "it waited for the input: {rec:?}"
    );
    // Released: running or asleep again, or dead of the flip, but never left in a trace stop.
    assert!(
        wait_for(|| !matches!(proc_state(pid), Some('t' | 'T'))),
        "left stopped: {:?}",
        proc_state(pid)
    );
    Ok(())
}

/// A thread whose system call does not return within the patience is stopped where it is,
/// reported as blocked, and released back into its call.
#[test]
fn a_call_that_does_not_return_in_time_is_reported_and_left_asleep() -> Result<()> {
    let mut rng = rng("follow-timeout", 10);
    let sleeper = KillOnDrop(Command::new("sleep").arg("30").spawn()?);
    let pid = sleeper.0.id() as i32;
    let asleep = || proc_state(pid) == Some('S');
    assert!(wait_for(asleep), "sleep never slept");
    let result = s3res_regflip::inject_after_syscall(
        pid,
        &RegFlipSpec::default(),
        &mut rng,
        Duration::from_millis(200),
        8,
    );
    assert!(
        matches!(result, Err(RegFlipError::InSyscall { .. })),
        "expected InSyscall, got {result:?}"
    );
    assert!(wait_for(asleep), "not back asleep: {:?}", proc_state(pid));
    Ok(())
}

#[test]
fn bad_specs_and_missing_processes_are_clean_errors() -> Result<()> {
    let mut rng = rng("errors", 9);
    let mut child = KillOnDrop(Command::new("true").spawn()?);
    let pid = child.0.id() as i32;
    // Dead and not yet reaped (a replica an earlier flip crashed): the kernel refuses to
    // attach with EPERM, which must read as gone, not as a missing privilege.
    assert!(
        wait_for(|| proc_state(pid) == Some('Z')),
        "true never exited"
    );
    assert!(matches!(
        inject(pid, &RegFlipSpec::default(), &mut rng),
        Err(RegFlipError::Gone { tid }) if tid == pid
    ));
    child.0.wait()?;
    assert!(matches!(
        inject(pid, &RegFlipSpec::default(), &mut rng),
        Err(RegFlipError::Gone { tid }) if tid == pid
    ));
    let zero_bits = RegFlipSpec {
        bits: 0,
        ..Default::default()
    };
    assert!(matches!(
        inject(1, &zero_bits, &mut rng),
        Err(RegFlipError::InvalidSpec(_))
    ));
    let unknown = spec(OperandRole::Any, 1, &["r16"]);
    assert!(
        matches!(inject(1, &unknown, &mut rng), Err(RegFlipError::InvalidSpec(m)) if m.contains("r16"))
    );
    let other = RegFlipSpec {
        tid: Some(pid),
        ..Default::default()
    };
    assert!(matches!(
        inject(std::process::id() as i32, &other, &mut rng),
        Err(RegFlipError::NotAThreadOf { .. })
    ));
    Ok(())
}

#[test]
fn signals_arriving_during_injections_are_delivered_once_with_their_value() -> Result<()> {
    let mut rng = rng("signals", 10);
    let mut target = Target::gpr("gpr-signals")?;
    let pid = target.pid();
    let signals = 3000;
    let done = Arc::new(AtomicBool::new(false));
    let sender = {
        let done = done.clone();
        std::thread::spawn(move || {
            for value in 0..signals {
                let sent = replica_rt::sys::sigqueue(pid, libc::SIGRTMIN(), value);
                if value % 16 == 0 {
                    std::thread::sleep(Duration::from_micros(100));
                }
                if sent.is_err() {
                    break;
                }
            }
            done.store(true, Ordering::SeqCst);
        })
    };
    // Destination flips single-step the thread, so signals meet the injector mid-step.
    let (mut injections, mut deferred, mut stepped, mut misses) = (0, 0, 0, 0);
    while !done.load(Ordering::SeqCst) {
        let rec = match inject(pid, &spec(OperandRole::Destination, 1, &["r12"]), &mut rng) {
            Ok(rec) => rec,
            // Stopped inside the handler, which reaches its write(2) without writing r12.
            Err(RegFlipError::NoCandidate { .. } | RegFlipError::InSyscall { .. }) => {
                misses += 1;
                continue;
            }
            Err(e) => return Err(e.into()),
        };
        injections += 1;
        deferred += rec.signals_deferred.len();
        stepped += usize::from(rec.role == OperandRole::Destination);
        // A flip inside the signal handler is undone by sigreturn: only a flip in the loop
        // is reported.
        if rec.instruction == "mov r12, r14" {
            target.check_report(&rec)?;
        }
    }
    sender.join().expect("sender thread");
    let mut received: BTreeMap<i32, u32> = BTreeMap::new();
    let mut bytes = Vec::new();
    let deadline = Instant::now() + REPORT_TIMEOUT;
    while bytes.len() < 4 * signals as usize && Instant::now() < deadline {
        if let Ok(chunk) = target.stderr.recv_timeout(Duration::from_millis(100)) {
            bytes.extend_from_slice(&chunk);
        }
    }
    for value in bytes.chunks_exact(4) {
        *received
            .entry(i32::from_le_bytes(value.try_into().unwrap()))
            .or_default() += 1;
    }
    eprintln!(
        "{injections} injections ({misses} attempts found no r12 destination), \
         {deferred} signals re-sent by the injector"
    );
    assert!(stepped > 0, "no injection single-stepped");
    assert!(
        received.values().all(|&n| n == 1),
        "duplicates: {received:?}"
    );
    assert_eq!(
        received.keys().copied().collect::<Vec<_>>(),
        (0..signals).collect::<Vec<_>>()
    );
    Ok(())
}

#[test]
fn the_asked_thread_is_injected_and_the_main_thread_by_default() -> Result<()> {
    let mut rng = rng("threads", 11);
    let mut target = Target::gpr("gpr-thread")?;
    let pid = target.pid();
    let worker: i32 = std::fs::read_dir(format!("/proc/{pid}/task"))?
        .filter_map(|e| e.ok()?.file_name().to_str()?.parse().ok())
        .find(|&tid| tid != pid)
        .context("the worker thread")?;
    for _ in 0..20 {
        let on_worker = RegFlipSpec {
            tid: Some(worker),
            ..spec(OperandRole::Source, 1, &["r12"])
        };
        let rec = target.flip(&on_worker, &mut rng)?;
        assert_eq!((rec.pid, rec.tid), (pid, worker));
    }
    // The main thread is blocked joining the worker: no register fault there.
    assert!(matches!(
        inject(pid, &spec(OperandRole::Source, 1, &["r12"]), &mut rng),
        Err(RegFlipError::InSyscall { tid, .. }) if tid == pid
    ));
    Ok(())
}

#[test]
fn a_job_control_stopped_process_is_not_injected_and_stays_stopped() -> Result<()> {
    let mut rng = rng("stopped", 12);
    let target = Target::gpr("gpr")?;
    let pid = target.pid();
    replica_rt::sys::kill(pid, libc::SIGSTOP)?;
    assert!(
        wait_for(|| proc_state(pid) == Some('T')),
        "SIGSTOP did not stop it"
    );
    let result = inject(pid, &RegFlipSpec::default(), &mut rng);
    assert!(
        matches!(result, Err(RegFlipError::JobControlStopped { sig, .. }) if sig == libc::SIGSTOP),
        "{result:?}"
    );
    // Detached, it wakes up briefly and re-enters its group-stop.
    assert!(
        wait_for(|| proc_state(pid) == Some('T')),
        "not stopped again: {:?}",
        proc_state(pid)
    );
    let status = std::fs::read_to_string(format!("/proc/{pid}/status"))?;
    assert!(status.contains("TracerPid:\t0"), "{status}");
    Ok(())
}
