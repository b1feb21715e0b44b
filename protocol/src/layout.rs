//! Monitored fields: where the numbers sit in a frame, and how to read them without allocating.
//!
//! A channel's frames are opaque bytes to the voter; a layout names the numeric fields worth
//! watching. All fields are little-endian (the project's frame convention). In JSON a layout is
//! an array of fields, each `{"name": "v", "type": "f64", "offset": 8}`.

use serde::{Deserialize, Serialize};
use thiserror::Error;

/// The most fields one layout may monitor. Detectors keep a few values per field per replica;
/// this bounds that memory and the cost of a frame.
pub const MAX_FIELDS: usize = 256;

/// The numeric type of a monitored field (little-endian in the frame).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FieldType {
    F64,
    F32,
    I64,
    U64,
    I32,
    U32,
    I16,
    U16,
    I8,
    U8,
}

impl FieldType {
    /// Every type, in the order the documentation lists them.
    pub const ALL: [FieldType; 10] = [
        FieldType::F64,
        FieldType::F32,
        FieldType::I64,
        FieldType::U64,
        FieldType::I32,
        FieldType::U32,
        FieldType::I16,
        FieldType::U16,
        FieldType::I8,
        FieldType::U8,
    ];

    /// The type called `name` in JSON (`"f64"`, `"u16"`, ...).
    pub fn from_name(name: &str) -> Option<FieldType> {
        FieldType::ALL.into_iter().find(|t| t.name() == name)
    }

    /// Bytes the field takes in a frame.
    pub const fn size(self) -> usize {
        match self {
            FieldType::F64 | FieldType::I64 | FieldType::U64 => 8,
            FieldType::F32 | FieldType::I32 | FieldType::U32 => 4,
            FieldType::I16 | FieldType::U16 => 2,
            FieldType::I8 | FieldType::U8 => 1,
        }
    }

    pub const fn is_float(self) -> bool {
        matches!(self, FieldType::F64 | FieldType::F32)
    }

    /// The name used in JSON.
    pub const fn name(self) -> &'static str {
        match self {
            FieldType::F64 => "f64",
            FieldType::F32 => "f32",
            FieldType::I64 => "i64",
            FieldType::U64 => "u64",
            FieldType::I32 => "i32",
            FieldType::U32 => "u32",
            FieldType::I16 => "i16",
            FieldType::U16 => "u16",
            FieldType::I8 => "i8",
            FieldType::U8 => "u8",
        }
    }
}

/// One monitored field.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Field {
    pub name: String,
    #[serde(rename = "type")]
    pub ty: FieldType,
    /// Byte offset of the field's first byte in the frame's payload.
    pub offset: usize,
}

impl Field {
    pub fn new(name: impl Into<String>, ty: FieldType, offset: usize) -> Self {
        Field {
            name: name.into(),
            ty,
            offset,
        }
    }

    /// One past the field's last byte.
    pub fn end(&self) -> usize {
        self.offset + self.ty.size()
    }

    /// The field's raw bytes, widened to a u64 (zero-extended), or `None` if the frame is too
    /// short.
    #[inline]
    pub fn read_bits(&self, frame: &[u8]) -> Option<u64> {
        let bytes = frame.get(self.offset..self.end())?;
        let mut wide = [0u8; 8];
        wide[..bytes.len()].copy_from_slice(bytes);
        Some(u64::from_le_bytes(wide))
    }

    /// The field's value as an f64 (integers above 2^53 in magnitude are rounded), or `None` if
    /// the frame is too short.
    #[inline]
    pub fn read_f64(&self, frame: &[u8]) -> Option<f64> {
        let bits = self.read_bits(frame)?;
        Some(value_of_bits(self.ty, bits))
    }
}

/// Interprets the zero-extended little-endian bits of a field of type `ty`.
#[inline]
pub fn value_of_bits(ty: FieldType, bits: u64) -> f64 {
    match ty {
        FieldType::F64 => f64::from_bits(bits),
        FieldType::F32 => f64::from(f32::from_bits(bits as u32)),
        FieldType::I64 => bits as i64 as f64,
        FieldType::U64 => bits as f64,
        FieldType::I32 => f64::from(bits as u32 as i32),
        FieldType::U32 => f64::from(bits as u32),
        FieldType::I16 => f64::from(bits as u16 as i16),
        FieldType::U16 => f64::from(bits as u16),
        FieldType::I8 => f64::from(bits as u8 as i8),
        FieldType::U8 => f64::from(bits as u8),
    }
}

/// What is wrong with a layout. Every variant names the field.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum LayoutError {
    #[error("the layout has no fields: monitor at least one")]
    Empty,
    #[error("the layout has {count} fields; at most {MAX_FIELDS} may be monitored")]
    TooMany { count: usize },
    #[error("field {index} has an empty name")]
    EmptyName { index: usize },
    #[error("field `{name}` appears twice (fields {first} and {second})")]
    DuplicateName {
        name: String,
        first: usize,
        second: usize,
    },
    #[error("field `{name}` ({ty}, offset {offset}) ends at byte {end}, beyond the channel's maximum frame of {max_frame} bytes")]
    BeyondFrame {
        name: String,
        ty: &'static str,
        offset: usize,
        end: usize,
        max_frame: usize,
    },
    #[error("field `{name}` (bytes {start}..{end}) overlaps field `{other}` (bytes {other_start}..{other_end})")]
    Overlap {
        name: String,
        start: usize,
        end: usize,
        other: String,
        other_start: usize,
        other_end: usize,
    },
}

/// A frame too short for the layout (or an output slice of the wrong length).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Error)]
pub enum DecodeError {
    #[error("frame of {have} bytes is too short: the layout reads up to byte {need}")]
    ShortFrame { have: usize, need: usize },
    #[error("output has room for {have} values, the layout has {want} fields")]
    OutputLength { have: usize, want: usize },
}

/// The monitored fields of a channel: validated (names unique and non-empty, no two fields
/// overlap), in the order given. JSON: an array of [`Field`]s.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(try_from = "Vec<Field>", into = "Vec<Field>")]
pub struct FieldLayout {
    fields: Vec<Field>,
    /// One past the last byte any field reads: the shortest frame that can be decoded.
    min_frame: usize,
}

impl FieldLayout {
    /// Validates `fields` (see [`LayoutError`]); the offsets are checked against
    /// [`within`](Self::within) separately, since the channel's maximum lives elsewhere.
    pub fn new(fields: Vec<Field>) -> Result<Self, LayoutError> {
        if fields.is_empty() {
            return Err(LayoutError::Empty);
        }
        if fields.len() > MAX_FIELDS {
            return Err(LayoutError::TooMany {
                count: fields.len(),
            });
        }
        for (i, f) in fields.iter().enumerate() {
            if f.name.trim().is_empty() {
                return Err(LayoutError::EmptyName { index: i });
            }
            if let Some(j) = fields[..i].iter().position(|g| g.name == f.name) {
                return Err(LayoutError::DuplicateName {
                    name: f.name.clone(),
                    first: j,
                    second: i,
                });
            }
            // A field whose end overflows usize is certainly beyond any frame.
            if f.offset.checked_add(f.ty.size()).is_none() {
                return Err(LayoutError::BeyondFrame {
                    name: f.name.clone(),
                    ty: f.ty.name(),
                    offset: f.offset,
                    end: usize::MAX,
                    max_frame: usize::MAX,
                });
            }
            for g in &fields[..i] {
                if f.offset < g.end() && g.offset < f.end() {
                    return Err(LayoutError::Overlap {
                        name: f.name.clone(),
                        start: f.offset,
                        end: f.end(),
                        other: g.name.clone(),
                        other_start: g.offset,
                        other_end: g.end(),
                    });
                }
            }
        }
        let min_frame = fields.iter().map(Field::end).max().unwrap_or(0);
        Ok(FieldLayout { fields, min_frame })
    }

    /// Checks that every field lies within frames of at most `max_frame` bytes.
    pub fn within(&self, max_frame: usize) -> Result<(), LayoutError> {
        match self.fields.iter().find(|f| f.end() > max_frame) {
            Some(f) => Err(LayoutError::BeyondFrame {
                name: f.name.clone(),
                ty: f.ty.name(),
                offset: f.offset,
                end: f.end(),
                max_frame,
            }),
            None => Ok(()),
        }
    }

    pub fn fields(&self) -> &[Field] {
        &self.fields
    }

    pub fn len(&self) -> usize {
        self.fields.len()
    }

    /// Always false: a layout has at least one field.
    pub fn is_empty(&self) -> bool {
        self.fields.is_empty()
    }

    /// The shortest frame every field can be read from.
    pub fn min_frame(&self) -> usize {
        self.min_frame
    }

    /// Reads every field of `frame` into `out` (one value per field, in layout order) without
    /// allocating. A frame shorter than [`min_frame`](Self::min_frame) is an error and leaves
    /// `out` unspecified.
    pub fn decode(&self, frame: &[u8], out: &mut [f64]) -> Result<(), DecodeError> {
        if out.len() != self.fields.len() {
            return Err(DecodeError::OutputLength {
                have: out.len(),
                want: self.fields.len(),
            });
        }
        self.check_len(frame)?;
        for (f, o) in self.fields.iter().zip(out.iter_mut()) {
            // Cannot fail: the frame is at least min_frame long.
            *o = f.read_f64(frame).unwrap_or(f64::NAN);
        }
        Ok(())
    }

    /// An error if `frame` is too short for this layout.
    #[inline]
    pub fn check_len(&self, frame: &[u8]) -> Result<(), DecodeError> {
        if frame.len() < self.min_frame {
            Err(DecodeError::ShortFrame {
                have: frame.len(),
                need: self.min_frame,
            })
        } else {
            Ok(())
        }
    }
}

impl FieldLayout {
    /// Parses a layout written as JSON: an array of fields, or an object with a `fields` array
    /// (a channel entry of a system description; its other keys are ignored). Errors carry the
    /// line and column.
    pub fn from_json(text: &str) -> Result<FieldLayout, serde_json::Error> {
        #[derive(Deserialize)]
        struct Channel {
            fields: FieldLayout,
        }
        // Parsed from the text (not via a Value) so that errors carry line and column.
        if text.trim_start().starts_with('{') {
            serde_json::from_str::<Channel>(text).map(|c| c.fields)
        } else {
            serde_json::from_str::<FieldLayout>(text)
        }
    }
}

impl TryFrom<Vec<Field>> for FieldLayout {
    type Error = LayoutError;
    fn try_from(fields: Vec<Field>) -> Result<Self, LayoutError> {
        FieldLayout::new(fields)
    }
}

impl From<FieldLayout> for Vec<Field> {
    fn from(layout: FieldLayout) -> Self {
        layout.fields
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    const TYPES: [FieldType; 10] = FieldType::ALL;

    proptest! {
        /// Any type at any offset reads back what was written there, and any shorter frame is
        /// an error, never a panic.
        #[test]
        fn any_type_at_any_offset(
            t in 0usize..10,
            offset in 0usize..100,
            raw in any::<u64>(),
            fill in any::<u8>(),
            cut in 0usize..200,
        ) {
            let ty = TYPES[t];
            let layout = FieldLayout::new(vec![Field::new("v", ty, offset)]).unwrap();
            let mut frame = vec![fill; offset + ty.size() + 3];
            frame[offset..offset + ty.size()].copy_from_slice(&raw.to_le_bytes()[..ty.size()]);
            let expected = match ty {
                FieldType::F64 => f64::from_bits(raw),
                FieldType::F32 => f64::from(f32::from_bits(raw as u32)),
                FieldType::I64 => raw as i64 as f64,
                FieldType::U64 => raw as f64,
                FieldType::I32 => f64::from(raw as i32),
                FieldType::U32 => f64::from(raw as u32),
                FieldType::I16 => f64::from(raw as i16),
                FieldType::U16 => f64::from(raw as u16),
                FieldType::I8 => f64::from(raw as i8),
                FieldType::U8 => f64::from(raw as u8),
            };
            let mut out = [0.0];
            layout.decode(&frame, &mut out).unwrap();
            prop_assert!(out[0] == expected || (out[0].is_nan() && expected.is_nan()));
            let short = cut.min(offset + ty.size() - 1);
            prop_assert_eq!(
                layout.decode(&frame[..short], &mut out),
                Err(DecodeError::ShortFrame { have: short, need: offset + ty.size() })
            );
        }
    }

    fn put(frame: &mut [u8], offset: usize, bytes: &[u8]) {
        frame[offset..offset + bytes.len()].copy_from_slice(bytes);
    }

    #[test]
    fn decodes_every_type_at_its_offset() {
        let mut frame = vec![0xAAu8; 64];
        put(&mut frame, 1, &(-2.5f64).to_le_bytes());
        put(&mut frame, 9, &1.25f32.to_le_bytes());
        put(&mut frame, 13, &(-7_000_000_000i64).to_le_bytes());
        put(&mut frame, 21, &9_000_000_000u64.to_le_bytes());
        put(&mut frame, 29, &(-123_456i32).to_le_bytes());
        put(&mut frame, 33, &4_000_000_000u32.to_le_bytes());
        put(&mut frame, 37, &(-300i16).to_le_bytes());
        put(&mut frame, 39, &65_000u16.to_le_bytes());
        put(&mut frame, 41, &(-5i8).to_le_bytes());
        put(&mut frame, 42, &250u8.to_le_bytes());
        let layout = FieldLayout::new(vec![
            Field::new("a", FieldType::F64, 1),
            Field::new("b", FieldType::F32, 9),
            Field::new("c", FieldType::I64, 13),
            Field::new("d", FieldType::U64, 21),
            Field::new("e", FieldType::I32, 29),
            Field::new("f", FieldType::U32, 33),
            Field::new("g", FieldType::I16, 37),
            Field::new("h", FieldType::U16, 39),
            Field::new("i", FieldType::I8, 41),
            Field::new("j", FieldType::U8, 42),
        ])
        .unwrap();
        assert_eq!(layout.min_frame(), 43);
        let mut out = [0.0; 10];
        layout.decode(&frame, &mut out).unwrap();
        assert_eq!(
            out,
            [
                -2.5,
                1.25,
                -7_000_000_000.0,
                9_000_000_000.0,
                -123_456.0,
                4_000_000_000.0,
                -300.0,
                65_000.0,
                -5.0,
                250.0
            ]
        );
    }

    #[test]
    fn short_frame_is_an_error_not_a_panic() {
        let layout = FieldLayout::new(vec![Field::new("v", FieldType::F64, 8)]).unwrap();
        let mut out = [0.0];
        for len in 0..16 {
            assert_eq!(
                layout.decode(&vec![0; len], &mut out),
                Err(DecodeError::ShortFrame {
                    have: len,
                    need: 16
                })
            );
        }
        assert!(layout.decode(&[0; 16], &mut out).is_ok());
        assert_eq!(
            layout.decode(&[0; 16], &mut [0.0; 2]),
            Err(DecodeError::OutputLength { have: 2, want: 1 })
        );
    }

    #[test]
    fn json_shape_is_pleasant_and_round_trips() {
        let json = r#"[{"name":"x","type":"f64","offset":0},{"name":"n","type":"u16","offset":8}]"#;
        let layout: FieldLayout = serde_json::from_str(json).unwrap();
        assert_eq!(layout.fields()[1], Field::new("n", FieldType::U16, 8));
        assert_eq!(serde_json::to_string(&layout).unwrap(), json);
    }

    #[test]
    fn types_by_name_and_layouts_from_either_json_shape() {
        for t in FieldType::ALL {
            assert_eq!(FieldType::from_name(t.name()), Some(t));
        }
        assert_eq!(FieldType::from_name("f16"), None);
        let bare = r#"[{"name":"x","type":"f64","offset":0}]"#;
        let channel =
            r#" {"from": "a.out", "to": "b.in", "fields": [{"name":"x","type":"f64","offset":0}]}"#;
        assert_eq!(
            FieldLayout::from_json(bare).unwrap(),
            FieldLayout::from_json(channel).unwrap()
        );
        let err = FieldLayout::from_json("[\n{\"name\":\"x\",\"type\":\"f16\",\"offset\":0}]")
            .unwrap_err();
        assert_eq!(err.line(), 2, "{err}");
    }

    #[test]
    fn overlap_names_both_fields() {
        let json = r#"[{"name":"x","type":"f64","offset":0},{"name":"y","type":"f32","offset":4}]"#;
        let err = serde_json::from_str::<FieldLayout>(json)
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("field `y` (bytes 4..8) overlaps field `x` (bytes 0..8)"),
            "{err}"
        );
    }

    #[test]
    fn bad_layouts_are_named_errors() {
        assert_eq!(FieldLayout::new(vec![]), Err(LayoutError::Empty));
        let dup = FieldLayout::new(vec![
            Field::new("x", FieldType::U8, 0),
            Field::new("x", FieldType::U8, 1),
        ]);
        assert!(matches!(dup, Err(LayoutError::DuplicateName { ref name, .. }) if name == "x"));
        let blank = FieldLayout::new(vec![Field::new(" ", FieldType::U8, 0)]);
        assert_eq!(blank, Err(LayoutError::EmptyName { index: 0 }));
        let huge = FieldLayout::new(vec![Field::new("x", FieldType::U64, usize::MAX - 3)]);
        assert!(matches!(huge, Err(LayoutError::BeyondFrame { .. })));
        let unknown = r#"[{"name":"x","type":"f16","offset":0}]"#;
        let err = serde_json::from_str::<FieldLayout>(unknown)
            .unwrap_err()
            .to_string();
        assert!(err.contains("unknown variant `f16`"), "{err}");
        let extra = r#"[{"name":"x","type":"f64","offset":0,"scale":2}]"#;
        assert!(serde_json::from_str::<FieldLayout>(extra).is_err());
    }

    #[test]
    fn within_checks_the_channel_maximum() {
        let layout = FieldLayout::new(vec![
            Field::new("a", FieldType::U32, 0),
            Field::new("far", FieldType::F64, 60),
        ])
        .unwrap();
        assert!(layout.within(68).is_ok());
        let err = layout.within(64).unwrap_err().to_string();
        assert_eq!(
            err,
            "field `far` (f64, offset 60) ends at byte 68, beyond the channel's maximum frame of 64 bytes"
        );
    }
}
