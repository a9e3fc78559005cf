//! Exact float comparisons: numbers read from JSON, bit-for-bit equality,
//! and the check that serde_json reads back every f64 it writes.

use serde_json::Value;

/// A JSON array of numbers.
pub fn floats(v: &Value) -> Vec<f64> {
    v.as_array()
        .unwrap_or_else(|| panic!("not an array: {v}"))
        .iter()
        .map(|x| x.as_f64().unwrap_or_else(|| panic!("not a number: {x}")))
        .collect()
}

/// Bit-for-bit equality of float slices (NaN-safe, -0 ≠ +0).
pub fn assert_bits_eq(got: &[f64], want: &[f64], what: &str) {
    let g: Vec<u64> = got.iter().map(|x| x.to_bits()).collect();
    let w: Vec<u64> = want.iter().map(|x| x.to_bits()).collect();
    assert_eq!(g, w, "{what}: got {got:?}, want {want:?}");
}

/// serde_json in this test build reads back every f64 it writes exactly
/// (the `float_roundtrip` feature), or bit-equality checks would be moot.
pub fn assert_float_roundtrip() {
    let mut x = 0.1f64;
    for i in 0..10_000 {
        x = (x * 1.618_033_988_749_895 + 0.3).fract() * 10f64.powi(i % 40 - 20);
        let text = serde_json::to_string(&x).expect("to_string");
        let back: f64 = serde_json::from_str(&text).expect("from_str");
        assert_eq!(back.to_bits(), x.to_bits(), "{x} → {text} → {back}");
    }
}
