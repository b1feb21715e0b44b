//! # s3res-description
//!
//! The system description (`system.json`) and nothing that runs it, so that bootstrap and the
//! tools that read a description (`s3res-inject`) share one parser and one set of checks:
//!
//! - [`description`]: parsing and checking a description; every error names the file, line
//!   and field ([`posindex`] maps JSON paths to positions);
//! - [`plan`]: the checked system ([`plan::SystemPlan`]), which bootstrap runs;
//! - [`exec`]: finding the programs a description names, and s3res's own binaries (voter,
//!   injector, bootstrap) beside the running one or on `PATH`.

#![forbid(unsafe_code)]

pub mod description;
pub mod exec;
pub mod plan;
pub mod posindex;
