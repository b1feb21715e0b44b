//! # replica-rt
//!
//! The library an s3res component binary links. The same binary runs unprotected (started by
//! `s3res-bootstrap`) or as one replica of a protected component (started by `s3res-voter`)
//! without change.
//!
//! See `docs/writing-a-component.md` for a complete example.

pub mod contract;
pub mod frame;
pub mod sys;
