//! Shared helpers of the example components.
