//! Breaking copy-on-write sharing after a fork.
//!
//! After `fork` the parent and the child share every private page until one of them writes to
//! it. A bit flip in such a shared physical page would corrupt both replicas at once, and the
//! vote could not see it. [`break_cow_sharing`] writes once to every resident page of every
//! private writable mapping, so the kernel gives the caller its own copy of each — but for
//! the stack below the stack pointer (`DeadStack`), which holds nothing live: each replica
//! writes such a page before it reads from it, and that write copies it then; a flip in it
//! while it is shared reaches neither. Read-only private pages (the relocated read-only data,
//! which `memory::lock` protects once start-up is over) are left shared too: nothing writes
//! them, and a flip in one hits donor and child alike, as a flip in the program's text would
//! hit every replica (the trade-off is in `memory::protect_relocated_data`).
//!
//! The private writable mappings are found with the `PROCMAP_QUERY` ioctl on `/proc/self/maps`
//! (Linux ≥ 6.11): one call per mapping, the kernel skipping to the next readable and writable
//! one, with no text to format and parse. Older kernels answer ENOTTY (or EINVAL), and the walk
//! then reads the file's text, as it did before (`/proc/self/maps` parsed in place from a fixed
//! stack buffer). Each run of resident pages is broken with one `madvise(MADV_POPULATE_WRITE)`
//! (Linux ≥ 5.14): the kernel write-faults the run in one call instead of one trap per page.
//! Older kernels answer EINVAL, and the walk then writes to the pages one by one.
//!
//! **The donor lists the mappings, the child walks them.** Opening `/proc/self/maps` is the
//! dearest single system call of a fork child's walk (15–20 µs on the AMD host of
//! docs/results.md, stop 42; the first open in a new process), and the child's address space is
//! its donor's at the fork. So each replica keeps its own maps file open (`open_own_maps`,
//! at start and, in a fork child, once it has joined), and the donor lists its private writable
//! mappings with `PROCMAP_QUERY` on it right before `_Fork` (`take_snapshot`): nothing runs
//! in between that could map or unmap memory (the handler's own calls do not), so the list is
//! exactly the child's. The list joins mappings that touch (the stack's two parts, a
//! program's data and bss), so the child asks `mincore` once per stretch of memory, not per
//! mapping. The child walks the list (`break_cow_sharing_after_fork`) and opens nothing.
//! Every signal that can wait is blocked from before the list until the child has joined
//! (`restart`), so no handler of the component's own maps or unmaps memory in between.
//! Where the list could not be made (no kept fd, no `PROCMAP_QUERY`, the fd no longer the file
//! it was, a query that failed part of the way, more mappings than the list holds) the child
//! walks as before, from its own maps file.
//!
//! The walk runs in a fork child, the list in its donor, both inside the restart signal handler
//! or at the release of a deferred restart (`restart`), so nothing here allocates or takes a
//! lock, and the only system calls touch no user-space state (`open`, `fcntl`, `fstat`,
//! `ioctl`, `read`, `close`, `mincore`, `madvise`).

use std::sync::atomic::{AtomicBool, AtomicI32, AtomicU64, AtomicUsize, Ordering};

/// Bytes of `/proc/self/maps` read per `read` call.
const READ_BUF: usize = 4096;
/// Bytes of one maps line kept. Longer lines only have a long path cut off, and the fields we
/// need (range, permissions, and the short `[name]` of special mappings) fit well within.
const LINE_MAX: usize = 256;
/// Pages asked about per `mincore` call (its result vector lives on the stack).
const MINCORE_PAGES: usize = 1024;

/// Why a walk could not be done (an errno value, so the error needs no allocation).
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("reading /proc/self/maps failed: errno {errno}")]
pub struct WalkError {
    pub errno: i32,
}

/// What a walk did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct WalkStats {
    /// Private writable mappings visited (from a donor's list, adjacent ones count as one).
    pub mappings: usize,
    /// Resident pages written to.
    pub pages_touched: usize,
}

static PAGE_SIZE: AtomicUsize = AtomicUsize::new(0);

/// The page size, cached on first use. `init` calls this before installing the restart handler,
/// so the handler only ever takes the cached value (an atomic load).
pub fn page_size() -> usize {
    let cached = PAGE_SIZE.load(Ordering::Relaxed);
    if cached != 0 {
        return cached;
    }
    // SAFETY: sysconf takes an integer and returns one.
    let size = match unsafe { libc::sysconf(libc::_SC_PAGESIZE) } {
        n if n > 0 => n as usize,
        // Linux always answers; 4 KiB is the smallest page any Linux platform uses, so walking
        // with it visits every page (some twice) rather than missing any.
        _ => 4096,
    };
    PAGE_SIZE.store(size, Ordering::Relaxed);
    size
}

/// Writes to every resident page of every private writable mapping (`rw-p` in
/// `/proc/self/maps`, except the kernel's `[vsyscall]`, `[vvar]` and `[vdso]`), so that this
/// process shares no physical page that holds live data with its fork parent or children.
/// Non-resident pages are skipped: nothing is shared there, and touching them would only cost
/// memory (or a SIGBUS for a file mapping past the end of its file). So is dead memory (the
/// module's doc).
///
/// Async-signal-safe: no allocation, no lock.
///
/// # Safety
///
/// No other thread may run while this walks: each page is read and written back, and a write by
/// another thread in between would be lost. In the restart handler this holds because the forked
/// child has only the one thread; elsewhere, call it only in a single-threaded process.
pub unsafe fn break_cow_sharing() -> Result<WalkStats, WalkError> {
    let fd = open_maps()?;
    let result = walk_maps(fd);
    close(fd);
    result
}

/// [`break_cow_sharing`] in a fork child: from the mappings its donor listed right before the
/// fork ([`take_snapshot`]), without opening anything; from the child's own maps file where the
/// donor made no list.
///
/// # Safety
///
/// As [`break_cow_sharing`]; and the caller must be the child of the fork that followed the
/// donor's [`take_snapshot`], before it has mapped or unmapped anything.
pub(crate) unsafe fn break_cow_sharing_after_fork() -> Result<WalkStats, WalkError> {
    let Some(len) = SNAPSHOT.len() else {
        // SAFETY: the caller's contract is this one's.
        return unsafe { break_cow_sharing() };
    };
    let mut stats = WalkStats::default();
    let dead = DeadStack::now();
    for (start, end) in SNAPSHOT.ranges(len) {
        stats.mappings += 1;
        for (from, to) in dead.live_parts(start, end) {
            stats.pages_touched += touch_resident(from, to);
        }
    }
    Ok(stats)
}

/// Mappings a donor's list holds at most; a process with more private writable ones (a
/// program with very many libraries) gives its child no list, and the child reads its maps.
const SNAPSHOT_MAX: usize = 128;

/// The donor's list of its private writable mappings, made right before `_Fork` and inherited
/// by the child with the rest of its memory. Atomics, because a signal handler writes it.
struct Snapshot {
    /// Mappings listed, or [`Snapshot::NONE`] when there is no valid list.
    len: AtomicUsize,
    starts: [AtomicUsize; SNAPSHOT_MAX],
    ends: [AtomicUsize; SNAPSHOT_MAX],
}

impl Snapshot {
    const NONE: usize = usize::MAX;

    fn len(&self) -> Option<usize> {
        match self.len.load(Ordering::SeqCst) {
            Self::NONE => None,
            n => Some(n.min(SNAPSHOT_MAX)),
        }
    }

    fn ranges(&self, len: usize) -> impl Iterator<Item = (usize, usize)> + '_ {
        (0..len).map(|i| {
            (
                self.starts[i].load(Ordering::Relaxed),
                self.ends[i].load(Ordering::Relaxed),
            )
        })
    }
}

static SNAPSHOT: Snapshot = Snapshot {
    len: AtomicUsize::new(Snapshot::NONE),
    starts: [const { AtomicUsize::new(0) }; SNAPSHOT_MAX],
    ends: [const { AtomicUsize::new(0) }; SNAPSHOT_MAX],
};

/// This process's own maps file, kept open for [`take_snapshot`] (-1: none), and its device and
/// inode, so that an fd number the component closed and reused is never taken for it.
static OWN_MAPS: AtomicI32 = AtomicI32::new(-1);
static OWN_MAPS_ID: AtomicU64 = AtomicU64::new(0);
static OWN_MAPS_DEV: AtomicU64 = AtomicU64::new(0);

/// The lowest fd number the kept maps file is moved to: out of the low numbers a program may
/// expect its own first `open` to get.
const OWN_MAPS_FLOOR: libc::c_int = 64;

/// Opens this process's maps file and keeps it for [`take_snapshot`]; closes the one inherited
/// from a donor first (it shows the donor's mappings, not ours). At start, and in a fork child
/// once it has joined. Async-signal-safe (`close`, `open`, `fcntl`, `fstat`). Best effort: without
/// it a child of ours opens its own maps file, as it always did.
pub(crate) fn open_own_maps() {
    let old = OWN_MAPS.swap(-1, Ordering::SeqCst);
    if old >= 0 && same_file(old) {
        close(old);
    }
    let Ok(fd) = open_maps() else { return };
    // SAFETY: fcntl(F_DUPFD_CLOEXEC) on an fd we own returns a new fd or -1; nothing else.
    let high = unsafe { libc::fcntl(fd, libc::F_DUPFD_CLOEXEC, OWN_MAPS_FLOOR) };
    let fd = if high >= 0 {
        close(fd);
        high
    } else {
        fd
    };
    let Some((dev, ino)) = file_id(fd) else {
        close(fd);
        return;
    };
    OWN_MAPS_DEV.store(dev, Ordering::SeqCst);
    OWN_MAPS_ID.store(ino, Ordering::SeqCst);
    OWN_MAPS.store(fd, Ordering::SeqCst);
}

/// Whether `fd` is still the maps file [`open_own_maps`] opened (the component may have closed
/// the number and opened something else on it). A component that closed it and opened its own
/// `/proc/self/maps` on the same number passes (same inode): that file lists the same mappings,
/// and a fork child of ours closes it as it would ours, which that component would not expect
/// of a number it had closed once.
fn same_file(fd: libc::c_int) -> bool {
    file_id(fd).is_some_and(|(dev, ino)| {
        dev == OWN_MAPS_DEV.load(Ordering::SeqCst) && ino == OWN_MAPS_ID.load(Ordering::SeqCst)
    })
}

/// The device and inode of what `fd` is open on (`fstat`); `None` for a closed fd.
/// Async-signal-safe.
pub(crate) fn file_id(fd: libc::c_int) -> Option<(u64, u64)> {
    let mut st = std::mem::MaybeUninit::<libc::stat>::uninit();
    // SAFETY: fstat writes one `struct stat` into `st`, which is large enough, and is read only
    // after it succeeded.
    if unsafe { libc::fstat(fd, st.as_mut_ptr()) } != 0 {
        return None;
    }
    // SAFETY: fstat succeeded, so `st` is initialised.
    let st = unsafe { st.assume_init() };
    // dev_t and ino_t are u64 on x86-64, narrower on some other targets.
    #[allow(clippy::unnecessary_cast)]
    Some((st.st_dev as u64, st.st_ino as u64))
}

/// Lists this process's private writable mappings for the child of the fork about to follow
/// (see the module doc). Async-signal-safe: `fstat` and `ioctl` on the kept maps file, atomics.
/// With no kept file, no `PROCMAP_QUERY`, or too many mappings, there is no list, and the child
/// reads its own maps file.
pub(crate) fn take_snapshot() {
    SNAPSHOT.len.store(Snapshot::NONE, Ordering::SeqCst);
    let fd = OWN_MAPS.load(Ordering::SeqCst);
    if fd < 0 || NO_PROCMAP_QUERY.load(Ordering::Relaxed) || !same_file(fd) {
        return;
    }
    let mut n = 0;
    let mut full = false;
    let listed = query_each_private_writable(fd, &mut |start, end| {
        // A mapping that starts where the last one listed ends joins it: the child's walk then
        // asks `mincore` and `madvise` once for both. The main thread's stack comes in two
        // mappings (`memory::lock` locks the part below the stack pointer on fault), and so do
        // a program's data and bss; joined, the stack's dead part is one stretch the walk skips.
        if n > 0 && SNAPSHOT.ends[n - 1].load(Ordering::Relaxed) == start {
            SNAPSHOT.ends[n - 1].store(end, Ordering::Relaxed);
            return Walk::GoOn;
        }
        if n == SNAPSHOT_MAX {
            // No list then: the child reads its maps file, and we ask no more.
            full = true;
            return Walk::Stop;
        }
        SNAPSHOT.starts[n].store(start, Ordering::Relaxed);
        SNAPSHOT.ends[n].store(end, Ordering::Relaxed);
        n += 1;
        Walk::GoOn
    });
    match listed {
        Ok(()) if !full => SNAPSHOT.len.store(n, Ordering::SeqCst),
        // Refused at once (a kernel before 6.11, a seccomp filter): not asked again, here or in
        // the walks.
        Err(QueryError::Unsupported) => NO_PROCMAP_QUERY.store(true, Ordering::Relaxed),
        _ => {}
    }
}

fn walk_maps(fd: libc::c_int) -> Result<WalkStats, WalkError> {
    let mut stats = WalkStats::default();
    let dead = DeadStack::now();
    for_each_private_writable(fd, |start, end| {
        stats.mappings += 1;
        for (from, to) in dead.live_parts(start, end) {
            stats.pages_touched += touch_resident(from, to);
        }
    })?;
    Ok(stats)
}

/// The part of the main thread's stack below the stack pointer: it holds nothing the process
/// will read before it writes it again. The walk leaves its pages shared; a bit flip in one of
/// them reaches neither replica, since each writes such a page (and so gets its own copy of
/// it, by that write) before it reads from it. They are 5 of a small replica's 45 shared
/// pages at a restart: at start [`crate::memory::lock`] keeps 32 KiB below the stack pointer
/// resident, deeper than the main loop runs.
///
/// Only the main thread's stack, as [`note_main_stack`] recorded it at start: a walk that
/// runs on another stack (an alternate signal stack or a coroutine's, which may be carved out
/// of a larger mapping that holds live data below it) skips nothing.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct DeadStack {
    /// An address in the walk's own stack frame: the mapping that holds it is the stack the
    /// walk runs on.
    here: usize,
    /// Pages of that mapping below this address are below the stack pointer (page-aligned,
    /// one page below `here`'s, to spare; the walk's own callees, below it, write their
    /// frames anyway). 0 (nothing skipped) when `here` is not on the main thread's stack.
    floor: usize,
    /// The main thread's stack mapping's start, as recorded: nothing below it is taken for
    /// dead stack, whatever range holds it (the donor's list joins adjacent mappings, and a
    /// mapping placed right below the stack would join it).
    low: usize,
}

impl DeadStack {
    /// Where it is now: `here` is in the frame of [`crate::memory::stack_pointer`], which is
    /// not inlined, so below every frame still live (the walk's callers, the signal frame, the
    /// interrupted code's).
    fn now() -> Self {
        let page = page_size();
        let here = crate::memory::stack_pointer();
        let (low, high) = (
            MAIN_STACK_LOW.load(Ordering::Relaxed),
            MAIN_STACK_HIGH.load(Ordering::Relaxed),
        );
        let on_main_stack = low <= here && here < high;
        Self {
            here,
            floor: if on_main_stack {
                (here & !(page - 1)).saturating_sub(page)
            } else {
                0
            },
            low,
        }
    }

    /// The parts of the range `[start, end)` that are not below the stack pointer: all of it,
    /// or for the range that holds the stack the walk runs on, what lies below the stack's
    /// recorded start and what lies from `floor` up. An empty part is `(x, x)`.
    fn live_parts(&self, start: usize, end: usize) -> [(usize, usize); 2] {
        let dead_from = start.max(self.low);
        if start <= self.here && self.here < end && dead_from < self.floor {
            [(start, dead_from), (self.floor, end)]
        } else {
            [(start, end), (end, end)]
        }
    }
}

/// The main thread's stack mapping (`[stack]`), as [`note_main_stack`] recorded it; empty
/// (0, 0) until then.
static MAIN_STACK_LOW: AtomicUsize = AtomicUsize::new(0);
static MAIN_STACK_HIGH: AtomicUsize = AtomicUsize::new(0);

/// Records the main thread's stack mapping `[low, high)` (`[stack]` in `/proc/self/maps`,
/// read at start by [`crate::memory::lock`]), so that the walk knows a stack pointer there
/// for the main thread's. Fork children inherit it, with the layout it describes.
pub(crate) fn note_main_stack(low: usize, high: usize) {
    MAIN_STACK_LOW.store(low, Ordering::Relaxed);
    MAIN_STACK_HIGH.store(high, Ordering::Relaxed);
}

/// Calls `visit(start, end)` for each private, readable and writable, not executable mapping
/// (`rw-p` in `/proc/self/maps`; the kernel's `[vsyscall]`, `[vvar]` and `[vdso]` are never
/// such) of the maps file open on `fd`, in address order: asked of the kernel mapping by
/// mapping where it answers `PROCMAP_QUERY`, else read from the file's text.
fn for_each_private_writable(
    fd: libc::c_int,
    mut visit: impl FnMut(usize, usize),
) -> Result<(), WalkError> {
    if !NO_PROCMAP_QUERY.load(Ordering::Relaxed) {
        let mut each = |start, end| {
            visit(start, end);
            Walk::GoOn
        };
        match query_each_private_writable(fd, &mut each) {
            Ok(()) => return Ok(()),
            // Refused at once (a kernel before 6.11, a seccomp filter): not tried again.
            // Nothing was visited.
            Err(QueryError::Unsupported) => NO_PROCMAP_QUERY.store(true, Ordering::Relaxed),
            // Failed part of the way: the text visits every mapping again (one already made
            // private stays private; touching it again costs a little time, nothing else).
            Err(QueryError::Failed) => {}
        }
    }
    for_each_line(
        |buf| read(fd, buf),
        |line| {
            if let Some(m) = parse_line(line) {
                if m.perms == *b"rw-p" && !m.special {
                    visit(m.start, m.end);
                }
            }
        },
    )
}

/// Set once `PROCMAP_QUERY` was refused at its first call (unknown to a kernel before 6.11, or
/// filtered): text from then on, in this process and the children it forks.
static NO_PROCMAP_QUERY: AtomicBool = AtomicBool::new(false);

/// `struct procmap_query` of `linux/fs.h` (Linux ≥ 6.11), the argument of `PROCMAP_QUERY`.
#[repr(C)]
#[derive(Default)]
struct ProcmapQuery {
    size: u64,
    query_flags: u64,
    query_addr: u64,
    vma_start: u64,
    vma_end: u64,
    vma_flags: u64,
    vma_page_size: u64,
    vma_offset: u64,
    inode: u64,
    dev_major: u32,
    dev_minor: u32,
    vma_name_size: u32,
    build_id_size: u32,
    vma_name_addr: u64,
    build_id_addr: u64,
}

/// `_IOWR('f', 17, struct procmap_query)`.
const PROCMAP_QUERY: libc::c_ulong =
    crate::sys::iowr(b'f', 17, std::mem::size_of::<ProcmapQuery>());
// The kernel's layout (104 bytes) and number, as `linux/fs.h` of 6.11 defines them.
const _: () = assert!(std::mem::size_of::<ProcmapQuery>() == 104);
const _: () = assert!(PROCMAP_QUERY == 0xC068_6611);
const PROCMAP_QUERY_VMA_READABLE: u64 = 0x01;
const PROCMAP_QUERY_VMA_WRITABLE: u64 = 0x02;
const PROCMAP_QUERY_VMA_EXECUTABLE: u64 = 0x04;
const PROCMAP_QUERY_VMA_SHARED: u64 = 0x08;
/// No mapping at the address: the next one (that matches the other flags) instead.
const PROCMAP_QUERY_COVERING_OR_NEXT_VMA: u64 = 0x10;

/// What a visitor of [`query_each_private_writable`] wants next.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Walk {
    GoOn,
    Stop,
}

enum QueryError {
    /// The kernel does not know the ioctl, or may not be asked it.
    Unsupported,
    /// Anything else (the text is read instead).
    Failed,
}

/// [`for_each_private_writable`] by `PROCMAP_QUERY`: from address 0, the next readable and
/// writable mapping each time, until the kernel says there is none (ENOENT).
fn query_each_private_writable(
    fd: libc::c_int,
    visit: &mut impl FnMut(usize, usize) -> Walk,
) -> Result<(), QueryError> {
    let mut addr = 0u64;
    loop {
        let mut q = ProcmapQuery {
            size: std::mem::size_of::<ProcmapQuery>() as u64,
            query_flags: PROCMAP_QUERY_VMA_READABLE
                | PROCMAP_QUERY_VMA_WRITABLE
                | PROCMAP_QUERY_COVERING_OR_NEXT_VMA,
            query_addr: addr,
            ..ProcmapQuery::default()
        };
        match procmap_query(fd, &mut q) {
            Ok(()) => {}
            Err(libc::ENOENT) => return Ok(()),
            // ENOTTY or EINVAL: a kernel before 6.11; EPERM or EACCES: a seccomp filter that
            // refuses it. Asked at 0 and refused, it will be refused every time.
            Err(_) if addr == 0 => return Err(QueryError::Unsupported),
            Err(_) => return Err(QueryError::Failed),
        }
        if q.vma_end <= addr {
            // Never from a sane kernel; without it a loop could not end.
            return Err(QueryError::Failed);
        }
        if q.vma_flags & (PROCMAP_QUERY_VMA_SHARED | PROCMAP_QUERY_VMA_EXECUTABLE) == 0
            && visit(q.vma_start as usize, q.vma_end as usize) == Walk::Stop
        {
            return Ok(());
        }
        addr = q.vma_end;
    }
}

fn procmap_query(fd: libc::c_int, q: &mut ProcmapQuery) -> Result<(), i32> {
    loop {
        // SAFETY: `q` is a valid, exclusively borrowed `struct procmap_query` whose `size` says
        // how large it is; `vma_name_size` and `build_id_size` are 0, so the kernel writes
        // nothing but `q` itself.
        let r = unsafe { libc::ioctl(fd, PROCMAP_QUERY as _, std::ptr::from_mut(q)) };
        if r == 0 {
            return Ok(());
        }
        match errno() {
            libc::EINTR => continue,
            e => return Err(e),
        }
    }
}

/// Calls `visit` with each line (without its newline) of what `read` yields until it returns 0.
/// Lines may be split across reads: their bytes collect in a stack buffer until the newline.
/// Bytes of a line beyond [`LINE_MAX`] are dropped.
fn for_each_line(
    mut read: impl FnMut(&mut [u8]) -> Result<usize, WalkError>,
    mut visit: impl FnMut(&[u8]),
) -> Result<(), WalkError> {
    let mut buf = [0u8; READ_BUF];
    let mut line = [0u8; LINE_MAX];
    let mut line_len = 0;
    loop {
        let n = read(&mut buf)?;
        if n == 0 {
            break;
        }
        for &b in &buf[..n] {
            if b == b'\n' {
                visit(&line[..line_len]);
                line_len = 0;
            } else if line_len < LINE_MAX {
                line[line_len] = b;
                line_len += 1;
            }
        }
    }
    if line_len > 0 {
        visit(&line[..line_len]);
    }
    Ok(())
}

/// One maps line: `start-end perms offset dev inode [path]`.
#[derive(Debug, PartialEq, Eq)]
pub(crate) struct MapLine {
    pub(crate) start: usize,
    pub(crate) end: usize,
    perms: [u8; 4],
    /// `[vsyscall]`, `[vvar]` (and `[vvar_vclock]`) or `[vdso]`: kernel pages, never touched.
    special: bool,
}

pub(crate) fn parse_line(line: &[u8]) -> Option<MapLine> {
    let dash = line.iter().position(|&b| b == b'-')?;
    let start = parse_hex(&line[..dash])?;
    let rest = &line[dash + 1..];
    let space = rest.iter().position(|&b| b == b' ')?;
    let end = parse_hex(&rest[..space])?;
    let perms: [u8; 4] = rest.get(space + 1..space + 5)?.try_into().ok()?;
    let special =
        line.ends_with(b"[vsyscall]") || line.ends_with(b"[vdso]") || contains(line, b"[vvar");
    Some(MapLine {
        start,
        end,
        perms,
        special,
    })
}

fn parse_hex(s: &[u8]) -> Option<usize> {
    if s.is_empty() || s.len() > 2 * std::mem::size_of::<usize>() {
        return None;
    }
    let mut v = 0usize;
    for &b in s {
        let d = (b as char).to_digit(16)?;
        v = (v << 4) | d as usize;
    }
    Some(v)
}

fn contains(hay: &[u8], needle: &[u8]) -> bool {
    hay.windows(needle.len()).any(|w| w == needle)
}

/// Breaks the sharing of the resident pages of `[start, end)`; returns how many.
///
/// Each run of resident pages (from `mincore`) gets one `madvise(MADV_POPULATE_WRITE)`: the
/// kernel write-faults the whole run in one call, as writing to each page would, without a trap
/// per page. Where that is refused (a kernel before 5.14 answers EINVAL; it is then not tried
/// again) or fails, the run's pages are written to one by one.
fn touch_resident(start: usize, end: usize) -> usize {
    let page = page_size();
    let mut residency = [0u8; MINCORE_PAGES];
    let mut touched = 0;
    let mut chunk = start;
    while chunk < end {
        let len = (end - chunk).min(MINCORE_PAGES * page);
        // An error (the mapping changed under us, which a single-threaded caller cannot cause)
        // just skips the chunk: nothing of it can be touched safely.
        if mincore(chunk, len, &mut residency).is_ok() {
            let pages = len.div_ceil(page);
            for_each_run(&residency[..pages], |first, count| {
                populate_or_touch(chunk + first * page, count, page);
                touched += count;
            });
        }
        chunk += len;
    }
    touched
}

/// Calls `run(first, count)` for each run of pages whose `mincore` byte has bit 0 set.
fn for_each_run(residency: &[u8], mut run: impl FnMut(usize, usize)) {
    let mut i = 0;
    while i < residency.len() {
        if residency[i] & 1 == 0 {
            i += 1;
            continue;
        }
        let first = i;
        while i < residency.len() && residency[i] & 1 != 0 {
            i += 1;
        }
        run(first, i - first);
    }
}

/// Set once `MADV_POPULATE_WRITE` answered EINVAL (kernel before 5.14): touch from then on.
static NO_POPULATE_WRITE: AtomicBool = AtomicBool::new(false);

/// Write-faults `count` resident pages from `addr`: one `madvise`, or page by page.
fn populate_or_touch(addr: usize, count: usize, page: usize) {
    if !NO_POPULATE_WRITE.load(Ordering::Relaxed) {
        match populate_write(addr, count * page) {
            Ok(()) => return,
            Err(libc::EINVAL) => NO_POPULATE_WRITE.store(true, Ordering::Relaxed),
            // Anything else (EFAULT, ENOMEM, EHWPOISON): do what we can page by page.
            Err(_) => {}
        }
    }
    for i in 0..count {
        touch(addr + i * page);
    }
}

fn open_maps() -> Result<libc::c_int, WalkError> {
    // SAFETY: the path is a NUL-terminated literal; open touches no other memory of ours.
    let fd = unsafe {
        libc::open(
            c"/proc/self/maps".as_ptr(),
            libc::O_RDONLY | libc::O_CLOEXEC,
        )
    };
    if fd < 0 {
        return Err(WalkError { errno: errno() });
    }
    Ok(fd)
}

fn read(fd: libc::c_int, buf: &mut [u8]) -> Result<usize, WalkError> {
    loop {
        // SAFETY: `buf` is valid for writes of `buf.len()` bytes during the call.
        let n = unsafe { libc::read(fd, buf.as_mut_ptr().cast(), buf.len()) };
        if n >= 0 {
            return Ok(n as usize);
        }
        let e = errno();
        if e != libc::EINTR {
            return Err(WalkError { errno: e });
        }
    }
}

fn close(fd: libc::c_int) {
    // SAFETY: `fd` was opened by `open_maps` and is closed exactly once, here.
    unsafe { libc::close(fd) };
}

fn mincore(addr: usize, len: usize, vec: &mut [u8; MINCORE_PAGES]) -> Result<(), i32> {
    // SAFETY: `addr` is page-aligned (a mapping start plus whole pages); `len` covers at most
    // MINCORE_PAGES pages, so the kernel writes at most `vec.len()` bytes into `vec`.
    let r = unsafe { libc::mincore(addr as *mut libc::c_void, len, vec.as_mut_ptr()) };
    if r < 0 {
        Err(errno())
    } else {
        Ok(())
    }
}

fn populate_write(addr: usize, len: usize) -> Result<(), i32> {
    loop {
        // SAFETY: `addr` is page-aligned and `[addr, addr + len)` lies in one private writable
        // mapping whose pages mincore just reported resident. MADV_POPULATE_WRITE only faults
        // those pages in writable (copying any page still shared copy-on-write); it changes no
        // byte of their contents.
        let r = unsafe { libc::madvise(addr as *mut libc::c_void, len, libc::MADV_POPULATE_WRITE) };
        if r == 0 {
            return Ok(());
        }
        match errno() {
            libc::EINTR => continue,
            e => return Err(e),
        }
    }
}

fn touch(addr: usize) {
    let p = addr as *mut u8;
    // SAFETY: `p` is in a private mapping that /proc/self/maps lists as readable and writable
    // (or the donor's list of them, made right before the fork with every signal blocked),
    // and mincore just reported its page resident (so no SIGBUS past a file's end). Writing back
    // the byte just read leaves memory unchanged; no other thread runs (the caller's contract),
    // so no concurrent write can be lost. Volatile keeps the compiler from eliding the write,
    // which is the whole point: the write fault makes the kernel copy the page.
    unsafe {
        let v = std::ptr::read_volatile(p);
        std::ptr::write_volatile(p, v);
    }
}

fn errno() -> i32 {
    // SAFETY: __errno_location returns this thread's errno slot, always valid.
    unsafe { *libc::__errno_location() }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_maps_lines() {
        let l = b"7ffd1c000000-7ffd1c021000 rw-p 00000000 00:00 0                          [stack]";
        assert_eq!(
            parse_line(l),
            Some(MapLine {
                start: 0x7ffd1c000000,
                end: 0x7ffd1c021000,
                perms: *b"rw-p",
                special: false
            })
        );
        let v = b"7ffd1c1f0000-7ffd1c1f4000 r--p 00000000 00:00 0                          [vvar]";
        assert!(parse_line(v).unwrap().special);
        let d = b"ffffffffff600000-ffffffffff601000 --xp 00000000 00:00 0  [vsyscall]";
        assert!(parse_line(d).unwrap().special);
        assert_eq!(parse_line(b"garbage"), None);
        assert_eq!(parse_line(b"12-34"), None);
        assert_eq!(parse_line(b"zz-34 rw-p"), None);
    }

    #[test]
    fn lines_split_across_reads_are_joined() {
        let text = format!("short\n{}\nlast-without-newline", "x".repeat(LINE_MAX + 50));
        for chunk in [1, 3, 7, 4096] {
            let mut rest = text.as_bytes();
            let mut lines = Vec::new();
            for_each_line(
                |buf| {
                    let n = chunk.min(rest.len()).min(buf.len());
                    buf[..n].copy_from_slice(&rest[..n]);
                    rest = &rest[n..];
                    Ok(n)
                },
                |l| lines.push(l.to_vec()),
            )
            .unwrap();
            assert_eq!(lines.len(), 3, "chunk {chunk}");
            assert_eq!(lines[0], b"short");
            assert_eq!(lines[1], vec![b'x'; LINE_MAX]);
            assert_eq!(lines[2], b"last-without-newline");
        }
    }

    #[test]
    fn runs_of_resident_pages() {
        let mut runs = Vec::new();
        for_each_run(&[1, 1, 0, 3, 0, 0, 1], |a, n| runs.push((a, n)));
        assert_eq!(runs, [(0, 2), (3, 1), (6, 1)]);
        runs.clear();
        for_each_run(&[0, 2, 0], |a, n| runs.push((a, n)));
        assert!(runs.is_empty(), "only bit 0 means resident");
        for_each_run(&[], |a, n| runs.push((a, n)));
        assert!(runs.is_empty());
    }

    #[test]
    fn walk_in_this_process_touches_something() {
        // Concurrent test threads may write the pages we touch; a lost write would only matter
        // to the bytes read-then-written in that instant, and all of them belong to this
        // process's own test data. Run it anyway in a forked child to keep the contract.
        let pid = fork_for_test();
        if pid == 0 {
            // SAFETY: the fork child has a single thread.
            let r = unsafe { break_cow_sharing() };
            let code = match r {
                Ok(s) if s.mappings > 0 && s.pages_touched > 0 => 0,
                Ok(_) => 2,
                Err(_) => 3,
            };
            crate::sys::exit_now(code);
        }
        assert_eq!(
            wait_exit(pid),
            0,
            "child walk failed (2: nothing touched, 3: maps error)"
        );
    }

    /// `PROCMAP_QUERY` and the text of `/proc/self/maps` name the same mappings, in a forked
    /// child (one thread: nothing maps or unmaps between the two listings; fixed arrays: no
    /// allocation after the fork). Without the ioctl (a kernel before 6.11) only the fallback
    /// is seen to work.
    #[test]
    fn the_query_and_the_text_list_the_same_mappings() {
        const MAX: usize = 512;
        let pid = fork_for_test();
        if pid == 0 {
            let list = |query: bool, out: &mut [(usize, usize); MAX]| -> Result<usize, i32> {
                let fd = open_maps().map_err(|_| 10)?;
                let mut n = 0;
                let mut push = |a: usize, b: usize| {
                    if n < MAX {
                        out[n] = (a, b);
                    }
                    n += 1;
                };
                let r = if query {
                    let mut each = |a, b| {
                        push(a, b);
                        Walk::GoOn
                    };
                    match query_each_private_writable(fd, &mut each) {
                        Ok(()) => Ok(()),
                        Err(QueryError::Unsupported) => Err(6),
                        Err(QueryError::Failed) => Err(11),
                    }
                } else {
                    NO_PROCMAP_QUERY.store(true, Ordering::Relaxed);
                    for_each_private_writable(fd, &mut push).map_err(|_| 12)
                };
                close(fd);
                r.map(|()| n)
            };
            let (mut by_query, mut by_text) = ([(0, 0); MAX], [(0, 0); MAX]);
            let code = match (list(true, &mut by_query), list(false, &mut by_text)) {
                (Err(6), Ok(n)) if n > 0 => 6,
                // Without the ioctl the text must still list something.
                (Err(6), _) => 13,
                (Ok(q), Ok(_)) if q == 0 || q > MAX => 7,
                (Ok(q), Ok(t)) if q != t || by_query[..q] != by_text[..t] => 8,
                (Ok(_), Ok(_)) => 0,
                (Err(e), _) | (_, Err(e)) => e,
            };
            crate::sys::exit_now(code);
        }
        match wait_exit(pid) {
            0 => {}
            6 => eprintln!("PROCMAP_QUERY unknown to this kernel: the text alone was checked"),
            c => panic!(
                "child exited {c} (7: none or too many mappings, 8: the two lists differ, \
                 10: open, 11: the query failed, 12: the text failed, 13: no ioctl, and the text listed \
                 nothing)"
            ),
        }
    }

    #[test]
    fn only_the_stack_the_walk_runs_on_loses_its_low_part() {
        let dead = DeadStack {
            here: 0x7000_2345,
            floor: 0x7000_1000,
            low: 0x6fff_0000,
        };
        let whole = |start, end| [(start, end), (end, end)];
        assert_eq!(
            dead.live_parts(0x6fff_0000, 0x7001_0000),
            [(0x6fff_0000, 0x6fff_0000), (0x7000_1000, 0x7001_0000)]
        );
        // Another mapping, below or above: whole.
        assert_eq!(dead.live_parts(0x1000, 0x9000), whole(0x1000, 0x9000));
        assert_eq!(
            dead.live_parts(0x7001_0000, 0x7002_0000),
            whole(0x7001_0000, 0x7002_0000)
        );
        // A floor below the mapping's start leaves it whole.
        assert_eq!(
            dead.live_parts(0x7000_2000, 0x7000_3000),
            whole(0x7000_2000, 0x7000_3000)
        );
        // A range that holds the stack and a mapping right below it (the donor's list joins
        // adjacent mappings): the mapping below is live, only the stack's own low part is not.
        assert_eq!(
            dead.live_parts(0x6ffe_0000, 0x7001_0000),
            [(0x6ffe_0000, 0x6fff_0000), (0x7000_1000, 0x7001_0000)]
        );
        // Not on the main thread's stack as recorded (none is, in a test thread): nothing.
        assert_eq!(DeadStack::now().floor, 0);
    }

    /// Writes `KIB` KiB of stack below the caller's frame, so those pages are resident.
    #[inline(never)]
    fn dirty_stack_below<const KIB: usize>() {
        let mut deep = [0u8; 1024 * 64];
        for (i, b) in deep.iter_mut().enumerate().take(KIB * 1024) {
            *b = i as u8;
        }
        std::hint::black_box(&mut deep);
    }

    /// What the walk leaves shared, exactly: of the stack it runs on, a page in its caller's
    /// frame (live) gets its own copy, and a page far below the stack pointer (dead) does not.
    #[test]
    fn the_stack_below_the_stack_pointer_stays_shared_and_the_rest_is_copied() {
        let page = page_size();
        let mut live = [0x11u8; 3 * 4096];
        std::hint::black_box(&mut live);
        if pfn(live.as_ptr() as usize) == 0 {
            eprintln!("skipped: /proc/self/pagemap shows no PFNs (needs CAP_SYS_ADMIN)");
            return;
        }
        dirty_stack_below::<64>();
        // This test thread's stack mapping: the fork child's only thread runs on it, so for
        // the child it is the main thread's stack (read here: the child may not allocate).
        let here = live.as_ptr() as usize;
        let maps = std::fs::read_to_string("/proc/self/maps").expect("maps");
        let (low, high) = maps
            .lines()
            .filter_map(|l| parse_line(l.as_bytes()))
            .map(|m| (m.start, m.end))
            .find(|&(a, b)| a <= here && here < b)
            .expect("the mapping of this thread's stack");
        let pid = fork_for_test();
        if pid == 0 {
            // Only async-signal-safe work in the child (the parent has other threads).
            note_main_stack(low, high);
            let live_page = (live.as_ptr() as usize).div_ceil(page) * page;
            // 48 KiB below this frame: deeper than the walk goes, written by the call above.
            let dead_page = ((live.as_ptr() as usize) & !(page - 1)) - 12 * page;
            let (live_before, dead_before) = (pfn(live_page), pfn(dead_page));
            // SAFETY: the fork child has a single thread.
            let walked = unsafe { break_cow_sharing() };
            let (live_after, dead_after) = (pfn(live_page), pfn(dead_page));
            let code = if walked.is_err() {
                3
            } else if [live_before, dead_before, live_after, dead_after].contains(&0) {
                4
            } else if live_after == live_before {
                5
            } else if dead_after != dead_before {
                6
            } else {
                0
            };
            crate::sys::exit_now(code);
        }
        let code = wait_exit(pid);
        assert_eq!(
            code, 0,
            "3: walk failed, 4: a probe not resident, 5: the live stack page still shared, \
             6: the dead stack page copied"
        );
        std::hint::black_box(&live);
    }

    /// The real check: after the walk, a heap page of the child is backed by another physical
    /// frame than the parent's.
    #[test]
    fn walk_gives_child_its_own_pages() {
        let Some((heap, addr, parent_pfn)) = heap_page() else {
            return;
        };
        let pid = fork_for_test();
        if pid == 0 {
            // Only async-signal-safe work in the child: the parent has other threads, whose
            // locks may be held forever here.
            let before = pfn(addr);
            // SAFETY: the fork child has a single thread.
            let walked = unsafe { break_cow_sharing() };
            let after = pfn(addr);
            let code = if walked.is_err() {
                3
            } else if before != parent_pfn {
                4
            } else if after == before || after == 0 {
                5
            } else {
                0
            };
            crate::sys::exit_now(code);
        }
        let code = wait_exit(pid);
        assert_eq!(
            code, 0,
            "3: walk failed, 4: page not shared right after fork, 5: still shared after walk"
        );
        drop(heap);
    }

    /// The donor lists its mappings before the fork, the child walks the list: the child's
    /// page is its own afterwards, and the list was what it walked. And a kept maps fd whose
    /// number now holds another file is never asked for a list.
    #[test]
    fn the_donors_list_gives_the_child_its_own_pages() {
        let _one_at_a_time = LIST_TESTS.lock().unwrap_or_else(|e| e.into_inner());
        let Some((heap, addr, parent_pfn)) = heap_page() else {
            return;
        };
        open_own_maps();
        let kept = OWN_MAPS.load(Ordering::SeqCst);
        assert!(
            kept >= OWN_MAPS_FLOOR,
            "the maps file is kept above the low numbers"
        );
        take_snapshot();
        let Some(listed) = SNAPSHOT.len() else {
            if NO_PROCMAP_QUERY.load(Ordering::Relaxed) {
                eprintln!("skipped: this kernel has no PROCMAP_QUERY (Linux < 6.11)");
            } else {
                // More private writable mappings than the list holds (a test process with
                // very many threads has an arena each).
                let mut n = 0;
                let fd = open_maps().expect("maps");
                let _ = query_each_private_writable(fd, &mut |_, _| {
                    n += 1;
                    Walk::GoOn
                });
                close(fd);
                assert!(
                    n > SNAPSHOT_MAX,
                    "no list although PROCMAP_QUERY answers ({n})"
                );
                eprintln!("skipped: {n} private writable mappings, more than a list holds");
            }
            return;
        };
        assert!(listed > 0);
        let heap_mapping = SNAPSHOT
            .ranges(listed)
            .find(|&(start, end)| start <= addr && addr < end)
            .expect("the heap page's mapping is listed");
        let pid = fork_for_test();
        if pid == 0 {
            // Only async-signal-safe work in the child (see walk_gives_child_its_own_pages).
            // The list cut down to the heap page's mapping: a walk of anything else than the
            // list would visit more than one mapping.
            SNAPSHOT.starts[0].store(heap_mapping.0, Ordering::Relaxed);
            SNAPSHOT.ends[0].store(heap_mapping.1, Ordering::Relaxed);
            SNAPSHOT.len.store(1, Ordering::SeqCst);
            let before = pfn(addr);
            // SAFETY: the fork child has a single thread and has mapped nothing since the fork.
            let walked = unsafe { break_cow_sharing_after_fork() };
            let after = pfn(addr);
            let code = match walked {
                Err(_) => 3,
                Ok(_) if before != parent_pfn => 4,
                Ok(_) if after == before || after == 0 => 5,
                Ok(stats) if stats.mappings != 1 => 6,
                Ok(_) => 0,
            };
            crate::sys::exit_now(code);
        }
        let code = wait_exit(pid);
        assert_eq!(
            code, 0,
            "3: walk failed, 4: page not shared right after fork, 5: still shared after walk, \
             6: the child walked something else than the list"
        );
        drop(heap);

        // The component closes the number and opens something else on it: no list.
        // SAFETY: /dev/null opened read-only, then dup2 onto the kept number (ours).
        unsafe {
            let null = libc::open(c"/dev/null".as_ptr(), libc::O_RDONLY | libc::O_CLOEXEC);
            assert!(null >= 0);
            assert_eq!(libc::dup2(null, kept), kept);
            libc::close(null);
        }
        take_snapshot();
        assert_eq!(
            SNAPSHOT.len(),
            None,
            "a reused fd number is not the maps file"
        );
        // Opened again: the stranger on the old number is left alone, a list is made.
        open_own_maps();
        assert!(file_id(kept).is_some(), "the other file was not closed");
        take_snapshot();
        assert!(SNAPSHOT.len().is_some());
        close(kept);
    }

    /// The kept maps file and the list are one per process: the tests that use them take turns.
    static LIST_TESTS: std::sync::Mutex<()> = std::sync::Mutex::new(());

    /// In a fork child (one thread: nothing maps memory behind its back), the list is exactly
    /// what a fresh maps file says (adjacent mappings joined), and a child's own kept maps file
    /// shows the child's mappings, not its parent's: a page mapped in the child is listed.
    #[test]
    fn the_list_is_the_mappings_of_the_process_that_takes_it() {
        let _one_at_a_time = LIST_TESTS.lock().unwrap_or_else(|e| e.into_inner());
        open_own_maps();
        take_snapshot();
        if SNAPSHOT.len().is_none() {
            eprintln!("skipped: no list here (see the_donors_list_gives_the_child_its_own_pages)");
            return;
        }
        let pid = fork_for_test();
        if pid == 0 {
            // Only async-signal-safe work in the child.
            open_own_maps();
            let page = page_size();
            // SAFETY: a fresh private anonymous mapping of one page; nothing else is touched.
            let fresh = unsafe {
                libc::mmap(
                    std::ptr::null_mut(),
                    page,
                    libc::PROT_READ | libc::PROT_WRITE,
                    libc::MAP_PRIVATE | libc::MAP_ANONYMOUS,
                    -1,
                    0,
                )
            };
            if fresh == libc::MAP_FAILED {
                crate::sys::exit_now(3);
            }
            let fresh = fresh as usize;
            take_snapshot();
            let Some(len) = SNAPSHOT.len() else {
                crate::sys::exit_now(4);
            };
            let Ok(fd) = open_maps() else {
                crate::sys::exit_now(3);
            };
            // The file's mappings, adjacent ones joined as the list joins them: each run must
            // be the list's next entry.
            let listed_at = |i: usize, (start, end): (usize, usize)| {
                i < len
                    && SNAPSHOT.starts[i].load(Ordering::Relaxed) == start
                    && SNAPSHOT.ends[i].load(Ordering::Relaxed) == end
            };
            let mut i = 0;
            let mut same = true;
            let mut run: Option<(usize, usize)> = None;
            let _ = query_each_private_writable(fd, &mut |start, end| {
                match run {
                    Some((from, to)) if to == start => run = Some((from, end)),
                    Some(done) => {
                        same &= listed_at(i, done);
                        i += 1;
                        run = Some((start, end));
                    }
                    None => run = Some((start, end)),
                }
                Walk::GoOn
            });
            if let Some(done) = run {
                same &= listed_at(i, done);
                i += 1;
            }
            close(fd);
            let listed = SNAPSHOT
                .ranges(len)
                .any(|(start, end)| start <= fresh && fresh < end);
            let code = if !same || i != len {
                5
            } else if !listed {
                6
            } else {
                0
            };
            crate::sys::exit_now(code);
        }
        let code = wait_exit(pid);
        assert_eq!(
            code, 0,
            "3: mmap or open failed, 4: no list in the child, 5: the list is not what the maps \
             file says, 6: the child's own new mapping is not listed (its parent's were)"
        );
    }

    /// A heap allocation, the address of a page wholly inside it (so no other allocation shares
    /// it) and that page's physical frame; `None` (said) where pagemap shows no frames.
    fn heap_page() -> Option<(Vec<u8>, usize, u64)> {
        let page = page_size();
        let mut heap = vec![0x5au8; page * 4];
        std::hint::black_box(&mut heap);
        let addr = (heap.as_ptr() as usize).div_ceil(page) * page + page;
        let frame = pfn(addr);
        if frame == 0 {
            eprintln!("skipped: /proc/self/pagemap shows no PFNs (needs CAP_SYS_ADMIN)");
            return None;
        }
        Some((heap, addr, frame))
    }

    fn fork_for_test() -> libc::pid_t {
        // SAFETY: the child only does async-signal-safe work and leaves by `_exit`.
        let pid = unsafe { crate::restart::raw_fork() };
        assert!(pid >= 0, "fork failed");
        pid
    }

    /// Waits (bounded) for `pid` to exit and returns its exit code.
    fn wait_exit(pid: libc::pid_t) -> i32 {
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(20);
        loop {
            match crate::sys::reap(pid).expect("waitpid") {
                Some((_, crate::sys::ExitStatus::Code(c))) => return c,
                Some((_, crate::sys::ExitStatus::Signal(s))) => panic!("child killed by {s}"),
                None if std::time::Instant::now() > deadline => {
                    let _ = crate::sys::kill(pid, libc::SIGKILL);
                    panic!("child did not finish in time");
                }
                None => std::thread::sleep(std::time::Duration::from_millis(5)),
            }
        }
    }

    /// Physical frame number of the page holding `addr`, 0 if unknown. Allocation-free.
    fn pfn(addr: usize) -> u64 {
        // SAFETY: literal NUL-terminated path.
        let fd = unsafe { libc::open(c"/proc/self/pagemap".as_ptr(), libc::O_RDONLY) };
        if fd < 0 {
            return 0;
        }
        let mut entry = [0u8; 8];
        let off = (addr / page_size() * 8) as libc::off_t;
        // SAFETY: `entry` is valid for 8 bytes of writes.
        let n = unsafe { libc::pread(fd, entry.as_mut_ptr().cast(), 8, off) };
        close(fd);
        if n != 8 {
            return 0;
        }
        let e = u64::from_ne_bytes(entry);
        if e >> 63 == 0 {
            return 0;
        }
        e & ((1 << 55) - 1)
    }
}
