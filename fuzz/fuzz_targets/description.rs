//! Validation of a whole system description (`s3res_bootstrap::description::parse`): any text
//! gives a plan or an error that names a line of the text, never a panic. Executables are
//! looked up in /usr/bin and /bin, so descriptions that name `true` or `sh` get past that
//! check to the ones behind it.
#![no_main]

use std::path::PathBuf;

use libfuzzer_sys::fuzz_target;
use s3res_bootstrap::description::{parse, HostContext};
use s3res_bootstrap::exec::SearchPath;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let ctx = HostContext {
        base_dir: PathBuf::from("/usr/bin"),
        search: SearchPath {
            self_dir: None,
            path_dirs: vec![PathBuf::from("/usr/bin"), PathBuf::from("/bin")],
        },
        cpus: vec![0, 1],
    };
    let lines = text.matches('\n').count() + 1;
    match parse("fuzz.json", text, &ctx) {
        Ok(plan) => {
            // A plan prints (what `--check` shows) without panicking.
            let _ = format!("{plan:?}");
        }
        Err(e) => {
            let line = e.line();
            assert!((1..=lines).contains(&line), "line {line} of {lines}: {e}");
            let _ = e.to_string();
        }
    }
});
