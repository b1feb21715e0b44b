//! The system description's position index (`s3res_bootstrap::posindex`): the tokenizer that
//! finds the line of every value and the duplicate keys serde_json merges silently. On any text
//! it must return an index or an error with a line inside the text, never panic; on text
//! serde_json accepts it must never report a syntax error, and every line it gives must exist.
#![no_main]

use libfuzzer_sys::fuzz_target;
use s3res_bootstrap::posindex::{element_path, member_path, IndexError, PositionIndex};

/// Whether some key makes two values share a path: an empty key (its path is its object's),
/// or one with `.` or `[` (`{"a.b": 1}` and `{"a": {"b": 1}}` both have `a.b`). Paths are
/// written as serde_path_to_error writes them, so that its errors find their lines; for such
/// keys they are ambiguous by design, and the index keeps one of the colliding values.
fn ambiguous(value: &serde_json::Value) -> bool {
    match value {
        serde_json::Value::Object(map) => map
            .iter()
            .any(|(k, v)| k.is_empty() || k.contains(['.', '[']) || ambiguous(v)),
        serde_json::Value::Array(items) => items.iter().any(ambiguous),
        _ => false,
    }
}

/// Walks `value` and checks that the index knows every path in it, and, when no two values
/// share a path (`exact`), every object's keys.
fn walk(index: &PositionIndex, value: &serde_json::Value, path: &str, lines: usize, exact: bool) {
    let line = index.line_or_parent(path);
    assert!(
        (1..=lines).contains(&line),
        "line {line} of {lines} for {path:?}"
    );
    match value {
        serde_json::Value::Object(map) => {
            // serde_json keeps one entry per distinct key; the index saw them all.
            if exact {
                assert_eq!(index.keys(path).len(), map.len(), "keys of {path:?}");
            }
            for (k, v) in map {
                let p = member_path(path, k);
                assert!(index.line(&p).is_some(), "no line for {p:?}");
                walk(index, v, &p, lines, exact);
            }
        }
        serde_json::Value::Array(items) => {
            for (i, v) in items.iter().enumerate() {
                let p = element_path(path, i);
                assert!(index.line(&p).is_some(), "no line for {p:?}");
                walk(index, v, &p, lines, exact);
            }
        }
        _ => {}
    }
}

fuzz_target!(|data: &[u8]| {
    let text = String::from_utf8_lossy(data);
    // A text of n newlines has n + 1 lines.
    let lines = text.matches('\n').count() + 1;
    let parsed = serde_json::from_str::<serde_json::Value>(&text);
    match PositionIndex::build(&text) {
        Ok(index) => {
            if let Ok(value) = &parsed {
                walk(&index, value, "", lines, !ambiguous(value));
            }
        }
        Err(e) => {
            assert!((1..=lines).contains(&e.line()), "{e:?} in {lines} lines");
            if parsed.is_ok() {
                assert!(
                    matches!(e, IndexError::DuplicateKey { .. }),
                    "serde_json accepts what the index calls {e:?}"
                );
            }
        }
    }
});
