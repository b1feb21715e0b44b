//! The voter's plan (`s3res-voter --plan JSON`): parsed by `VoterPlan::from_json` and checked by
//! the voter's `validate` before anything starts. Any text gives a plan or an error, never a
//! panic; a plan the voter accepts survives a round trip through its JSON unchanged.
#![no_main]

use libfuzzer_sys::fuzz_target;
use s3res_protocol::plan::VoterPlan;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let Ok(plan) = VoterPlan::from_json(text) else {
        return;
    };
    let checked = s3res_voter::validate_plan(&plan);
    let again = VoterPlan::from_json(&plan.to_json()).expect("a plan's own JSON reads back");
    assert_eq!(again, plan);
    if checked.is_ok() {
        assert!(plan.replicas >= 1 && plan.timeout_us > 0);
        assert!(plan.inputs.len() + plan.outputs.len() <= s3res_protocol::contract::MAX_PORTS);
    }
});
