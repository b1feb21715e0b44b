//! # s3res-replica-c: replica-rt for C and C++ components
//!
//! The replica runtime ([`replica_rt`]) behind a C ABI, built as `libs3res_replica_c.a` and
//! `libs3res_replica_c.so`, declared in `include/s3res.h` (written by hand; the tests compile a
//! C file that calls every declared function and link it against both libraries, and check that
//! the header and the exports here name the same functions). Nothing is reimplemented: every
//! call goes to replica-rt, so a C component gets the same port map, the same restart-by-fork
//! handler, the same injection hooks and the same memory locking as a Rust one.
//!
//! ## Conventions
//!
//! - Errors are negative `errno` values (`-EINVAL`, `-ENOENT`, `-EPROTO`, ...);
//!   [`s3res_last_error`] gives the whole message of the last failed call.
//! - No panic crosses the ABI: every entry point runs inside `catch_unwind`; a panic (a bug of
//!   this library) comes back as `-ENOTRECOVERABLE` with its message in [`s3res_last_error`].
//! - Handles are opaque pointers owned by the caller, freed by the matching `*_close` / `*_free`
//!   (NULL is accepted and ignored there).
//! - A received payload is borrowed from its port: valid until the next receive on that port
//!   or its close.

use std::any::Any;
use std::cell::RefCell;
use std::error::Error;
use std::ffi::{c_char, c_int, CStr, CString};
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::ptr;
use std::time::Duration;

use replica_rt::contract::{signals, MAX_PORTS};
use replica_rt::{InPort, InitError, Mode, OutPort, RecvError, Runtime, SendError, TryRecv};

/// `s3res_runtime` in the header: the component's runtime, from [`s3res_init`].
#[derive(Debug)]
pub struct S3resRuntime {
    rt: Runtime,
}

/// `s3res_in` in the header: an input port.
#[derive(Debug)]
pub struct S3resIn {
    port: InPort,
    name: CString,
}

/// `s3res_out` in the header: an output port.
#[derive(Debug)]
pub struct S3resOut {
    port: OutPort,
    name: CString,
}

/// [`s3res_mode`]: started by hand (`in` is stdin, `out` is stdout).
pub const S3RES_MODE_STANDALONE: c_int = 0;
/// [`s3res_mode`]: started by s3res-bootstrap, without a voter.
pub const S3RES_MODE_UNPROTECTED: c_int = 1;
/// [`s3res_mode`]: one replica of a protected component, started by s3res-voter.
pub const S3RES_MODE_REPLICA: c_int = 2;

/// [`s3res_log`] levels.
pub const S3RES_LOG_ERROR: c_int = 1;
pub const S3RES_LOG_WARN: c_int = 2;
pub const S3RES_LOG_INFO: c_int = 3;
pub const S3RES_LOG_DEBUG: c_int = 4;
pub const S3RES_LOG_TRACE: c_int = 5;

const VERSION: &CStr =
    match CStr::from_bytes_with_nul(concat!(env!("CARGO_PKG_VERSION"), "\0").as_bytes()) {
        Ok(v) => v,
        Err(_) => panic!("the package version contains a NUL"),
    };

thread_local! {
    /// The message of the last failed call on this thread (components are single-threaded).
    static LAST_ERROR: RefCell<CString> = RefCell::new(CString::default());
}

fn set_last_error(message: &str) {
    let c = CString::new(message.replace('\0', "\\0")).unwrap_or_default();
    LAST_ERROR.with(|e| *e.borrow_mut() = c);
}

/// `err` and its causes, joined by ": " (what `anyhow` prints with `{:#}`).
fn chain(err: &dyn Error) -> String {
    let mut text = err.to_string();
    let mut source = err.source();
    while let Some(s) = source {
        text.push_str(": ");
        text.push_str(&s.to_string());
        source = s.source();
    }
    text
}

/// Records `err` as the last error and returns `-code`.
fn fail(code: c_int, err: &dyn Error) -> c_int {
    set_last_error(&chain(err));
    -code
}

fn fail_msg(code: c_int, message: &str) -> c_int {
    set_last_error(message);
    -code
}

fn null_arg(function: &str, arg: &str) -> c_int {
    fail_msg(libc::EINVAL, &format!("{function}: `{arg}` is NULL"))
}

fn os_code(e: &std::io::Error) -> c_int {
    e.raw_os_error().unwrap_or(libc::EIO)
}

fn panic_message(payload: &(dyn Any + Send)) -> &str {
    payload
        .downcast_ref::<&str>()
        .copied()
        .or_else(|| payload.downcast_ref::<String>().map(String::as_str))
        .unwrap_or("(no message)")
}

/// Runs `f`; a panic becomes `on_panic` with the message kept for [`s3res_last_error`].
fn guard<T>(on_panic: T, f: impl FnOnce() -> T) -> T {
    match catch_unwind(AssertUnwindSafe(f)) {
        Ok(v) => v,
        Err(payload) => {
            set_last_error(&format!(
                "internal error in s3res (a panic; please report it): {}",
                panic_message(payload.as_ref())
            ));
            on_panic
        }
    }
}

/// [`guard`] for the functions that return a status.
fn guard_rc(f: impl FnOnce() -> c_int) -> c_int {
    guard(-libc::ENOTRECOVERABLE, f)
}

fn init_code(e: &InitError) -> c_int {
    match e {
        InitError::AlreadyInitialized => libc::EALREADY,
        InitError::BadPortMap { .. }
        | InitError::InvalidPortMap { .. }
        | InitError::ReplicaWithoutPorts { .. } => libc::EINVAL,
        InitError::SocketPath(_) => libc::ENAMETOOLONG,
        InitError::Signal { source, .. } => os_code(source),
    }
}

fn port_code(e: &replica_rt::PortError) -> c_int {
    use replica_rt::PortError;
    match e {
        PortError::Unknown { .. } | PortError::Standalone { .. } => libc::ENOENT,
        PortError::AlreadyTaken { .. } => libc::EBUSY,
        PortError::NotOpen { .. } | PortError::WrongAccess { .. } => libc::EBADF,
    }
}

fn recv_code(e: &RecvError) -> c_int {
    match e {
        RecvError::Frame { .. } => libc::EPROTO,
        RecvError::Io { source, .. } => os_code(source),
        RecvError::InputLost { .. } => libc::EIO,
    }
}

fn send_code(e: &SendError) -> c_int {
    match e {
        SendError::TooLarge { .. } => libc::EMSGSIZE,
        SendError::Io { source, .. } => os_code(source),
    }
}

/// A C string argument as UTF-8, or the status to return.
///
/// # Safety
///
/// `s` is NULL or points at a NUL-terminated string that stays valid for the returned borrow.
unsafe fn str_arg<'a>(s: *const c_char, function: &str, arg: &str) -> Result<&'a str, c_int> {
    if s.is_null() {
        return Err(null_arg(function, arg));
    }
    // SAFETY: not NULL (checked), and the caller promises a NUL-terminated string.
    let c = unsafe { CStr::from_ptr(s) };
    c.to_str()
        .map_err(|_| fail_msg(libc::EINVAL, &format!("{function}: `{arg}` is not UTF-8")))
}

/// A name as a C string (port names come from a JSON port map, which may hold a NUL).
fn c_name(name: &str) -> CString {
    CString::new(name.replace('\0', "\\0")).unwrap_or_default()
}

/// Negative: no limit.
fn timeout(us: i64) -> Option<Duration> {
    u64::try_from(us).ok().map(Duration::from_micros)
}

/// Stores a received frame (or none: NULL, 0) in the caller's out-parameters.
///
/// # Safety
///
/// `payload` and `len` are valid for writes (checked non-NULL by the caller).
unsafe fn put_frame(payload: *mut *const u8, len: *mut usize, frame: Option<&[u8]>) {
    let (p, n) = frame.map_or((ptr::null(), 0), |f| (f.as_ptr(), f.len()));
    // SAFETY: the caller promises both pointers valid for writes.
    unsafe {
        payload.write(p);
        len.write(n);
    }
}

/// The status of a non-blocking or timed receive: 1 frame, 0 end of stream, `-EAGAIN` none yet.
///
/// # Safety
///
/// As [`put_frame`].
unsafe fn try_status(
    got: Result<TryRecv<'_>, RecvError>,
    payload: *mut *const u8,
    len: *mut usize,
) -> c_int {
    match got {
        Ok(TryRecv::Frame(f)) => {
            // SAFETY: the caller's promise, passed on.
            unsafe { put_frame(payload, len, Some(f)) };
            1
        }
        Ok(TryRecv::Closed) => {
            // SAFETY: as above.
            unsafe { put_frame(payload, len, None) };
            0
        }
        Ok(TryRecv::Empty) => {
            // SAFETY: as above.
            unsafe { put_frame(payload, len, None) };
            fail_msg(libc::EAGAIN, "no whole frame yet")
        }
        Err(e) => fail(recv_code(&e), &e),
    }
}

// ---------------------------------------------------------------------------------------------
// Errors, version, logging
// ---------------------------------------------------------------------------------------------

/// The message of the last call that failed on this thread (`""` if none did). Valid until the
/// next failing call on this thread.
#[no_mangle]
pub extern "C" fn s3res_last_error() -> *const c_char {
    guard(ptr::null(), || LAST_ERROR.with(|e| e.borrow().as_ptr()))
}

/// The library's version, e.g. `"0.1.0"` (a static string).
#[no_mangle]
pub extern "C" fn s3res_version() -> *const c_char {
    VERSION.as_ptr()
}

/// Sends the runtime's log lines (and those of [`s3res_log`]) to stderr, filtered by
/// `RUST_LOG` (default `info`), each prefixed with component, replica and pid; as
/// `replica_rt::init_logging`. `component_default` (may be NULL) names the component when it
/// was not started by s3res. Call it before [`s3res_init`]; calling it again is harmless.
///
/// # Safety
///
/// `component_default` is NULL or a NUL-terminated string.
#[no_mangle]
pub unsafe extern "C" fn s3res_init_logging(component_default: *const c_char) {
    guard((), || {
        let name = if component_default.is_null() {
            "component".to_owned()
        } else {
            // SAFETY: not NULL (checked), NUL-terminated by the caller's promise.
            unsafe { CStr::from_ptr(component_default) }
                .to_string_lossy()
                .into_owned()
        };
        replica_rt::init_logging(&name);
    })
}

/// Logs `message` at `level` (`S3RES_LOG_ERROR` .. `S3RES_LOG_TRACE`; below is error, above
/// trace) through the runtime's logger (stderr). Without [`s3res_init_logging`] nothing is
/// written.
///
/// # Safety
///
/// `message` is NULL (nothing is logged) or a NUL-terminated string.
#[no_mangle]
pub unsafe extern "C" fn s3res_log(level: c_int, message: *const c_char) {
    guard((), || {
        if message.is_null() {
            return;
        }
        // SAFETY: not NULL (checked), NUL-terminated by the caller's promise.
        let text = unsafe { CStr::from_ptr(message) }.to_string_lossy();
        match level {
            ..=S3RES_LOG_ERROR => tracing::error!("{text}"),
            S3RES_LOG_WARN => tracing::warn!("{text}"),
            S3RES_LOG_INFO => tracing::info!("{text}"),
            S3RES_LOG_DEBUG => tracing::debug!("{text}"),
            _ => tracing::trace!("{text}"),
        }
    })
}

// ---------------------------------------------------------------------------------------------
// The runtime
// ---------------------------------------------------------------------------------------------

/// Starts the runtime, as `replica_rt::init`: reads the port map, installs the fault-injection
/// hooks and, in a replica, the restart handler (SIGCHLD ignored, memory locked). Also ignores
/// SIGPIPE, as a Rust program does, so a closed output is an `-EPIPE` from [`s3res_send`]
/// rather than a silent death. Once per process, before any other thread exists; stores the
/// runtime in `*rt`. 0, or `-EALREADY` (a second call), `-EINVAL` (a bad port map),
/// `-ENAMETOOLONG` (voter socket path), or the errno of a refused signal handler.
///
/// # Safety
///
/// `rt` is NULL (`-EINVAL`) or valid for writing one pointer.
#[no_mangle]
pub unsafe extern "C" fn s3res_init(rt: *mut *mut S3resRuntime) -> c_int {
    guard_rc(|| {
        if rt.is_null() {
            return null_arg("s3res_init", "rt");
        }
        if let Err(e) = replica_rt::sys::ignore_signal(libc::SIGPIPE) {
            return fail(os_code(&e), &e);
        }
        match replica_rt::init() {
            Ok(runtime) => {
                let boxed = Box::into_raw(Box::new(S3resRuntime { rt: runtime }));
                // SAFETY: not NULL (checked), valid for writes by the caller's promise.
                unsafe { rt.write(boxed) };
                0
            }
            Err(e) => fail(init_code(&e), &e),
        }
    })
}

/// Frees the runtime (the ports taken from it stay usable). NULL is ignored.
///
/// # Safety
///
/// `rt` is NULL or a runtime from [`s3res_init`] not freed before.
#[no_mangle]
pub unsafe extern "C" fn s3res_runtime_free(rt: *mut S3resRuntime) {
    guard((), || {
        if !rt.is_null() {
            // SAFETY: made by Box::into_raw in s3res_init and not freed (caller's promise).
            drop(unsafe { Box::from_raw(rt) });
        }
    })
}

/// `S3RES_MODE_STANDALONE`, `S3RES_MODE_UNPROTECTED` or `S3RES_MODE_REPLICA`; `-EINVAL` for NULL.
///
/// # Safety
///
/// `rt` is NULL or a live runtime from [`s3res_init`].
#[no_mangle]
pub unsafe extern "C" fn s3res_mode(rt: *const S3resRuntime) -> c_int {
    guard_rc(|| {
        // SAFETY: NULL or live (caller's promise).
        let Some(rt) = (unsafe { rt.as_ref() }) else {
            return null_arg("s3res_mode", "rt");
        };
        match rt.rt.mode() {
            Mode::Standalone => S3RES_MODE_STANDALONE,
            Mode::Unprotected => S3RES_MODE_UNPROTECTED,
            Mode::Replica => S3RES_MODE_REPLICA,
        }
    })
}

/// `S3RES_REPLICA` as read at init (a forked replica keeps its donor's), or -1 when the
/// process is not a replica; `-EINVAL` for NULL.
///
/// # Safety
///
/// `rt` is NULL or a live runtime from [`s3res_init`].
#[no_mangle]
pub unsafe extern "C" fn s3res_replica_index(rt: *const S3resRuntime) -> c_int {
    guard_rc(|| {
        // SAFETY: NULL or live (caller's promise).
        let Some(rt) = (unsafe { rt.as_ref() }) else {
            return null_arg("s3res_replica_index", "rt");
        };
        rt.rt
            .replica_index()
            .and_then(|i| c_int::try_from(i).ok())
            .unwrap_or(-1)
    })
}

/// Takes the input port `name` (once) into `*port`. 0, or `-ENOENT` (no such port; the message
/// lists the ones there are), `-EBUSY` (taken already), `-EBADF` (its fd is not open, or not
/// for reading), `-EINVAL` (NULL or non-UTF-8 argument).
///
/// # Safety
///
/// `rt` is NULL or a live runtime; `name` is NULL or NUL-terminated; `port` is NULL or valid
/// for writing one pointer.
#[no_mangle]
pub unsafe extern "C" fn s3res_input(
    rt: *mut S3resRuntime,
    name: *const c_char,
    port: *mut *mut S3resIn,
) -> c_int {
    // SAFETY: the caller's promises, passed on.
    unsafe {
        take_port(rt, name, port, "s3res_input", Runtime::input, |p| S3resIn {
            name: c_name(p.name()),
            port: p,
        })
    }
}

/// Takes the output port `name` (once) into `*port`. Errors as [`s3res_input`].
///
/// # Safety
///
/// As [`s3res_input`].
#[no_mangle]
pub unsafe extern "C" fn s3res_output(
    rt: *mut S3resRuntime,
    name: *const c_char,
    port: *mut *mut S3resOut,
) -> c_int {
    // SAFETY: the caller's promises, passed on.
    unsafe {
        take_port(rt, name, port, "s3res_output", Runtime::output, |p| {
            S3resOut {
                name: c_name(p.name()),
                port: p,
            }
        })
    }
}

/// The body of [`s3res_input`] and [`s3res_output`]: `take` the port `name` from `rt`, `wrap`
/// it, and store it boxed in `*port`.
///
/// # Safety
///
/// As [`s3res_input`].
unsafe fn take_port<P, H>(
    rt: *mut S3resRuntime,
    name: *const c_char,
    port: *mut *mut H,
    function: &str,
    take: impl FnOnce(&mut Runtime, &str) -> Result<P, replica_rt::PortError>,
    wrap: impl FnOnce(P) -> H,
) -> c_int {
    guard_rc(|| {
        // SAFETY: NULL or live (caller's promise).
        let Some(rt) = (unsafe { rt.as_mut() }) else {
            return null_arg(function, "rt");
        };
        // SAFETY: NULL or NUL-terminated (caller's promise).
        let name = match unsafe { str_arg(name, function, "name") } {
            Ok(n) => n,
            Err(rc) => return rc,
        };
        if port.is_null() {
            return null_arg(function, "port");
        }
        match take(&mut rt.rt, name) {
            Ok(p) => {
                let boxed = Box::into_raw(Box::new(wrap(p)));
                // SAFETY: not NULL (checked), valid for writes (caller's promise).
                unsafe { port.write(boxed) };
                0
            }
            Err(e) => fail(port_code(&e), &e),
        }
    })
}

/// Closes an input port (its fd is closed). NULL is ignored.
///
/// # Safety
///
/// `port` is NULL or a port from [`s3res_input`] not closed before; payloads it returned are
/// invalid afterwards.
#[no_mangle]
pub unsafe extern "C" fn s3res_in_close(port: *mut S3resIn) {
    guard((), || {
        if !port.is_null() {
            // SAFETY: made by Box::into_raw in s3res_input, not freed (caller's promise).
            drop(unsafe { Box::from_raw(port) });
        }
    })
}

/// Closes an output port, which ends the stream downstream. NULL is ignored.
///
/// # Safety
///
/// `port` is NULL or a port from [`s3res_output`] not closed before.
#[no_mangle]
pub unsafe extern "C" fn s3res_out_close(port: *mut S3resOut) {
    guard((), || {
        if !port.is_null() {
            // SAFETY: made by Box::into_raw in s3res_output, not freed (caller's promise).
            drop(unsafe { Box::from_raw(port) });
        }
    })
}

// ---------------------------------------------------------------------------------------------
// Frames
// ---------------------------------------------------------------------------------------------

/// Receives the next whole frame, blocking: 1 with `*payload`/`*len` set (the payload is
/// borrowed from the port until its next receive or close), 0 at end of stream (`*payload`
/// NULL, `*len` 0), `-EPROTO` for a bad frame stream (too large, cut), or another `-errno`.
///
/// # Safety
///
/// `port` is NULL or a live input port; `payload` and `len` are NULL or valid for writes.
#[no_mangle]
pub unsafe extern "C" fn s3res_recv(
    port: *mut S3resIn,
    payload: *mut *const u8,
    len: *mut usize,
) -> c_int {
    let f = |p: &mut InPort| match p.recv() {
        Ok(frame) => {
            let status = c_int::from(frame.is_some());
            // SAFETY: `receive` checked both non-NULL; valid for writes (caller's promise).
            unsafe { put_frame(payload, len, frame) };
            status
        }
        Err(e) => fail(recv_code(&e), &e),
    };
    // SAFETY: the caller's promises, passed on.
    unsafe { receive(port, payload, len, "s3res_recv", f) }
}

/// Receives the next frame if one can be had without blocking: 1 (a frame, as
/// [`s3res_recv`]), 0 (end of stream), `-EAGAIN` (no whole frame yet), or an error.
///
/// # Safety
///
/// As [`s3res_recv`].
#[no_mangle]
pub unsafe extern "C" fn s3res_try_recv(
    port: *mut S3resIn,
    payload: *mut *const u8,
    len: *mut usize,
) -> c_int {
    let f = |p: &mut InPort| {
        // SAFETY: `receive` checked both non-NULL; valid for writes (caller's promise).
        unsafe { try_status(p.try_recv(), payload, len) }
    };
    // SAFETY: the caller's promises, passed on.
    unsafe { receive(port, payload, len, "s3res_try_recv", f) }
}

/// Receives the next frame, waiting at most `timeout_us` microseconds (negative: no limit, as
/// [`s3res_recv`]). Returns as [`s3res_try_recv`]; `-EAGAIN` when none came whole in time.
///
/// # Safety
///
/// As [`s3res_recv`].
#[no_mangle]
pub unsafe extern "C" fn s3res_recv_timeout(
    port: *mut S3resIn,
    timeout_us: i64,
    payload: *mut *const u8,
    len: *mut usize,
) -> c_int {
    let f = |p: &mut InPort| {
        let got = match timeout(timeout_us) {
            Some(t) => p.recv_timeout(t),
            None => p.recv().map(|f| f.map_or(TryRecv::Closed, TryRecv::Frame)),
        };
        // SAFETY: `receive` checked both non-NULL; valid for writes (caller's promise).
        unsafe { try_status(got, payload, len) }
    };
    // SAFETY: the caller's promises, passed on.
    unsafe { receive(port, payload, len, "s3res_recv_timeout", f) }
}

/// The common part of the receives: checks the arguments, then runs `f` on the port.
///
/// # Safety
///
/// As [`s3res_recv`].
unsafe fn receive(
    port: *mut S3resIn,
    payload: *mut *const u8,
    len: *mut usize,
    function: &str,
    f: impl FnOnce(&mut InPort) -> c_int,
) -> c_int {
    guard_rc(|| {
        // SAFETY: NULL or live (caller's promise).
        let Some(port) = (unsafe { port.as_mut() }) else {
            return null_arg(function, "port");
        };
        if payload.is_null() || len.is_null() {
            return null_arg(function, "payload/len");
        }
        f(&mut port.port)
    })
}

/// Waits until at least one of `ports[0..n]` is ready (a whole frame buffered, or its fd
/// readable: data, end of stream or error), or `timeout_us` passes (negative: no limit). Sets
/// bit i of `*ready` for each ready `ports[i]` and returns how many are ready (0 on timeout);
/// `-EINVAL` for NULL arguments, n = 0 or n > 32. A ready port may still answer `-EAGAIN` to
/// [`s3res_try_recv`] (only part of a frame has come): wait again.
///
/// # Safety
///
/// `ports` is NULL or points at `n` pointers, each NULL (`-EINVAL`) or a live input port;
/// `ready` is NULL or valid for writes.
#[no_mangle]
pub unsafe extern "C" fn s3res_wait_any(
    ports: *const *mut S3resIn,
    n: usize,
    timeout_us: i64,
    ready: *mut u32,
) -> c_int {
    guard_rc(|| {
        if ports.is_null() || ready.is_null() {
            return null_arg("s3res_wait_any", "ports/ready");
        }
        if n == 0 || n > MAX_PORTS {
            return fail_msg(
                libc::EINVAL,
                &format!("s3res_wait_any: {n} ports; give 1 to {MAX_PORTS}"),
            );
        }
        // SAFETY: not NULL (checked) and `n` pointers long (caller's promise).
        let given = unsafe { std::slice::from_raw_parts(ports, n) };
        // SAFETY: each is NULL or a live input port (caller's promise).
        let Some(first) = (unsafe { given[0].as_ref() }) else {
            return null_arg("s3res_wait_any", "ports[0]");
        };
        // A fixed array: waiting allocates nothing, as in replica-rt.
        let mut refs: [&InPort; MAX_PORTS] = [&first.port; MAX_PORTS];
        for (slot, &p) in refs.iter_mut().zip(given) {
            // SAFETY: as above.
            match unsafe { p.as_ref() } {
                Some(p) => *slot = &p.port,
                None => return null_arg("s3res_wait_any", "ports[i]"),
            }
        }
        match replica_rt::wait_any(&refs[..n], timeout(timeout_us)) {
            Ok(r) => {
                let mask = (0..n)
                    .filter(|&i| r.is_ready(i))
                    .fold(0u32, |m, i| m | 1 << i);
                // SAFETY: not NULL (checked), valid for writes (caller's promise).
                unsafe { ready.write(mask) };
                mask.count_ones() as c_int
            }
            Err(e) => fail(os_code(&e), &e),
        }
    })
}

/// Sends `payload[0..len]` as one whole frame, blocking until it is written (a pending SDC
/// injection flips one bit of the copy sent). 0, `-EMSGSIZE` (above the port's maximum),
/// `-EPIPE` (nobody reads the channel any more), or another `-errno`.
///
/// # Safety
///
/// `port` is NULL or a live output port; `payload` is valid for reading `len` bytes (it may be
/// NULL when `len` is 0).
#[no_mangle]
pub unsafe extern "C" fn s3res_send(port: *mut S3resOut, payload: *const u8, len: usize) -> c_int {
    guard_rc(|| {
        // SAFETY: NULL or live (caller's promise).
        let Some(port) = (unsafe { port.as_mut() }) else {
            return null_arg("s3res_send", "port");
        };
        let bytes: &[u8] = if len == 0 {
            &[]
        } else if payload.is_null() {
            return null_arg("s3res_send", "payload");
        } else {
            // SAFETY: not NULL (checked), valid for `len` bytes (caller's promise).
            unsafe { std::slice::from_raw_parts(payload, len) }
        };
        match port.port.send(bytes) {
            Ok(()) => 0,
            Err(e) => fail(send_code(&e), &e),
        }
    })
}

// ---------------------------------------------------------------------------------------------
// Port facts
// ---------------------------------------------------------------------------------------------

/// The port's fd (for `poll` together with fds of your own; the number stays the same across a
/// restart, the pipe behind it does not); `-EINVAL` for NULL.
///
/// # Safety
///
/// `port` is NULL or a live input port.
#[no_mangle]
pub unsafe extern "C" fn s3res_in_fd(port: *const S3resIn) -> c_int {
    guard_rc(|| {
        // SAFETY: NULL or live (caller's promise).
        match unsafe { port.as_ref() } {
            Some(p) => std::os::fd::AsRawFd::as_raw_fd(&p.port),
            None => null_arg("s3res_in_fd", "port"),
        }
    })
}

/// As [`s3res_in_fd`], for an output port.
///
/// # Safety
///
/// `port` is NULL or a live output port.
#[no_mangle]
pub unsafe extern "C" fn s3res_out_fd(port: *const S3resOut) -> c_int {
    guard_rc(|| {
        // SAFETY: NULL or live (caller's promise).
        match unsafe { port.as_ref() } {
            Some(p) => std::os::fd::AsRawFd::as_raw_fd(&p.port),
            None => null_arg("s3res_out_fd", "port"),
        }
    })
}

/// The port's name (valid while the port is open); NULL for NULL.
///
/// # Safety
///
/// `port` is NULL or a live input port.
#[no_mangle]
pub unsafe extern "C" fn s3res_in_name(port: *const S3resIn) -> *const c_char {
    guard(ptr::null(), || {
        // SAFETY: NULL or live (caller's promise).
        unsafe { port.as_ref() }.map_or(ptr::null(), |p| p.name.as_ptr())
    })
}

/// As [`s3res_in_name`], for an output port.
///
/// # Safety
///
/// `port` is NULL or a live output port.
#[no_mangle]
pub unsafe extern "C" fn s3res_out_name(port: *const S3resOut) -> *const c_char {
    guard(ptr::null(), || {
        // SAFETY: NULL or live (caller's promise).
        unsafe { port.as_ref() }.map_or(ptr::null(), |p| p.name.as_ptr())
    })
}

/// The largest payload the port accepts (`max_frame` of its channel); 0 for NULL.
///
/// # Safety
///
/// `port` is NULL or a live input port.
#[no_mangle]
pub unsafe extern "C" fn s3res_in_max_frame(port: *const S3resIn) -> usize {
    guard(0, || {
        // SAFETY: NULL or live (caller's promise).
        unsafe { port.as_ref() }.map_or(0, |p| p.port.max_frame())
    })
}

/// As [`s3res_in_max_frame`], for an output port.
///
/// # Safety
///
/// `port` is NULL or a live output port.
#[no_mangle]
pub unsafe extern "C" fn s3res_out_max_frame(port: *const S3resOut) -> usize {
    guard(0, || {
        // SAFETY: NULL or live (caller's promise).
        unsafe { port.as_ref() }.map_or(0, |p| p.port.max_frame())
    })
}

/// Bytes read from the channel but not yet returned as frames; 0 for NULL.
///
/// # Safety
///
/// `port` is NULL or a live input port.
#[no_mangle]
pub unsafe extern "C" fn s3res_in_buffered(port: *const S3resIn) -> usize {
    guard(0, || {
        // SAFETY: NULL or live (caller's promise).
        unsafe { port.as_ref() }.map_or(0, |p| p.port.buffered())
    })
}

/// 1 if a whole frame is buffered in the port (a receive would not read), else 0; `-EINVAL`
/// for NULL.
///
/// # Safety
///
/// `port` is NULL or a live input port.
#[no_mangle]
pub unsafe extern "C" fn s3res_in_has_frame(port: *const S3resIn) -> c_int {
    guard_rc(|| {
        // SAFETY: NULL or live (caller's promise).
        match unsafe { port.as_ref() } {
            Some(p) => c_int::from(p.port.has_buffered_frame()),
            None => null_arg("s3res_in_has_frame", "port"),
        }
    })
}

// ---------------------------------------------------------------------------------------------
// Memory and signals
// ---------------------------------------------------------------------------------------------

/// `mlockall(MCL_CURRENT | MCL_FUTURE)`: keeps every page resident. [`s3res_init`] already
/// locks a replica's memory as the component's `lock_memory` says (`all`, the default, is this
/// call; `used` locks on fault), and says so in the log if it is refused; this is for other
/// modes, or again after mapping much memory (under `used` it populates everything). 0 or `-errno` (`-ENOMEM`/`-EPERM`: raise RLIMIT_MEMLOCK or grant
/// CAP_IPC_LOCK).
#[no_mangle]
pub extern "C" fn s3res_lock_memory() -> c_int {
    guard_rc(|| match replica_rt::sys::lock_all_memory() {
        Ok(()) => 0,
        Err(e) => fail(os_code(&e), &e),
    })
}

/// The voter's restart signal (SIGUSR1): handled by the runtime; never install your own.
#[no_mangle]
pub extern "C" fn s3res_signal_restart() -> c_int {
    signals::RESTART
}

/// The SDC injection signal (SIGUSR2): flips a bit of the next frame sent.
#[no_mangle]
pub extern "C" fn s3res_signal_inject_sdc() -> c_int {
    signals::INJECT_SDC
}

/// The control-flow-error injection signal (signal 36, glibc's SIGRTMIN+2): the process spins
/// forever.
#[no_mangle]
pub extern "C" fn s3res_signal_inject_cfe() -> c_int {
    guard_rc(signals::inject_cfe)
}

/// The variable-level injection signal (signal 37, glibc's SIGRTMIN+3): XORs masks into bytes
/// of the next frame.
#[no_mangle]
pub extern "C" fn s3res_signal_inject_var() -> c_int {
    guard_rc(signals::inject_var)
}

#[cfg(test)]
mod tests;
