//! Test harness: boots the real s3res-bootstrap in a temp dir and tears it down on drop.
