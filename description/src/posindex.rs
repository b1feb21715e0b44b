//! Where each value of a JSON text sits, by path, so that errors found after parsing (an unknown
//! component, a CPU the machine lacks) can still point at a line. It also finds duplicate object
//! keys, which serde_json accepts silently (the last one wins) but which in a description almost
//! always mean two components were given the same name.
//!
//! Paths look like `components.echo.priority` and `channels[1].from`; the root is `""`.
//! The index is built from text serde_json has already accepted, but it does not rely on that:
//! anything it cannot read is reported as an error with a line, never a panic.

use std::collections::HashMap;

use thiserror::Error;

/// What the tokenizer found wrong.
#[derive(Debug, Error, Clone, PartialEq, Eq)]
pub enum IndexError {
    /// The same key appears twice in one object.
    #[error("duplicate key `{key}`")]
    DuplicateKey {
        key: String,
        /// Path of the second occurrence.
        path: String,
        line: usize,
    },
    /// Not JSON (only reachable if the text was not checked by serde_json first).
    #[error("unreadable JSON: {what}")]
    Syntax { what: String, line: usize },
}

impl IndexError {
    pub fn line(&self) -> usize {
        match self {
            IndexError::DuplicateKey { line, .. } | IndexError::Syntax { line, .. } => *line,
        }
    }
}

/// Line (1-based) of every value by path, and the order of the keys of every object.
#[derive(Debug, Default, Clone)]
pub struct PositionIndex {
    lines: HashMap<String, usize>,
    keys: HashMap<String, Vec<String>>,
}

impl PositionIndex {
    /// Indexes `text`.
    pub fn build(text: &str) -> Result<Self, IndexError> {
        let mut t = Tokenizer {
            bytes: text.as_bytes(),
            pos: 0,
            line: 1,
            index: PositionIndex::default(),
        };
        t.skip_ws();
        t.value(String::new(), 0)?;
        t.skip_ws();
        if t.pos < t.bytes.len() {
            return Err(t.syntax("trailing characters after the top-level value"));
        }
        Ok(t.index)
    }

    /// Line of the value at `path`, if indexed.
    pub fn line(&self, path: &str) -> Option<usize> {
        self.lines.get(path).copied()
    }

    /// Line of `path`, or of its nearest indexed ancestor (`a.b[2].c` → `a.b[2]` → `a.b` → `a`),
    /// or 1. Used for errors about things that are implied rather than written (a missing field
    /// is reported at its object).
    pub fn line_or_parent(&self, path: &str) -> usize {
        let mut p = path;
        loop {
            if let Some(l) = self.line(p) {
                return l;
            }
            match p.rfind(['.', '[']) {
                Some(cut) => p = &p[..cut],
                None => return self.line("").unwrap_or(1),
            }
        }
    }

    /// Keys of the object at `path`, in document order.
    pub fn keys(&self, path: &str) -> &[String] {
        self.keys.get(path).map_or(&[], Vec::as_slice)
    }
}

/// Path of member `key` of the object at `parent`.
pub fn member_path(parent: &str, key: &str) -> String {
    if parent.is_empty() {
        key.to_owned()
    } else {
        format!("{parent}.{key}")
    }
}

/// Path of element `i` of the array at `parent`.
pub fn element_path(parent: &str, i: usize) -> String {
    format!("{parent}[{i}]")
}

/// Deeper than this is refused (serde_json's own limit is 128), so recursion stays bounded.
const MAX_DEPTH: usize = 256;

struct Tokenizer<'a> {
    bytes: &'a [u8],
    pos: usize,
    line: usize,
    index: PositionIndex,
}

impl Tokenizer<'_> {
    fn syntax(&self, what: &str) -> IndexError {
        IndexError::Syntax {
            what: what.to_owned(),
            line: self.line,
        }
    }

    fn peek(&self) -> Option<u8> {
        self.bytes.get(self.pos).copied()
    }

    fn skip_ws(&mut self) {
        while let Some(b) = self.peek() {
            match b {
                b'\n' => self.line += 1,
                b' ' | b'\t' | b'\r' => {}
                _ => return,
            }
            self.pos += 1;
        }
    }

    fn expect(&mut self, b: u8) -> Result<(), IndexError> {
        if self.peek() == Some(b) {
            self.pos += 1;
            Ok(())
        } else {
            Err(self.syntax(&format!("expected `{}`", b as char)))
        }
    }

    /// One value at `path`; the caller has skipped leading whitespace and recorded the line.
    fn value(&mut self, path: String, depth: usize) -> Result<(), IndexError> {
        if depth > MAX_DEPTH {
            return Err(self.syntax("nested too deeply"));
        }
        self.index.lines.entry(path.clone()).or_insert(self.line);
        match self.peek() {
            Some(b'{') => self.object(path, depth),
            Some(b'[') => self.array(path, depth),
            Some(b'"') => self.string().map(drop),
            Some(b'-' | b'0'..=b'9') => {
                self.number();
                Ok(())
            }
            Some(b't') => self.literal("true"),
            Some(b'f') => self.literal("false"),
            Some(b'n') => self.literal("null"),
            Some(_) => Err(self.syntax("expected a value")),
            None => Err(self.syntax("unexpected end of text")),
        }
    }

    fn object(&mut self, path: String, depth: usize) -> Result<(), IndexError> {
        self.expect(b'{')?;
        let mut keys: Vec<String> = Vec::new();
        self.skip_ws();
        if self.peek() == Some(b'}') {
            self.pos += 1;
            self.index.keys.insert(path, keys);
            return Ok(());
        }
        loop {
            self.skip_ws();
            let key_line = self.line;
            let key = self.string()?;
            let child = member_path(&path, &key);
            if keys.contains(&key) {
                return Err(IndexError::DuplicateKey {
                    key,
                    path: child,
                    line: key_line,
                });
            }
            keys.push(key);
            // A member is reported at its key's line: that is where a reader looks for it.
            self.index.lines.insert(child.clone(), key_line);
            self.skip_ws();
            self.expect(b':')?;
            self.skip_ws();
            self.value(child, depth + 1)?;
            self.skip_ws();
            match self.peek() {
                Some(b',') => self.pos += 1,
                Some(b'}') => {
                    self.pos += 1;
                    self.index.keys.insert(path, keys);
                    return Ok(());
                }
                _ => return Err(self.syntax("expected `,` or `}`")),
            }
        }
    }

    fn array(&mut self, path: String, depth: usize) -> Result<(), IndexError> {
        self.expect(b'[')?;
        self.skip_ws();
        if self.peek() == Some(b']') {
            self.pos += 1;
            return Ok(());
        }
        let mut i = 0;
        loop {
            self.skip_ws();
            self.value(element_path(&path, i), depth + 1)?;
            i += 1;
            self.skip_ws();
            match self.peek() {
                Some(b',') => self.pos += 1,
                Some(b']') => {
                    self.pos += 1;
                    return Ok(());
                }
                _ => return Err(self.syntax("expected `,` or `]`")),
            }
        }
    }

    /// A string token, decoded the way serde_json decodes it (so keys match serde's).
    fn string(&mut self) -> Result<String, IndexError> {
        self.expect(b'"')?;
        let mut out: Vec<u8> = Vec::new();
        loop {
            let Some(b) = self.peek() else {
                return Err(self.syntax("unterminated string"));
            };
            self.pos += 1;
            match b {
                b'"' => break,
                b'\\' => {
                    let Some(e) = self.peek() else {
                        return Err(self.syntax("unterminated escape"));
                    };
                    self.pos += 1;
                    let c = match e {
                        b'"' => '"',
                        b'\\' => '\\',
                        b'/' => '/',
                        b'b' => '\u{8}',
                        b'f' => '\u{c}',
                        b'n' => '\n',
                        b'r' => '\r',
                        b't' => '\t',
                        b'u' => self.unicode_escape()?,
                        _ => return Err(self.syntax("unknown escape")),
                    };
                    let mut buf = [0u8; 4];
                    out.extend_from_slice(c.encode_utf8(&mut buf).as_bytes());
                }
                b'\n' => return Err(self.syntax("newline inside a string")),
                _ => out.push(b),
            }
        }
        String::from_utf8(out).map_err(|_| self.syntax("string is not UTF-8"))
    }

    /// After `\u`: four hex digits, and for a high surrogate the `\uDC00`-style low half.
    fn unicode_escape(&mut self) -> Result<char, IndexError> {
        let hi = self.hex4()?;
        let code = if (0xD800..0xDC00).contains(&hi) {
            if self.bytes.get(self.pos..self.pos + 2) != Some(b"\\u") {
                // serde_json rejects a lone surrogate too; keep going with a stand-in.
                return Ok(char::REPLACEMENT_CHARACTER);
            }
            self.pos += 2;
            let lo = self.hex4()?;
            if !(0xDC00..0xE000).contains(&lo) {
                return Ok(char::REPLACEMENT_CHARACTER);
            }
            0x10000 + ((hi - 0xD800) << 10) + (lo - 0xDC00)
        } else {
            hi
        };
        Ok(char::from_u32(code).unwrap_or(char::REPLACEMENT_CHARACTER))
    }

    fn hex4(&mut self) -> Result<u32, IndexError> {
        let digits = self
            .bytes
            .get(self.pos..self.pos + 4)
            .and_then(|d| std::str::from_utf8(d).ok())
            .and_then(|d| u32::from_str_radix(d, 16).ok())
            .ok_or_else(|| self.syntax("bad \\u escape"))?;
        self.pos += 4;
        Ok(digits)
    }

    fn number(&mut self) {
        while let Some(b'-' | b'+' | b'.' | b'e' | b'E' | b'0'..=b'9') = self.peek() {
            self.pos += 1;
        }
    }

    fn literal(&mut self, word: &str) -> Result<(), IndexError> {
        if self.bytes[self.pos..].starts_with(word.as_bytes()) {
            self.pos += word.len();
            Ok(())
        } else {
            Err(self.syntax("expected a value"))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const TEXT: &str = r#"{
  "name": "x",
  "components": {
    "a": { "exec": "e",
           "priority": 3 },
    "b\"q\u00e9": {
      "exec": "f"
    }
  },
  "channels": [
    { "from": "a.out",
      "to": "b.in" },
    {
      "from": "stdin", "to": "a.in" }
  ]
}"#;

    #[test]
    fn records_lines_by_path() {
        let idx = PositionIndex::build(TEXT).unwrap();
        assert_eq!(idx.line(""), Some(1));
        assert_eq!(idx.line("name"), Some(2));
        assert_eq!(idx.line("components.a"), Some(4));
        assert_eq!(idx.line("components.a.exec"), Some(4));
        assert_eq!(idx.line("components.a.priority"), Some(5));
        assert_eq!(idx.line("components.b\"qé.exec"), Some(7));
        assert_eq!(idx.line("channels[0]"), Some(11));
        assert_eq!(idx.line("channels[0].to"), Some(12));
        assert_eq!(idx.line("channels[1]"), Some(13));
        assert_eq!(idx.line("channels[1].from"), Some(14));
    }

    #[test]
    fn keeps_key_order() {
        let idx = PositionIndex::build(TEXT).unwrap();
        assert_eq!(idx.keys("components"), ["a", "b\"qé"]);
        assert_eq!(idx.keys(""), ["name", "components", "channels"]);
        assert!(idx.keys("nowhere").is_empty());
    }

    #[test]
    fn falls_back_to_the_nearest_ancestor() {
        let idx = PositionIndex::build(TEXT).unwrap();
        assert_eq!(idx.line_or_parent("components.a.timeout_us"), 4);
        assert_eq!(idx.line_or_parent("channels[1].max_frame"), 13);
        assert_eq!(idx.line_or_parent("channels[7].from"), 10);
        assert_eq!(idx.line_or_parent("zzz"), 1);
    }

    #[test]
    fn finds_duplicate_keys_with_their_line() {
        let text = "{\n \"components\": {\n  \"a\": {},\n  \"a\": {}\n }\n}";
        let err = PositionIndex::build(text).unwrap_err();
        assert_eq!(
            err,
            IndexError::DuplicateKey {
                key: "a".into(),
                path: "components.a".into(),
                line: 4
            }
        );
    }

    #[test]
    fn duplicate_keys_compare_decoded() {
        let text = r#"{"a": 1, "\u0061": 2}"#;
        assert!(matches!(
            PositionIndex::build(text),
            Err(IndexError::DuplicateKey { .. })
        ));
    }

    #[test]
    fn scalars_arrays_and_surrogates() {
        let text = "[1, -2.5e3, true, false, null, \"\\ud83d\\ude00\", [], {}]";
        let idx = PositionIndex::build(text).unwrap();
        assert_eq!(idx.line("[7]"), Some(1));
    }

    #[test]
    fn bad_text_is_an_error_not_a_panic() {
        for bad in [
            "",
            "{",
            "[1,",
            "{\"a\" 1}",
            "\"abc",
            "tru",
            "{\"a\":1}x",
            "\"\\u12\"",
        ] {
            assert!(
                matches!(PositionIndex::build(bad), Err(IndexError::Syntax { .. })),
                "{bad:?}"
            );
        }
    }

    #[test]
    fn deep_nesting_is_refused() {
        let text = "[".repeat(1000);
        assert!(PositionIndex::build(&text).is_err());
    }
}
