//! Every frame the robot's components exchange, with its byte layout.
//!
//! All layouts are fixed and little-endian: integers as `u8`/`u16`/`u32`/`u64`, reals as IEEE-754
//! `f64`. Every frame starts with a one-byte tag naming its type, so a frame sent to the wrong
//! port is an error, not a misread. Decoding checks the tag, the length and every count, and
//! returns [`MsgError`] for anything else: it never panics on bad input (a corrupted frame is
//! data, not a bug). Encoding writes into a caller's `Vec`, which the components reuse.
//!
//! | frame | tag | from → to | layout after the tag |
//! |---|---|---|---|
//! | [`Scan`] | `S` | sim → filter → navigator, mapper | `seq u32, grid_w u16, grid_h u16, block f64, x f64, y f64, theta f64, goal_x f64, goal_y f64, ranges [f64; 16]` |
//! | [`Cmd`] | `C` | navigator → sim | `seq u32, v f64, w f64, plan u32` |
//! | [`Request`] | `R` | navigator → planner | `seq u32, want u8 (0/1), x f64, y f64, goal_x f64, goal_y f64` |
//! | [`MapUpdate`] | `M` | mapper → planner | `seq u32, next u32, w u16, h u16, block f64, x f64, y f64, goal_x f64, goal_y f64, cells [u8; w*h]` (row-major, row 0 at y = 0; 0 unknown, 1 free, 2 occupied) |
//! | [`Waypoints`] | `W` | planner → navigator | `plan u32, seq u32, n u16, n × (x f64, y f64)` |
//! | [`Telemetry`] | `T` | sim → logger | `seq u32, x f64, y f64, theta f64, v f64, w f64` |
//! | [`Tick`] | `K` | sim → load | `seq u32` |
//! | [`LoadSum`] | `L` | load → logger | `seq u32, sum u64` |

use thiserror::Error;

/// Number of range sensors on the robot's ring.
pub const RANGES: usize = 16;

/// Most waypoints one [`Waypoints`] frame may carry.
pub const MAX_WAYPOINTS: usize = 4000;

/// Largest grid side a [`MapUpdate`] may carry.
pub const MAX_GRID_SIDE: usize = 1024;

/// A frame could not be decoded.
#[derive(Debug, Error, PartialEq, Eq)]
pub enum MsgError {
    #[error("empty frame, expected a {want} frame")]
    Empty { want: &'static str },
    #[error("frame tag {got:?} is not a {want} frame (tag {expected:?})")]
    Tag {
        want: &'static str,
        expected: char,
        got: char,
    },
    #[error("{want} frame of {got} bytes, expected {expected}")]
    Length {
        want: &'static str,
        expected: usize,
        got: usize,
    },
    #[error("{want} frame: {field} = {value} is out of range")]
    Range {
        want: &'static str,
        field: &'static str,
        value: u64,
    },
}

/// Reads fields in order from a payload whose length was checked first.
struct Reader<'a> {
    b: &'a [u8],
    at: usize,
}

impl<'a> Reader<'a> {
    /// Checks tag and exact length (`fixed` bytes after the tag, plus `extra`).
    fn open(b: &'a [u8], want: &'static str, tag: u8, len: usize) -> Result<Reader<'a>, MsgError> {
        let Some(&got) = b.first() else {
            return Err(MsgError::Empty { want });
        };
        if got != tag {
            return Err(MsgError::Tag {
                want,
                expected: tag as char,
                got: got as char,
            });
        }
        if b.len() != len {
            return Err(MsgError::Length {
                want,
                expected: len,
                got: b.len(),
            });
        }
        Ok(Reader { b, at: 1 })
    }

    fn take<const N: usize>(&mut self) -> [u8; N] {
        let mut out = [0u8; N];
        // In bounds: `open` checked the total length against the layout.
        out.copy_from_slice(&self.b[self.at..self.at + N]);
        self.at += N;
        out
    }
    fn u8(&mut self) -> u8 {
        self.take::<1>()[0]
    }
    fn u16(&mut self) -> u16 {
        u16::from_le_bytes(self.take())
    }
    fn u32(&mut self) -> u32 {
        u32::from_le_bytes(self.take())
    }
    fn u64(&mut self) -> u64 {
        u64::from_le_bytes(self.take())
    }
    fn f64(&mut self) -> f64 {
        f64::from_le_bytes(self.take())
    }
    fn rest(&self) -> &'a [u8] {
        &self.b[self.at..]
    }
}

/// Peeks a `u16` at byte `at` (for counts that decide the length), if the frame is long enough.
fn peek_u16(b: &[u8], at: usize) -> Option<u16> {
    Some(u16::from_le_bytes([*b.get(at)?, *b.get(at + 1)?]))
}

fn put_f64(out: &mut Vec<u8>, v: f64) {
    out.extend_from_slice(&v.to_le_bytes());
}

/// Sensor frame: the robot's pose and its 16 ranges (raw from the sim, cleaned by the filter).
/// Also carries the arena's size and the goal, so that no component needs them as arguments
/// that could disagree with the sim's.
#[derive(Debug, Clone, PartialEq)]
pub struct Scan {
    pub seq: u32,
    pub grid_w: u16,
    pub grid_h: u16,
    /// Side of one grid block, metres.
    pub block: f64,
    pub x: f64,
    pub y: f64,
    pub theta: f64,
    pub goal_x: f64,
    pub goal_y: f64,
    /// Range of beam `i` (at `theta + i·2π/16`), metres, at most the sensor's range.
    pub ranges: [f64; RANGES],
}

impl Scan {
    pub const TAG: u8 = b'S';
    pub const LEN: usize = 1 + 4 + 2 + 2 + 8 * 6 + 8 * RANGES;

    pub fn encode(&self, out: &mut Vec<u8>) {
        out.clear();
        out.push(Self::TAG);
        out.extend_from_slice(&self.seq.to_le_bytes());
        out.extend_from_slice(&self.grid_w.to_le_bytes());
        out.extend_from_slice(&self.grid_h.to_le_bytes());
        for v in [
            self.block,
            self.x,
            self.y,
            self.theta,
            self.goal_x,
            self.goal_y,
        ] {
            put_f64(out, v);
        }
        for r in self.ranges {
            put_f64(out, r);
        }
    }

    pub fn decode(b: &[u8]) -> Result<Scan, MsgError> {
        let mut r = Reader::open(b, "scan", Self::TAG, Self::LEN)?;
        let mut s = Scan {
            seq: r.u32(),
            grid_w: r.u16(),
            grid_h: r.u16(),
            block: r.f64(),
            x: r.f64(),
            y: r.f64(),
            theta: r.f64(),
            goal_x: r.f64(),
            goal_y: r.f64(),
            ranges: [0.0; RANGES],
        };
        for v in s.ranges.iter_mut() {
            *v = r.f64();
        }
        Ok(s)
    }
}

/// Velocity command for the period `seq`, and the plan it follows (for counting replans).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Cmd {
    pub seq: u32,
    /// Forward speed, m/s.
    pub v: f64,
    /// Turn rate, rad/s (counter-clockwise positive).
    pub w: f64,
    /// Id of the plan being followed; 0 before the first plan.
    pub plan: u32,
}

impl Cmd {
    pub const TAG: u8 = b'C';
    pub const LEN: usize = 1 + 4 + 8 + 8 + 4;

    pub fn encode(&self, out: &mut Vec<u8>) {
        out.clear();
        out.push(Self::TAG);
        out.extend_from_slice(&self.seq.to_le_bytes());
        put_f64(out, self.v);
        put_f64(out, self.w);
        out.extend_from_slice(&self.plan.to_le_bytes());
    }

    pub fn decode(b: &[u8]) -> Result<Cmd, MsgError> {
        let mut r = Reader::open(b, "cmd", Self::TAG, Self::LEN)?;
        Ok(Cmd {
            seq: r.u32(),
            v: r.f64(),
            w: r.f64(),
            plan: r.u32(),
        })
    }
}

/// The navigator's word to the planner for period `seq`: sent every period (a reactive round
/// expects it), `want` says whether a plan is asked for.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Request {
    pub seq: u32,
    pub want: bool,
    pub x: f64,
    pub y: f64,
    pub goal_x: f64,
    pub goal_y: f64,
}

impl Request {
    pub const TAG: u8 = b'R';
    pub const LEN: usize = 1 + 4 + 1 + 8 * 4;

    pub fn encode(&self, out: &mut Vec<u8>) {
        out.clear();
        out.push(Self::TAG);
        out.extend_from_slice(&self.seq.to_le_bytes());
        out.push(self.want as u8);
        for v in [self.x, self.y, self.goal_x, self.goal_y] {
            put_f64(out, v);
        }
    }

    pub fn decode(b: &[u8]) -> Result<Request, MsgError> {
        let mut r = Reader::open(b, "request", Self::TAG, Self::LEN)?;
        let seq = r.u32();
        let want = match r.u8() {
            0 => false,
            1 => true,
            v => {
                return Err(MsgError::Range {
                    want: "request",
                    field: "want",
                    value: v as u64,
                })
            }
        };
        Ok(Request {
            seq,
            want,
            x: r.f64(),
            y: r.f64(),
            goal_x: r.f64(),
            goal_y: r.f64(),
        })
    }
}

/// State of one occupancy-grid cell as the mapper publishes it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u8)]
pub enum Cell {
    Unknown = 0,
    Free = 1,
    Occupied = 2,
}

/// The mapper's occupancy grid after scan `seq`, with the pose of that scan (so the planner can
/// replan from where the robot was).
#[derive(Debug, Clone, PartialEq)]
pub struct MapUpdate {
    pub seq: u32,
    /// The `seq` of the next update the mapper will send (its schedule), so that the planner
    /// can merge updates and requests in `seq` order without guessing.
    pub next: u32,
    pub w: u16,
    pub h: u16,
    pub block: f64,
    pub x: f64,
    pub y: f64,
    pub goal_x: f64,
    pub goal_y: f64,
    /// `w*h` cells, row-major, row 0 at y = 0.
    pub cells: Vec<Cell>,
}

impl MapUpdate {
    pub const TAG: u8 = b'M';
    pub const HEADER: usize = 1 + 4 + 4 + 2 + 2 + 8 * 5;

    pub fn encode(&self, out: &mut Vec<u8>) {
        out.clear();
        out.push(Self::TAG);
        out.extend_from_slice(&self.seq.to_le_bytes());
        out.extend_from_slice(&self.next.to_le_bytes());
        out.extend_from_slice(&self.w.to_le_bytes());
        out.extend_from_slice(&self.h.to_le_bytes());
        for v in [self.block, self.x, self.y, self.goal_x, self.goal_y] {
            put_f64(out, v);
        }
        out.extend(self.cells.iter().map(|&c| c as u8));
    }

    pub fn decode(b: &[u8]) -> Result<MapUpdate, MsgError> {
        let want = "map";
        let (w, h) = (
            peek_u16(b, 9).unwrap_or(0) as usize,
            peek_u16(b, 11).unwrap_or(0) as usize,
        );
        for (field, v) in [("w", w), ("h", h)] {
            if v > MAX_GRID_SIDE {
                return Err(MsgError::Range {
                    want,
                    field,
                    value: v as u64,
                });
            }
        }
        let mut r = Reader::open(b, want, Self::TAG, Self::HEADER + w * h)?;
        let mut m = MapUpdate {
            seq: r.u32(),
            next: r.u32(),
            w: r.u16(),
            h: r.u16(),
            block: r.f64(),
            x: r.f64(),
            y: r.f64(),
            goal_x: r.f64(),
            goal_y: r.f64(),
            cells: Vec::with_capacity(w * h),
        };
        for (i, &c) in r.rest().iter().enumerate() {
            m.cells.push(match c {
                0 => Cell::Unknown,
                1 => Cell::Free,
                2 => Cell::Occupied,
                v => {
                    return Err(MsgError::Range {
                        want,
                        field: "cell",
                        value: (i as u64) << 8 | v as u64,
                    })
                }
            });
        }
        Ok(m)
    }
}

/// A plan: the path from the robot to the goal as points in metres, nearest first. `plan`
/// numbers the plans the planner has made (1, 2, ...); `seq` is the period of the request or map
/// it answers.
#[derive(Debug, Clone, PartialEq)]
pub struct Waypoints {
    pub plan: u32,
    pub seq: u32,
    pub points: Vec<(f64, f64)>,
}

impl Waypoints {
    pub const TAG: u8 = b'W';
    pub const HEADER: usize = 1 + 4 + 4 + 2;

    pub fn encode(&self, out: &mut Vec<u8>) {
        out.clear();
        out.push(Self::TAG);
        out.extend_from_slice(&self.plan.to_le_bytes());
        out.extend_from_slice(&self.seq.to_le_bytes());
        let n = self.points.len().min(MAX_WAYPOINTS);
        out.extend_from_slice(&(n as u16).to_le_bytes());
        for &(x, y) in &self.points[..n] {
            put_f64(out, x);
            put_f64(out, y);
        }
    }

    pub fn decode(b: &[u8]) -> Result<Waypoints, MsgError> {
        let want = "waypoints";
        let n = peek_u16(b, 9).unwrap_or(0) as usize;
        if n > MAX_WAYPOINTS {
            return Err(MsgError::Range {
                want,
                field: "n",
                value: n as u64,
            });
        }
        let mut r = Reader::open(b, want, Self::TAG, Self::HEADER + 16 * n)?;
        let plan = r.u32();
        let seq = r.u32();
        let _n = r.u16();
        let points = (0..n).map(|_| (r.f64(), r.f64())).collect();
        Ok(Waypoints { plan, seq, points })
    }
}

/// The robot's true pose and the command in force, once per period (sim → logger).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Telemetry {
    pub seq: u32,
    pub x: f64,
    pub y: f64,
    pub theta: f64,
    pub v: f64,
    pub w: f64,
}

impl Telemetry {
    pub const TAG: u8 = b'T';
    pub const LEN: usize = 1 + 4 + 8 * 5;

    pub fn encode(&self, out: &mut Vec<u8>) {
        out.clear();
        out.push(Self::TAG);
        out.extend_from_slice(&self.seq.to_le_bytes());
        for v in [self.x, self.y, self.theta, self.v, self.w] {
            put_f64(out, v);
        }
    }

    pub fn decode(b: &[u8]) -> Result<Telemetry, MsgError> {
        let mut r = Reader::open(b, "telemetry", Self::TAG, Self::LEN)?;
        Ok(Telemetry {
            seq: r.u32(),
            x: r.f64(),
            y: r.f64(),
            theta: r.f64(),
            v: r.f64(),
            w: r.f64(),
        })
    }
}

/// One unit of background work to do (sim → load).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Tick {
    pub seq: u32,
}

impl Tick {
    pub const TAG: u8 = b'K';
    pub const LEN: usize = 1 + 4;

    pub fn encode(&self, out: &mut Vec<u8>) {
        out.clear();
        out.push(Self::TAG);
        out.extend_from_slice(&self.seq.to_le_bytes());
    }

    pub fn decode(b: &[u8]) -> Result<Tick, MsgError> {
        let mut r = Reader::open(b, "tick", Self::TAG, Self::LEN)?;
        Ok(Tick { seq: r.u32() })
    }
}

/// The checksum of the work done for tick `seq` (load → logger).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LoadSum {
    pub seq: u32,
    pub sum: u64,
}

impl LoadSum {
    pub const TAG: u8 = b'L';
    pub const LEN: usize = 1 + 4 + 8;

    pub fn encode(&self, out: &mut Vec<u8>) {
        out.clear();
        out.push(Self::TAG);
        out.extend_from_slice(&self.seq.to_le_bytes());
        out.extend_from_slice(&self.sum.to_le_bytes());
    }

    pub fn decode(b: &[u8]) -> Result<LoadSum, MsgError> {
        let mut r = Reader::open(b, "load sum", Self::TAG, Self::LEN)?;
        Ok(LoadSum {
            seq: r.u32(),
            sum: r.u64(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scan() -> Scan {
        let mut ranges = [0.0; RANGES];
        for (i, r) in ranges.iter_mut().enumerate() {
            *r = i as f64 * 0.125;
        }
        Scan {
            seq: 7,
            grid_w: 33,
            grid_h: 33,
            block: 0.25,
            x: 1.5,
            y: -2.25,
            theta: 0.5,
            goal_x: 7.0,
            goal_y: 8.0,
            ranges,
        }
    }

    #[test]
    fn every_frame_round_trips() {
        let mut buf = Vec::new();
        let s = scan();
        s.encode(&mut buf);
        assert_eq!(buf.len(), Scan::LEN);
        assert_eq!(Scan::decode(&buf).unwrap(), s);

        let c = Cmd {
            seq: 3,
            v: 0.5,
            w: -1.0,
            plan: 2,
        };
        c.encode(&mut buf);
        assert_eq!(Cmd::decode(&buf).unwrap(), c);

        let r = Request {
            seq: 9,
            want: true,
            x: 1.0,
            y: 2.0,
            goal_x: 3.0,
            goal_y: 4.0,
        };
        r.encode(&mut buf);
        assert_eq!(Request::decode(&buf).unwrap(), r);

        let m = MapUpdate {
            seq: 10,
            next: 15,
            w: 3,
            h: 2,
            block: 0.25,
            x: 0.1,
            y: 0.2,
            goal_x: 1.0,
            goal_y: 1.0,
            cells: vec![
                Cell::Unknown,
                Cell::Free,
                Cell::Occupied,
                Cell::Free,
                Cell::Free,
                Cell::Unknown,
            ],
        };
        m.encode(&mut buf);
        assert_eq!(MapUpdate::decode(&buf).unwrap(), m);

        let w = Waypoints {
            plan: 4,
            seq: 11,
            points: vec![(0.5, 0.5), (1.0, 0.75)],
        };
        w.encode(&mut buf);
        assert_eq!(Waypoints::decode(&buf).unwrap(), w);

        let t = Telemetry {
            seq: 1,
            x: 1.0,
            y: 2.0,
            theta: 3.0,
            v: 0.4,
            w: 0.1,
        };
        t.encode(&mut buf);
        assert_eq!(Telemetry::decode(&buf).unwrap(), t);

        Tick { seq: 5 }.encode(&mut buf);
        assert_eq!(Tick::decode(&buf).unwrap(), Tick { seq: 5 });
        let l = LoadSum { seq: 5, sum: 77 };
        l.encode(&mut buf);
        assert_eq!(LoadSum::decode(&buf).unwrap(), l);
    }

    #[test]
    fn bad_frames_are_errors_not_panics() {
        let mut buf = Vec::new();
        scan().encode(&mut buf);
        assert!(matches!(Scan::decode(&[]), Err(MsgError::Empty { .. })));
        assert!(matches!(Cmd::decode(&buf), Err(MsgError::Tag { .. })));
        assert!(matches!(
            Scan::decode(&buf[..buf.len() - 1]),
            Err(MsgError::Length { .. })
        ));
        // Counts that promise more than the frame holds, or more than allowed.
        assert!(Waypoints::decode(&[b'W', 0, 0, 0, 0, 0, 0, 0, 0, 0xff, 0xff]).is_err());
        assert!(Waypoints::decode(&[b'W', 0, 0, 0, 0, 0, 0, 0, 0, 2, 0]).is_err());
        assert!(MapUpdate::decode(&[b'M', 0, 0, 0, 0, 0, 0, 0, 0, 0xff, 0xff, 1, 0]).is_err());
        let mut req = Vec::new();
        Request {
            seq: 0,
            want: false,
            x: 0.0,
            y: 0.0,
            goal_x: 0.0,
            goal_y: 0.0,
        }
        .encode(&mut req);
        req[5] = 7;
        assert!(matches!(
            Request::decode(&req),
            Err(MsgError::Range { field: "want", .. })
        ));
        // Every truncation and every single-byte corruption of every frame: never a panic.
        for len in 0..buf.len() {
            let _ = Scan::decode(&buf[..len]);
            let _ = MapUpdate::decode(&buf[..len]);
            let _ = Waypoints::decode(&buf[..len]);
        }
        for i in 0..buf.len() {
            let mut b = buf.clone();
            b[i] ^= 0xff;
            let _ = Scan::decode(&b);
            b[0] = b'W';
            let _ = Waypoints::decode(&b);
            b[0] = b'M';
            let _ = MapUpdate::decode(&b);
        }
    }
}
