//! Probes for the system's C and C++ compilers, which the tests of this crate use to build the
//! C example and the header checks. As in `testkit/build.rs`: a test that needs one is
//! `#[cfg_attr(not(s3res_cc), ignore = "reason")]`, so where the compiler is missing `cargo
//! test` lists it as ignored with the reason instead of passing it silently; where it is there,
//! the test runs, and fails naming the compiler if it has gone missing since the build.
//!
//! | cfg         | set when                          |
//! |-------------|-----------------------------------|
//! | `s3res_cc`  | `cc --version` succeeds            |
//! | `s3res_cxx` | `c++ --version` succeeds           |

use std::process::{Command, Stdio};

fn main() {
    for cfg in ["s3res_cc", "s3res_cxx"] {
        println!("cargo::rustc-check-cfg=cfg({cfg})");
    }
    println!("cargo::rerun-if-changed=build.rs");
    println!("cargo::rerun-if-env-changed=PATH");
    for (cfg, compiler) in [("s3res_cc", "cc"), ("s3res_cxx", "c++")] {
        let found = Command::new(compiler)
            .arg("--version")
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .status()
            .is_ok_and(|s| s.success());
        if found {
            println!("cargo::rustc-cfg={cfg}");
        }
    }
}
