//! The clock of every timestamp the formats carry (`ts_ns` of events, `updated_ns` and
//! `since_ns` of the live view): CLOCK_MONOTONIC in nanoseconds, the same in every process of
//! one machine.

/// CLOCK_MONOTONIC in nanoseconds. Async-signal-safe (one `clock_gettime`, no allocation).
pub fn monotonic_ns() -> u64 {
    // CLOCK_MONOTONIC always exists on Linux; clock_gettime cannot fail for it.
    let ts = nix::time::clock_gettime(nix::time::ClockId::CLOCK_MONOTONIC)
        .expect("CLOCK_MONOTONIC exists");
    ts.tv_sec() as u64 * 1_000_000_000 + ts.tv_nsec() as u64
}

#[cfg(test)]
mod tests {
    #[test]
    fn monotonic_ns_does_not_go_back() {
        let a = super::monotonic_ns();
        let b = super::monotonic_ns();
        assert!(a > 0 && b >= a);
    }
}
