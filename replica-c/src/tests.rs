//! The entry points answer bad arguments with `-EINVAL` and a message instead of crashing, and
//! a panic inside comes back as a status. (The header is checked against the library by
//! `tests/c_abi.rs`.)

use std::ffi::CStr;

use super::*;

fn last_error() -> String {
    // SAFETY: s3res_last_error returns a NUL-terminated string owned by this thread.
    unsafe { CStr::from_ptr(s3res_last_error()) }
        .to_string_lossy()
        .into_owned()
}

#[test]
fn null_arguments_are_einval_with_a_message() {
    let mut payload = ptr::null();
    let mut len = 0usize;
    // SAFETY: NULL handles are documented as accepted (-EINVAL); the out-pointers are valid.
    let rc = unsafe { s3res_recv(ptr::null_mut(), &mut payload, &mut len) };
    assert_eq!(rc, -libc::EINVAL);
    assert!(
        last_error().contains("s3res_recv: `port` is NULL"),
        "{}",
        last_error()
    );
    // SAFETY: as above.
    unsafe {
        assert_eq!(s3res_send(ptr::null_mut(), ptr::null(), 0), -libc::EINVAL);
        assert_eq!(s3res_init(ptr::null_mut()), -libc::EINVAL);
        assert_eq!(s3res_mode(ptr::null()), -libc::EINVAL);
        assert_eq!(s3res_in_fd(ptr::null()), -libc::EINVAL);
        assert_eq!(s3res_in_max_frame(ptr::null()), 0);
        assert!(s3res_out_name(ptr::null()).is_null());
        let mut ready = 0u32;
        assert_eq!(s3res_wait_any(ptr::null(), 1, 0, &mut ready), -libc::EINVAL);
        // Closing NULL is a no-op.
        s3res_in_close(ptr::null_mut());
        s3res_out_close(ptr::null_mut());
        s3res_runtime_free(ptr::null_mut());
        s3res_log(S3RES_LOG_INFO, ptr::null());
    }
    assert!(last_error().contains("s3res_wait_any"), "{}", last_error());
}

#[test]
fn a_panic_becomes_enotrecoverable_not_an_abort() {
    let rc = guard_rc(|| panic!("boom"));
    assert_eq!(rc, -libc::ENOTRECOVERABLE);
    assert!(last_error().contains("boom"), "{}", last_error());
}

#[test]
fn errors_keep_their_causes() {
    let e = RecvError::Io {
        port: "samples".into(),
        source: std::io::Error::from_raw_os_error(libc::EBADF),
    };
    assert_eq!(fail(recv_code(&e), &e), -libc::EBADF);
    let msg = last_error();
    assert!(
        msg.starts_with("input port \"samples\": read failed: "),
        "{msg}"
    );
}

#[test]
fn the_version_and_signals_are_there() {
    // SAFETY: a static NUL-terminated string.
    let v = unsafe { CStr::from_ptr(s3res_version()) };
    assert_eq!(v.to_str().unwrap(), env!("CARGO_PKG_VERSION"));
    assert_eq!(s3res_signal_restart(), libc::SIGUSR1);
    assert_eq!(s3res_signal_inject_sdc(), libc::SIGUSR2);
    assert_eq!(s3res_signal_inject_cfe(), 36);
    assert_eq!(s3res_signal_inject_var(), 37);
}
