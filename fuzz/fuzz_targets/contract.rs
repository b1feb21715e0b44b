//! The replica contract: the port map a component reads from `S3RES_PORTS`
//! (`replica_rt::parse_port_map`, the check `init` does), and the fixed-size messages of the
//! restart handshake (`Hello`, `Spare`, `Ready`) and the `var` injection request a replica decodes from a
//! signal's value. Any bytes give a value or an error, never a panic; what is accepted is what
//! the contract promises, and the messages round-trip.
#![no_main]

use libfuzzer_sys::fuzz_target;
use s3res_protocol::contract::handshake::{Hello, Ready, Spare};
use s3res_protocol::contract::signals::VarRequest;
use s3res_protocol::contract::MAX_PORTS;

fuzz_target!(|data: &[u8]| {
    // Handshake messages: any bytes decode, and encode back to the same bytes.
    if let Some(b) = data.get(..Hello::SIZE) {
        let b: [u8; Hello::SIZE] = b.try_into().unwrap();
        assert_eq!(Hello::from_bytes(b).to_bytes(), b);
    }
    if let Some(b) = data.get(..Spare::SIZE) {
        let b: [u8; Spare::SIZE] = b.try_into().unwrap();
        assert_eq!(Spare::from_bytes(b).to_bytes(), b);
    }
    if let Some(b) = data.get(..Ready::SIZE) {
        let b: [u8; Ready::SIZE] = b.try_into().unwrap();
        assert_eq!(Ready::from_bytes(b).to_bytes(), b);
    }
    // A var request is a signal's value: any i32 decodes to a request or to nothing, and a
    // request encodes back to the same value.
    for word in data.chunks_exact(4).take(64) {
        let value = i32::from_le_bytes(word.try_into().unwrap());
        if let Some(req) = VarRequest::from_value(value) {
            assert!(req.offset <= VarRequest::MAX_OFFSET);
            assert_eq!(req.to_value(), Some(value));
        }
    }
    // The port map, as the environment gives it.
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    if let Ok(map) = replica_rt::parse_port_map(text) {
        assert!(map.ports.len() <= MAX_PORTS);
        for (i, p) in map.ports.iter().enumerate() {
            assert!(p.fd >= 0 && p.max_frame <= u32::MAX as usize);
            for q in &map.ports[..i] {
                assert!(q.fd != p.fd && (q.name != p.name || q.dir != p.dir));
            }
        }
    }
});
