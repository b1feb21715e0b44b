//! The encoders, renderers and the line check of `s3res-frames` (feeding and watching frames).
//!
//! - [`Encoding`] turns one line of input into one frame's payload: the line's bytes (text), one
//!   or more numbers of a type, or a JSON value (as its text, or laid out by a
//!   [`FieldLayout`]).
//! - [`Format`] turns one frame's payload into one line: hex, text (escaped so that it stays one
//!   line), or the fields of a layout (`name=value ...`).
//! - [`LineCheck`] compares rendered frames with the lines of an expected file.
//! - [`parse_layout`] reads a layout given on the command line: the JSON the anomaly detectors
//!   use (inline, or a file), or the shorthand `name:type[@offset],...`.
//!
//! Everything here returns errors for bad input, never panics: a bad line is the user's typo.

use std::fmt::Write as _;
use std::path::Path;

use anyhow::{anyhow, bail, Context, Result};
use s3res_protocol::layout::{Field, FieldLayout, FieldType};

/// The type names `--as` accepts for numbers, as listed in `--help`.
pub const NUMBER_TYPES: &str = "u8 u16 u32 u64 i8 i16 i32 i64 f32 f64";

/// Reads a layout given on the command line:
///
/// - `[...]` or `{...}`: JSON, the array of fields the system description's `fields` uses
///   (`[{"name": "x", "type": "f64", "offset": 8}]`), or an object with such a `fields` array;
/// - a path (it contains `/` or ends in `.json`): a file holding that JSON;
/// - otherwise the shorthand `name:type[@offset],...`, for example `count:u64,mean:f64`: each
///   field follows the previous one unless `@offset` places it.
///
/// The layout is validated as a channel's `fields` are (unique names, no overlap).
pub fn parse_layout(spec: &str) -> Result<FieldLayout> {
    let trimmed = spec.trim();
    if trimmed.starts_with('[') || trimmed.starts_with('{') {
        return FieldLayout::from_json(trimmed).context("layout (JSON)");
    }
    if trimmed.contains('/') || trimmed.ends_with(".json") {
        let path = Path::new(trimmed);
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("cannot read layout file {}", path.display()))?;
        return FieldLayout::from_json(&text)
            .with_context(|| format!("layout file {}", path.display()));
    }
    parse_shorthand(trimmed)
}

/// `name:type[@offset],...` (see [`parse_layout`]).
fn parse_shorthand(spec: &str) -> Result<FieldLayout> {
    let mut fields = Vec::new();
    let mut next = 0usize;
    for (i, part) in spec.split(',').enumerate() {
        let part = part.trim();
        let bad = |why: &str| {
            anyhow!(
                "layout field {} `{part}`: {why} (write `name:type` or `name:type@offset`, \
                 types {NUMBER_TYPES}, e.g. `count:u64,mean:f64`; or give the layout as JSON \
                 or a .json file)",
                i + 1
            )
        };
        let Some((name, rest)) = part.split_once(':') else {
            return Err(bad("no `:type`"));
        };
        let (ty, offset) = match rest.split_once('@') {
            Some((ty, off)) => {
                let off = off
                    .trim()
                    .parse::<usize>()
                    .map_err(|_| bad("the offset after `@` is not a byte count"))?;
                (ty.trim(), off)
            }
            None => (rest.trim(), next),
        };
        let ty = FieldType::from_name(ty).ok_or_else(|| bad("unknown type"))?;
        let name = name.trim();
        if name.is_empty() {
            return Err(bad("the name is empty"));
        }
        next = offset
            .checked_add(ty.size())
            .ok_or_else(|| bad("the offset is too large"))?;
        fields.push(Field::new(name, ty, offset));
    }
    FieldLayout::new(fields).context("layout")
}

/// A number on its way into a frame: integers exactly, floats as f64.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Num {
    Int(i128),
    Float(f64),
}

/// The smallest and largest value of an integer type.
fn int_range(ty: FieldType) -> (i128, i128) {
    match ty {
        FieldType::U8 => (0, u8::MAX.into()),
        FieldType::U16 => (0, u16::MAX.into()),
        FieldType::U32 => (0, u32::MAX.into()),
        FieldType::U64 => (0, u64::MAX.into()),
        FieldType::I8 => (i8::MIN.into(), i8::MAX.into()),
        FieldType::I16 => (i16::MIN.into(), i16::MAX.into()),
        FieldType::I32 => (i32::MIN.into(), i32::MAX.into()),
        FieldType::I64 => (i64::MIN.into(), i64::MAX.into()),
        FieldType::F32 | FieldType::F64 => (0, 0),
    }
}

/// Appends `v` as `ty`, little-endian. An integer outside the type's range, or a float for an
/// integer type, is an error that says what would fit.
fn put(ty: FieldType, v: Num, out: &mut Vec<u8>) -> Result<(), String> {
    match (ty, v) {
        (FieldType::F64, Num::Float(x)) => out.extend_from_slice(&x.to_le_bytes()),
        (FieldType::F64, Num::Int(i)) => out.extend_from_slice(&(i as f64).to_le_bytes()),
        (FieldType::F32, Num::Float(x)) => out.extend_from_slice(&(x as f32).to_le_bytes()),
        (FieldType::F32, Num::Int(i)) => out.extend_from_slice(&(i as f32).to_le_bytes()),
        (_, Num::Float(_)) => return Err(format!("not an integer ({} expected)", ty.name())),
        (_, Num::Int(i)) => {
            let (lo, hi) = int_range(ty);
            if i < lo || i > hi {
                return Err(format!("out of range for {} ({lo} to {hi})", ty.name()));
            }
            // Two's complement little-endian, cut to the type's width: exact within the range.
            out.extend_from_slice(&i.to_le_bytes()[..ty.size()]);
        }
    }
    Ok(())
}

/// One number written as text, for a field of type `ty`.
fn parse_number(ty: FieldType, token: &str) -> Result<Num, String> {
    if ty.is_float() {
        return token
            .parse::<f64>()
            .map(Num::Float)
            .map_err(|_| format!("not a number ({} expected)", ty.name()));
    }
    token
        .parse::<i128>()
        .map(Num::Int)
        .map_err(|_| format!("not an integer ({} expected)", ty.name()))
}

/// How `send` turns a line into a frame.
#[derive(Debug, Clone)]
pub enum Encoding {
    /// The line's bytes, as they are (without the line end).
    Text,
    /// Whitespace-separated numbers, each as `FieldType`, little-endian, one after the other.
    Numbers(FieldType),
    /// One JSON value per line, sent as its text (as written, trimmed) once it parses.
    Json,
    /// One JSON value per line, an object with a value for every field (or an array of them in
    /// layout order), laid out as the layout says; the frame is `size` bytes, zero-filled
    /// between fields.
    JsonLayout { layout: FieldLayout, size: usize },
}

impl Encoding {
    /// Whether a blank line is skipped (it holds no value) rather than sent as an empty frame.
    pub fn skips_blank_lines(&self) -> bool {
        !matches!(self, Encoding::Text)
    }

    /// Encodes one line (without its line end) into `out`, replacing its contents. `Ok(false)`:
    /// nothing to send (a blank line where a value is expected). The error says what is wrong
    /// with the line; the caller adds where it is.
    pub fn encode(&self, line: &[u8], out: &mut Vec<u8>) -> Result<bool, String> {
        out.clear();
        if let Encoding::Text = self {
            out.extend_from_slice(line);
            return Ok(true);
        }
        let text = std::str::from_utf8(line).map_err(|e| format!("not UTF-8 text ({e})"))?;
        let text = text.trim();
        if text.is_empty() {
            return Ok(false);
        }
        match self {
            Encoding::Text => unreachable!("handled above"),
            Encoding::Numbers(ty) => {
                for (k, token) in text
                    .split(|c: char| c.is_whitespace() || c == ',')
                    .filter(|t| !t.is_empty())
                    .enumerate()
                {
                    let v = parse_number(*ty, token).map_err(|e| {
                        if k == 0 {
                            format!("`{token}` is {e}")
                        } else {
                            format!("`{token}` (number {}) is {e}", k + 1)
                        }
                    })?;
                    put(*ty, v, out).map_err(|e| format!("`{token}` is {e}"))?;
                }
            }
            Encoding::Json => {
                serde_json::from_str::<serde_json::Value>(text)
                    .map_err(|e| format!("not one JSON value ({e})"))?;
                out.extend_from_slice(text.as_bytes());
            }
            Encoding::JsonLayout { layout, size } => {
                let value = serde_json::from_str::<serde_json::Value>(text)
                    .map_err(|e| format!("not one JSON value ({e})"))?;
                encode_json_layout(layout, *size, &value, out)?;
            }
        }
        Ok(true)
    }
}

/// Lays `value` (an object with every field, or an array in layout order) out by `layout` into
/// a frame of `size` bytes.
fn encode_json_layout(
    layout: &FieldLayout,
    size: usize,
    value: &serde_json::Value,
    out: &mut Vec<u8>,
) -> Result<(), String> {
    let fields = layout.fields();
    let names = || {
        fields
            .iter()
            .map(|f| f.name.as_str())
            .collect::<Vec<_>>()
            .join(", ")
    };
    let values: Vec<&serde_json::Value> = match value {
        serde_json::Value::Object(map) => {
            if let Some(k) = map.keys().find(|k| !fields.iter().any(|f| &f.name == *k)) {
                return Err(format!(
                    "`{k}` is not a field of the layout (fields: {})",
                    names()
                ));
            }
            fields
                .iter()
                .map(|f| {
                    map.get(&f.name)
                        .ok_or_else(|| format!("field `{}` is missing", f.name))
                })
                .collect::<Result<_, _>>()?
        }
        serde_json::Value::Array(items) if items.len() == fields.len() => items.iter().collect(),
        serde_json::Value::Array(items) => {
            return Err(format!(
                "an array of {} values, the layout has {} fields ({})",
                items.len(),
                fields.len(),
                names()
            ))
        }
        other => {
            return Err(format!(
                "{other} is neither an object nor an array of the layout's fields ({})",
                names()
            ))
        }
    };
    out.clear();
    out.resize(size, 0);
    let mut one = Vec::with_capacity(8);
    for (f, v) in fields.iter().zip(values) {
        let num = match v {
            serde_json::Value::Number(n) => {
                if let Some(i) = n.as_i64() {
                    Num::Int(i.into())
                } else if let Some(u) = n.as_u64() {
                    Num::Int(u.into())
                } else if let Some(x) = n.as_f64() {
                    Num::Float(x)
                } else {
                    return Err(format!("field `{}`: {n} is not a number", f.name));
                }
            }
            other => return Err(format!("field `{}`: {other} is not a number", f.name)),
        };
        one.clear();
        put(f.ty, num, &mut one).map_err(|e| format!("field `{}`: {v} is {e}", f.name))?;
        let Some(slot) = out.get_mut(f.offset..f.offset + one.len()) else {
            return Err(format!(
                "field `{}` ends at byte {}, beyond the frame size {size}",
                f.name,
                f.end()
            ));
        };
        slot.copy_from_slice(&one);
    }
    Ok(())
}

/// Parses `--as`: `text`, `json`, or a number type.
pub fn parse_encoding_name(name: &str) -> Result<Option<FieldType>> {
    match name {
        "text" | "json" => Ok(None),
        _ => FieldType::from_name(name).map(Some).ok_or_else(|| {
            anyhow!(
                "--as {name}: unknown encoding; use text, json, or a number type: {NUMBER_TYPES}"
            )
        }),
    }
}

/// How `show` and `check` turn a frame into a line.
#[derive(Debug, Clone)]
pub enum Format {
    /// Every payload byte as two lowercase hex digits.
    Hex,
    /// The payload as UTF-8 text; bytes that would break the line or are not UTF-8 are escaped
    /// (see [`escape_text`]).
    Text,
    /// `name=value` for every field of the layout, separated by spaces.
    Layout(FieldLayout),
}

impl Format {
    /// `hex`, `text`, or `layout:SPEC` (see [`parse_layout`]).
    pub fn parse(s: &str) -> Result<Format> {
        match s {
            "hex" => Ok(Format::Hex),
            "text" => Ok(Format::Text),
            _ => match s.strip_prefix("layout:") {
                Some(spec) => Ok(Format::Layout(parse_layout(spec)?)),
                None => bail!(
                    "--format {s}: unknown format; use hex, text, or layout:SPEC \
                     (e.g. layout:count:u64,mean:f64)"
                ),
            },
        }
    }

    /// Renders `frame` into `out` (cleared first). A frame too short for a layout is rendered
    /// as a note saying so, and `false` is returned.
    pub fn render(&self, frame: &[u8], out: &mut String) -> bool {
        out.clear();
        match self {
            Format::Hex => {
                for b in frame {
                    let _ = write!(out, "{b:02x}");
                }
                true
            }
            Format::Text => {
                escape_text(frame, out);
                true
            }
            Format::Layout(layout) => {
                if let Err(e) = layout.check_len(frame) {
                    let _ = write!(out, "({e})");
                    return false;
                }
                for (i, f) in layout.fields().iter().enumerate() {
                    if i > 0 {
                        out.push(' ');
                    }
                    let _ = write!(out, "{}=", f.name);
                    // check_len above: every field is within the frame.
                    let bits = f.read_bits(frame).unwrap_or(0);
                    write_value(f.ty, bits, out);
                }
                true
            }
        }
    }
}

/// A field's value: integers exactly, floats in Rust's shortest round-trip form (`1.0`, `2.5`,
/// `1e-7`, `NaN`, `inf`).
fn write_value(ty: FieldType, bits: u64, out: &mut String) {
    let _ = match ty {
        FieldType::F64 => write!(out, "{:?}", f64::from_bits(bits)),
        FieldType::F32 => write!(out, "{:?}", f32::from_bits(bits as u32)),
        FieldType::U64 | FieldType::U32 | FieldType::U16 | FieldType::U8 => write!(out, "{bits}"),
        FieldType::I64 => write!(out, "{}", bits as i64),
        FieldType::I32 => write!(out, "{}", bits as u32 as i32),
        FieldType::I16 => write!(out, "{}", bits as u16 as i16),
        FieldType::I8 => write!(out, "{}", bits as u8 as i8),
    };
}

/// Text as one line: valid UTF-8 as it is, except `\n`, `\r`, the other control characters
/// (tab aside) and DEL, which become `\n`, `\r` and `\xNN`; bytes that are not UTF-8 become
/// `\xNN`. A backslash stays as it is, so a line sent as text shows as itself.
pub fn escape_text(bytes: &[u8], out: &mut String) {
    for chunk in bytes.utf8_chunks() {
        for c in chunk.valid().chars() {
            match c {
                '\n' => out.push_str("\\n"),
                '\r' => out.push_str("\\r"),
                '\t' => out.push('\t'),
                c if c.is_ascii_control() => {
                    let _ = write!(out, "\\x{:02x}", c as u32);
                }
                c => out.push(c),
            }
        }
        for b in chunk.invalid() {
            let _ = write!(out, "\\x{b:02x}");
        }
    }
}

/// Where two streams of lines first part.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Difference {
    /// Frame index (from 0; the expected file's line is `index + 1`).
    pub index: usize,
    /// The expected line, `None` past the end of the file (an extra frame).
    pub expected: Option<String>,
    /// The frame as rendered, `None` past the end of the stream (a missing frame).
    pub got: Option<String>,
}

/// What [`LineCheck::finish`] found.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CheckReport {
    pub frames: usize,
    pub expected: usize,
    /// Frames whose line differs from the expected line at the same index.
    pub differing: usize,
    /// Expected lines past the last frame.
    pub missing: usize,
    /// Frames past the last expected line.
    pub extra: usize,
    pub first: Option<Difference>,
}

impl CheckReport {
    pub fn ok(&self) -> bool {
        self.first.is_none()
    }
}

impl std::fmt::Display for CheckReport {
    /// Several lines: the first difference, then the counts.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let Some(d) = &self.first else {
            return write!(f, "check: {} frames, all as expected: OK", self.frames);
        };
        let line = d.index + 1;
        match (&d.expected, &d.got) {
            (Some(e), Some(g)) => writeln!(
                f,
                "check: first difference at frame {} (line {line}):\n  expected: {e}\n  got:      {g}",
                d.index
            )?,
            (Some(e), None) => writeln!(
                f,
                "check: first difference at frame {} (line {line}): the stream ended\n  expected: {e}\n  got:      nothing",
                d.index
            )?,
            (None, Some(g)) => writeln!(
                f,
                "check: first difference at frame {}: an extra frame, the expected file has {} lines\n  expected: nothing\n  got:      {g}",
                d.index, self.expected
            )?,
            (None, None) => {}
        }
        write!(
            f,
            "check: {} frames, {} expected: {} differing, {} missing, {} extra: FAILED",
            self.frames, self.expected, self.differing, self.missing, self.extra
        )
    }
}

/// Compares rendered frames, one at a time, with expected lines.
#[derive(Debug)]
pub struct LineCheck {
    expected: Vec<String>,
    frames: usize,
    differing: usize,
    first: Option<Difference>,
}

impl LineCheck {
    /// The expected lines: `text` split at `\n` (a last line end adds no empty line).
    pub fn new(text: &str) -> Self {
        let expected = if text.is_empty() {
            Vec::new()
        } else {
            text.strip_suffix('\n')
                .unwrap_or(text)
                .split('\n')
                .map(str::to_owned)
                .collect()
        };
        LineCheck {
            expected,
            frames: 0,
            differing: 0,
            first: None,
        }
    }

    /// The next frame, rendered.
    pub fn frame(&mut self, got: &str) {
        let index = self.frames;
        self.frames += 1;
        let expected = self.expected.get(index);
        if expected.is_some_and(|e| e == got) {
            return;
        }
        if expected.is_some() {
            self.differing += 1;
        }
        if self.first.is_none() {
            self.first = Some(Difference {
                index,
                expected: expected.cloned(),
                got: Some(got.to_owned()),
            });
        }
    }

    pub fn finish(mut self) -> CheckReport {
        let missing = self.expected.len().saturating_sub(self.frames);
        let extra = self.frames.saturating_sub(self.expected.len());
        if self.first.is_none() && missing > 0 {
            self.first = Some(Difference {
                index: self.frames,
                expected: self.expected.get(self.frames).cloned(),
                got: None,
            });
        }
        CheckReport {
            frames: self.frames,
            expected: self.expected.len(),
            differing: self.differing,
            missing,
            extra,
            first: self.first,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn enc(e: &Encoding, line: &str) -> Result<Vec<u8>, String> {
        let mut out = vec![0xEE; 3];
        match e.encode(line.as_bytes(), &mut out)? {
            true => Ok(out),
            false => Ok(b"<skipped>".to_vec()),
        }
    }

    fn mean_layout() -> FieldLayout {
        parse_layout("count:u64,mean:f64").unwrap()
    }

    #[test]
    fn shorthand_layouts_place_fields_one_after_another_or_at_offsets() {
        let l = mean_layout();
        assert_eq!(
            l.fields(),
            [
                Field::new("count", FieldType::U64, 0),
                Field::new("mean", FieldType::F64, 8)
            ]
        );
        let l = parse_layout(" seq:u32@0, x:f64@8 ,flag:u8").unwrap();
        assert_eq!(l.fields()[2], Field::new("flag", FieldType::U8, 16));
        let json = parse_layout(
            r#"[{"name":"count","type":"u64","offset":0},{"name":"mean","type":"f64","offset":8}]"#,
        )
        .unwrap();
        assert_eq!(json, mean_layout());
        let channel =
            parse_layout(r#"{"from":"a.b","fields":[{"name":"v","type":"i16","offset":2}]}"#)
                .unwrap();
        assert_eq!(channel.fields()[0], Field::new("v", FieldType::I16, 2));
    }

    #[test]
    fn bad_layouts_say_what_is_wrong() {
        let err = |s: &str| format!("{:#}", parse_layout(s).unwrap_err());
        assert!(err("count:u65").contains("field 1 `count:u65`: unknown type"));
        assert!(err("a:u8,b").contains("field 2 `b`: no `:type`"));
        assert!(err("a:u8@x").contains("not a byte count"));
        assert!(err(":u8").contains("the name is empty"));
        assert!(
            err("a:u32,b:u8@2").contains("overlaps field `a`"),
            "{}",
            err("a:u32,b:u8@2")
        );
        assert!(err("a:u8,a:u8").contains("appears twice"));
        assert!(err("nope/layout.json").contains("cannot read layout file nope/layout.json"));
        assert!(err("[{\"name\":1}]").contains("layout (JSON)"));
    }

    #[test]
    fn layout_files_are_read() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("l.json");
        std::fs::write(&p, r#"[{"name":"x","type":"f32","offset":4}]"#).unwrap();
        let l = parse_layout(p.to_str().unwrap()).unwrap();
        assert_eq!(l.fields()[0], Field::new("x", FieldType::F32, 4));
    }

    #[test]
    fn text_lines_are_sent_as_they_are() {
        assert_eq!(enc(&Encoding::Text, "hello world").unwrap(), b"hello world");
        assert_eq!(enc(&Encoding::Text, "").unwrap(), b"");
        let mut out = Vec::new();
        assert!(Encoding::Text.encode(&[0xff, b'a'], &mut out).unwrap());
        assert_eq!(out, [0xff, b'a']);
    }

    #[test]
    fn numbers_are_little_endian_and_range_checked() {
        let u32s = Encoding::Numbers(FieldType::U32);
        assert_eq!(enc(&u32s, "258").unwrap(), [2, 1, 0, 0]);
        assert_eq!(
            enc(&u32s, " 1 2,3 ").unwrap(),
            [1, 0, 0, 0, 2, 0, 0, 0, 3, 0, 0, 0]
        );
        assert_eq!(enc(&u32s, "   ").unwrap(), b"<skipped>");
        assert_eq!(
            enc(&u32s, "4294967296").unwrap_err(),
            "`4294967296` is out of range for u32 (0 to 4294967295)"
        );
        assert_eq!(
            enc(&u32s, "-1").unwrap_err(),
            "`-1` is out of range for u32 (0 to 4294967295)"
        );
        assert_eq!(
            enc(&u32s, "1.5").unwrap_err(),
            "`1.5` is not an integer (u32 expected)"
        );
        assert_eq!(
            enc(&u32s, "1 x").unwrap_err(),
            "`x` (number 2) is not an integer (u32 expected)"
        );
        let i64s = Encoding::Numbers(FieldType::I64);
        assert_eq!(enc(&i64s, "-2").unwrap(), (-2i64).to_le_bytes());
        assert_eq!(
            enc(&i64s, "-9223372036854775808").unwrap(),
            i64::MIN.to_le_bytes()
        );
        let u64s = Encoding::Numbers(FieldType::U64);
        assert_eq!(
            enc(&u64s, "18446744073709551615").unwrap(),
            u64::MAX.to_le_bytes()
        );
        let i8s = Encoding::Numbers(FieldType::I8);
        assert_eq!(enc(&i8s, "-128").unwrap(), [0x80]);
        assert!(enc(&i8s, "128").is_err());
        let f64s = Encoding::Numbers(FieldType::F64);
        assert_eq!(enc(&f64s, "2.5").unwrap(), 2.5f64.to_le_bytes());
        assert_eq!(enc(&f64s, "1e3").unwrap(), 1000.0f64.to_le_bytes());
        assert_eq!(
            enc(&f64s, "abc").unwrap_err(),
            "`abc` is not a number (f64 expected)"
        );
        let f32s = Encoding::Numbers(FieldType::F32);
        assert_eq!(enc(&f32s, "0.1").unwrap(), 0.1f32.to_le_bytes());
        let mut out = Vec::new();
        assert!(f64s
            .encode(&[0xff], &mut out)
            .unwrap_err()
            .contains("not UTF-8"));
    }

    #[test]
    fn json_is_checked_and_sent_as_written() {
        assert_eq!(
            enc(&Encoding::Json, r#" {"a": [1, 2]} "#).unwrap(),
            br#"{"a": [1, 2]}"#
        );
        assert!(enc(&Encoding::Json, "{oops")
            .unwrap_err()
            .starts_with("not one JSON value"));
        assert_eq!(enc(&Encoding::Json, "").unwrap(), b"<skipped>");
    }

    #[test]
    fn json_with_a_layout_lays_the_fields_out() {
        let e = Encoding::JsonLayout {
            layout: parse_layout("seq:u32@0,x:f64@8").unwrap(),
            size: 20,
        };
        let mut want = vec![0u8; 20];
        want[..4].copy_from_slice(&7u32.to_le_bytes());
        want[8..16].copy_from_slice(&(-1.5f64).to_le_bytes());
        assert_eq!(enc(&e, r#"{"x": -1.5, "seq": 7}"#).unwrap(), want);
        assert_eq!(enc(&e, "[7, -1.5]").unwrap(), want);
        // An integer is a fine float; a float is not an integer.
        want[8..16].copy_from_slice(&3.0f64.to_le_bytes());
        assert_eq!(enc(&e, r#"{"seq": 7, "x": 3}"#).unwrap(), want);
        let err = |s: &str| enc(&e, s).unwrap_err();
        assert_eq!(
            err(r#"{"seq": 1.5, "x": 0}"#),
            "field `seq`: 1.5 is not an integer (u32 expected)"
        );
        assert_eq!(
            err(r#"{"seq": -1, "x": 0}"#),
            "field `seq`: -1 is out of range for u32 (0 to 4294967295)"
        );
        assert_eq!(err(r#"{"x": 0}"#), "field `seq` is missing");
        assert_eq!(
            err(r#"{"seq": 1, "x": 0, "y": 2}"#),
            "`y` is not a field of the layout (fields: seq, x)"
        );
        assert_eq!(
            err(r#"{"seq": "1", "x": 0}"#),
            r#"field `seq`: "1" is not a number"#
        );
        assert_eq!(
            err("[1]"),
            "an array of 1 values, the layout has 2 fields (seq, x)"
        );
        assert_eq!(
            err("3"),
            "3 is neither an object nor an array of the layout's fields (seq, x)"
        );
        let short = Encoding::JsonLayout {
            layout: parse_layout("seq:u32@0,x:f64@8").unwrap(),
            size: 10,
        };
        assert_eq!(
            enc(&short, "[1, 2]").unwrap_err(),
            "field `x` ends at byte 16, beyond the frame size 10"
        );
    }

    #[test]
    fn encoding_names() {
        assert_eq!(parse_encoding_name("text").unwrap(), None);
        assert_eq!(parse_encoding_name("i16").unwrap(), Some(FieldType::I16));
        let err = parse_encoding_name("int").unwrap_err().to_string();
        assert!(
            err.contains("unknown encoding") && err.contains("f64"),
            "{err}"
        );
    }

    fn show(f: &Format, frame: &[u8]) -> String {
        let mut s = String::from("stale");
        f.render(frame, &mut s);
        s
    }

    #[test]
    fn hex_and_text_render_one_line() {
        assert_eq!(show(&Format::Hex, &[0, 0xab, 0x10]), "00ab10");
        assert_eq!(show(&Format::Hex, &[]), "");
        assert_eq!(show(&Format::Text, b"caf\xc3\xa9 a\\b"), "café a\\b");
        assert_eq!(
            show(&Format::Text, b"a\nb\r\tc\x00\x7f\xff"),
            "a\\nb\\r\tc\\x00\\x7f\\xff"
        );
    }

    #[test]
    fn layouts_render_exact_values() {
        let f = Format::parse("layout:count:u64,mean:f64").unwrap();
        let mut frame = 3u64.to_le_bytes().to_vec();
        frame.extend(2.0f64.to_le_bytes());
        assert_eq!(show(&f, &frame), "count=3 mean=2.0");
        frame[..8].copy_from_slice(&u64::MAX.to_le_bytes());
        frame[8..].copy_from_slice(&1e-7f64.to_le_bytes());
        frame.push(0xAA); // bytes past the layout are not shown
        assert_eq!(show(&f, &frame), "count=18446744073709551615 mean=1e-7");
        let mut s = String::new();
        assert!(!f.render(&frame[..9], &mut s));
        assert_eq!(
            s,
            "(frame of 9 bytes is too short: the layout reads up to byte 16)"
        );
        let every = Format::parse("layout:a:i8,b:i16,c:i32,d:i64,e:u8,f:u16,g:u32,h:f32").unwrap();
        let mut frame = vec![0xff; 1 + 2 + 4 + 8 + 1 + 2 + 4];
        frame.extend(0.1f32.to_le_bytes());
        assert_eq!(
            show(&every, &frame),
            "a=-1 b=-1 c=-1 d=-1 e=255 f=65535 g=4294967295 h=0.1"
        );
    }

    #[test]
    fn formats_parse_or_say_what_is_known() {
        assert!(matches!(Format::parse("hex"), Ok(Format::Hex)));
        let err = Format::parse("bin").unwrap_err().to_string();
        assert!(err.contains("hex, text, or layout:SPEC"), "{err}");
        assert!(Format::parse("layout:x").is_err());
    }

    #[test]
    fn what_send_encodes_show_renders_back() {
        let layout = parse_layout("seq:u32,x:f64,n:i16").unwrap();
        let e = Encoding::JsonLayout {
            layout: layout.clone(),
            size: layout.min_frame(),
        };
        let f = Format::Layout(layout);
        for line in [
            r#"{"seq": 1, "x": 0.5, "n": -3}"#,
            "[4294967295, -1e300, 32767]",
        ] {
            let frame = enc(&e, line).unwrap();
            let shown = show(&f, &frame);
            let again = enc(
                &e,
                &format!(
                    "[{}]",
                    shown
                        .split(' ')
                        .map(|kv| kv.split_once('=').unwrap().1)
                        .collect::<Vec<_>>()
                        .join(",")
                ),
            )
            .unwrap();
            assert_eq!(again, frame, "{shown}");
        }
        let text = "plain text, with a \\ backslash";
        assert_eq!(
            show(&Format::Text, &enc(&Encoding::Text, text).unwrap()),
            text
        );
    }

    fn check(expected: &str, got: &[&str]) -> CheckReport {
        let mut c = LineCheck::new(expected);
        for g in got {
            c.frame(g);
        }
        c.finish()
    }

    #[test]
    fn exact_match_passes() {
        let r = check("a\nb\n", &["a", "b"]);
        assert!(r.ok());
        assert_eq!(r.to_string(), "check: 2 frames, all as expected: OK");
        assert!(check("a\nb", &["a", "b"]).ok(), "no final line end");
        assert!(check("", &[]).ok());
        assert!(
            !check("\n", &[]).ok(),
            "one empty line expects one empty frame"
        );
        assert!(check("\n", &[""]).ok());
    }

    #[test]
    fn first_difference_and_counts() {
        let r = check("a\nb\nc\nd\n", &["a", "B", "C"]);
        assert!(!r.ok());
        assert_eq!(
            (r.frames, r.expected, r.differing, r.missing, r.extra),
            (3, 4, 2, 1, 0)
        );
        assert_eq!(
            r.to_string(),
            "check: first difference at frame 1 (line 2):\n  expected: b\n  got:      B\n\
             check: 3 frames, 4 expected: 2 differing, 1 missing, 0 extra: FAILED"
        );
        let r = check("a\nb\n", &["a"]);
        assert_eq!(
            r.first,
            Some(Difference {
                index: 1,
                expected: Some("b".into()),
                got: None
            })
        );
        assert!(r.to_string().contains("the stream ended"), "{r}");
        let r = check("a\n", &["a", "x", "y"]);
        assert_eq!((r.differing, r.missing, r.extra), (0, 0, 2));
        assert_eq!(
            r.first,
            Some(Difference {
                index: 1,
                expected: None,
                got: Some("x".into())
            })
        );
        assert!(
            r.to_string()
                .contains("an extra frame, the expected file has 1 lines"),
            "{r}"
        );
    }

    #[test]
    fn due_times_are_exact() {
        let start = std::time::Instant::now();
        let period = std::time::Duration::from_nanos(333_333_333);
        assert_eq!(
            crate::due_at(start, period, 3).unwrap() - start,
            std::time::Duration::from_nanos(999_999_999)
        );
        assert!(crate::due_at(start, std::time::Duration::MAX, u64::MAX).is_none());
    }
}
