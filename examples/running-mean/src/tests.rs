//! Unit tests of the frame parsing and encoding in `main.rs`.

use super::{encode_answer, parse_sample};

#[test]
fn a_sample_is_eight_little_endian_bytes() {
    assert_eq!(parse_sample(&2.5f64.to_le_bytes()).unwrap(), 2.5);
    assert_eq!(
        parse_sample(&(-0.0f64).to_le_bytes()).unwrap().to_bits(),
        (-0.0f64).to_bits()
    );
    let nan = parse_sample(&f64::NAN.to_le_bytes()).unwrap();
    assert!(nan.is_nan());
}

#[test]
fn a_frame_of_the_wrong_size_is_an_error_naming_the_size() {
    for len in [0, 1, 7, 9, 16] {
        let err = parse_sample(&vec![0u8; len]).unwrap_err().to_string();
        assert!(err.contains("must be 8 bytes"), "{err}");
        assert!(err.contains(&format!("got {len}")), "{err}");
    }
}

#[test]
fn the_answer_is_count_then_mean() {
    let a = encode_answer(3, 1.25);
    assert_eq!(a[..8], 3u64.to_le_bytes());
    assert_eq!(a[8..], 1.25f64.to_le_bytes());
}
