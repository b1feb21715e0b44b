//! Frame capture files: the s3res framing (4-byte little-endian length, then the payload),
//! frame after frame, as the integrator can record from a channel. Training reads them.

use replica_rt::frame::{encode_into, FrameDecoder, FrameError};
use std::io::Read;
use std::path::{Path, PathBuf};
use thiserror::Error;

#[derive(Debug, Error)]
pub enum CaptureError {
    #[error("cannot read frame file {path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("frame file {path}, frame {index} (at byte {offset}): {source}")]
    Frame {
        path: PathBuf,
        index: u64,
        offset: u64,
        source: FrameError,
    },
}

/// Calls `each` with every frame's payload in `path`, in order; returns how many there were.
/// A length above `max_frame` or a file that ends inside a frame is an error naming the frame.
pub fn for_each_frame(
    path: &Path,
    max_frame: usize,
    mut each: impl FnMut(&[u8]),
) -> Result<u64, CaptureError> {
    let io = |source| CaptureError::Io {
        path: path.into(),
        source,
    };
    let mut file = std::fs::File::open(path).map_err(io)?;
    let mut decoder = FrameDecoder::new(max_frame);
    let (mut index, mut offset) = (0u64, 0u64);
    let bad = |index, offset, source| CaptureError::Frame {
        path: path.into(),
        index,
        offset,
        source,
    };
    loop {
        let spare = decoder.spare(64 * 1024);
        let got = match file.read(spare) {
            Ok(got) => got,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => 0,
            Err(e) => return Err(io(e)),
        };
        decoder.commit(64 * 1024, got);
        loop {
            match decoder.next_frame() {
                Ok(Some(frame)) => {
                    each(frame);
                    offset += (frame.len() + replica_rt::frame::HEADER_LEN) as u64;
                    index += 1;
                }
                Ok(None) => break,
                Err(e) => return Err(bad(index, offset, e)),
            }
        }
        if got == 0 {
            decoder.finish().map_err(|e| bad(index, offset, e))?;
            return Ok(index);
        }
    }
}

/// Writes `frames` to `path` in the s3res framing.
pub fn write_frames<'a>(
    path: &Path,
    frames: impl IntoIterator<Item = &'a [u8]>,
) -> std::io::Result<()> {
    let mut bytes = Vec::new();
    for f in frames {
        encode_into(f, &mut bytes);
    }
    std::fs::write(path, bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_round_trip_and_damage_is_named() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("frames.bin");
        let frames: Vec<Vec<u8>> = (0..1000u32)
            .map(|i| i.to_le_bytes().repeat(1 + i as usize % 50))
            .collect();
        write_frames(&path, frames.iter().map(Vec::as_slice)).unwrap();
        let mut got = Vec::new();
        let count = for_each_frame(&path, 1024, |f| got.push(f.to_vec())).unwrap();
        assert_eq!(count, 1000);
        assert_eq!(got, frames);

        let mut bytes = std::fs::read(&path).unwrap();
        bytes.truncate(bytes.len() - 1);
        std::fs::write(&path, &bytes).unwrap();
        let err = for_each_frame(&path, 1024, |_| {}).unwrap_err().to_string();
        assert!(err.contains("frame 999"), "{err}");
        assert!(err.contains("closed after"), "{err}");

        let err = for_each_frame(&path, 8, |_| {}).unwrap_err().to_string();
        assert!(err.contains("frame 2 (at byte 20)"), "{err}");
        let err = for_each_frame(&dir.path().join("none"), 8, |_| {})
            .unwrap_err()
            .to_string();
        assert!(err.contains("cannot read frame file"), "{err}");
    }
}
