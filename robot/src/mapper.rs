//! The mapper: an occupancy grid built from filtered scans and the robot's pose.
//!
//! Each cell keeps a log-odds score (small integers, so replicas agree exactly). Every beam
//! lowers the score of the cells it crosses (evidence of free space) and, if it ended on
//! something — short of [`SAW_NOTHING_FROM`] — raises the score of the cell it ended in
//! (evidence of a wall). The published
//! state of a cell is `Occupied` at a score of [`OCCUPIED_AT`] or more, `Free` at
//! [`FREE_AT`] or less, `Unknown` otherwise.
//!
//! Updates are sent on a fixed schedule: after every scan whose `seq` is a multiple of `every`.
//! The schedule depends on `seq` only, so it survives a restart and is the same in every replica
//! (a stream-mode voter compares the k-th update of each replica).

use crate::msg::{Cell, MapUpdate, Scan, RANGES};

/// Score added where a beam ended on a wall.
pub const HIT: i8 = 2;
/// Score added to a cell a beam crossed.
pub const MISS: i8 = -1;
/// Scores are kept within ±[`CLAMP`], so that the map can change its mind.
pub const CLAMP: i8 = 8;
pub const OCCUPIED_AT: i8 = 3;
pub const FREE_AT: i8 = -1;

/// Sensor range the mapper assumes.
pub const MAX_RANGE: f64 = 2.0;

/// A reading at or beyond this saw nothing: the sensor's noise (±1 cm, the sim's `noise_m`)
/// spreads the readings of a beam that met no wall over 1.99–2.0 m (clamped at its range), half
/// of them below 2.0. Taken as walls, they put a ring of ghost blocks at the range's end
/// around the robot, wherever a corridor was open further than that. Most were crossed and
/// cleared by later beams; one left where the robot never looked again could close the only
/// way to the goal on the map (`delay_sweep` over mazes 1–16: 30 of 3,200 missions out of
/// time, 29 of them maze 15's; 0 with this bound). The navigator reads the same bound as
/// nothing seen.
pub const SAW_NOTHING_FROM: f64 = MAX_RANGE - 0.01;

/// The occupancy grid and its update schedule.
#[derive(Debug, Clone)]
pub struct Mapper {
    every: u32,
    w: usize,
    h: usize,
    block: f64,
    score: Vec<i8>,
    /// Marks cells already updated by the current beam (generation counter, no clearing).
    touched: Vec<u32>,
    generation: u32,
}

impl Mapper {
    /// `every`: send an update after every scan whose `seq` is a multiple of it (at least 1).
    pub fn new(every: u32) -> Mapper {
        Mapper {
            every: every.max(1),
            w: 0,
            h: 0,
            block: 0.0,
            score: Vec::new(),
            touched: Vec::new(),
            generation: 0,
        }
    }

    /// The grid's published state of cell (cx, cy).
    pub fn cell(&self, cx: usize, cy: usize) -> Cell {
        let s = self.score[cy * self.w + cx];
        if s >= OCCUPIED_AT {
            Cell::Occupied
        } else if s <= FREE_AT {
            Cell::Free
        } else {
            Cell::Unknown
        }
    }

    /// Integrates one scan; returns the update to send if the schedule says so.
    pub fn on_scan(&mut self, scan: &Scan) -> Option<MapUpdate> {
        let (w, h) = (scan.grid_w as usize, scan.grid_h as usize);
        if w == 0 || h == 0 || scan.block.is_nan() || scan.block <= 0.0 {
            return None;
        }
        if (w, h) != (self.w, self.h) || scan.block != self.block {
            // First scan (or the arena changed): start a fresh grid.
            self.w = w;
            self.h = h;
            self.block = scan.block;
            self.score = vec![0; w * h];
            self.touched = vec![0; w * h];
        }
        for (i, &r) in scan.ranges.iter().enumerate() {
            let a = scan.theta + i as f64 * std::f64::consts::TAU / RANGES as f64;
            self.integrate_beam(scan.x, scan.y, a, r);
        }
        // (`checked_rem`, not `is_multiple_of`: the workspace supports Rust 1.80.)
        if scan.seq.checked_rem(self.every) != Some(0) {
            return None;
        }
        let cells = (0..h)
            .flat_map(|cy| (0..w).map(move |cx| (cx, cy)))
            .map(|(cx, cy)| self.cell(cx, cy))
            .collect();
        Some(MapUpdate {
            seq: scan.seq,
            next: scan.seq.saturating_add(self.every),
            w: w as u16,
            h: h as u16,
            block: self.block,
            x: scan.x,
            y: scan.y,
            goal_x: scan.goal_x,
            goal_y: scan.goal_y,
            cells,
        })
    }

    fn cell_of(&self, x: f64, y: f64) -> Option<usize> {
        let (cx, cy) = ((x / self.block).floor(), (y / self.block).floor());
        if cx < 0.0 || cy < 0.0 || cx >= self.w as f64 || cy >= self.h as f64 {
            return None;
        }
        Some(cy as usize * self.w + cx as usize)
    }

    fn add(&mut self, cell: usize, delta: i8) {
        if self.touched[cell] == self.generation {
            return;
        }
        self.touched[cell] = self.generation;
        self.score[cell] = self.score[cell].saturating_add(delta).clamp(-CLAMP, CLAMP);
    }

    fn integrate_beam(&mut self, x: f64, y: f64, angle: f64, range: f64) {
        if !range.is_finite() || !x.is_finite() || !y.is_finite() || !angle.is_finite() {
            return;
        }
        self.generation = self.generation.wrapping_add(1);
        if self.generation == 0 {
            self.touched.iter_mut().for_each(|t| *t = 0);
            self.generation = 1;
        }
        let range = range.clamp(0.0, MAX_RANGE);
        let (dx, dy) = (angle.cos(), angle.sin());
        let hit = range < SAW_NOTHING_FROM;
        // The endpoint cell first, so that the free-space pass cannot clear a wall it grazes.
        if hit {
            let reach = range + self.block * 0.25;
            if let Some(c) = self.cell_of(x + reach * dx, y + reach * dy) {
                self.add(c, HIT);
            }
        }
        let step = self.block / 4.0;
        let free_to = if hit {
            range - self.block * 0.25
        } else {
            range
        };
        let n = (free_to.max(0.0) / step) as usize;
        for k in 0..=n {
            let t = k as f64 * step;
            if let Some(c) = self.cell_of(x + t * dx, y + t * dy) {
                self.add(c, MISS);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::filter::MedianFilter;
    use crate::mission::ghost_blocks;
    use crate::sim::{Sim, SimConfig};

    #[test]
    fn a_wall_in_front_becomes_occupied_and_the_gap_free() {
        let mut m = Mapper::new(1);
        let mut ranges = [MAX_RANGE; RANGES];
        ranges[0] = 1.0; // beam 0 looks east (theta = 0) and hits at x = 1.5
        let scan = Scan {
            seq: 0,
            grid_w: 12,
            grid_h: 12,
            block: 0.25,
            x: 0.5,
            y: 0.6,
            theta: 0.0,
            goal_x: 0.0,
            goal_y: 0.0,
            ranges,
        };
        let mut up = None;
        for _ in 0..3 {
            up = m.on_scan(&scan);
        }
        let up = up.expect("every = 1 sends every time");
        assert_eq!((up.seq, up.next), (0, 1));
        // x = 1.5 .. 1.75 is column 6; row of y = 0.6 is 2.
        assert_eq!(m.cell(6, 2), Cell::Occupied);
        for cx in 2..6 {
            assert_eq!(m.cell(cx, 2), Cell::Free, "column {cx}");
        }
        assert_eq!(m.cell(11, 11), Cell::Unknown);
        assert_eq!(up.cells[2 * 12 + 6], Cell::Occupied);
    }

    #[test]
    fn a_beam_that_saw_nothing_marks_no_wall_whatever_its_noise() {
        let mut m = Mapper::new(1);
        let mut scan = Scan {
            seq: 0,
            grid_w: 24,
            grid_h: 24,
            block: 0.25,
            x: 3.1,
            y: 3.1,
            theta: 0.0,
            goal_x: 0.0,
            goal_y: 0.0,
            ranges: [MAX_RANGE; RANGES],
        };
        // A beam that met no wall reads its range give or take the noise (clamped at it).
        for (i, r) in scan.ranges.iter_mut().enumerate() {
            *r = [SAW_NOTHING_FROM, 1.995, MAX_RANGE][i % 3];
        }
        for _ in 0..5 {
            m.on_scan(&scan);
        }
        let occupied = |m: &Mapper| {
            (0..24)
                .flat_map(|cy| (0..24).map(move |cx| (cx, cy)))
                .filter(|&(cx, cy)| m.cell(cx, cy) == Cell::Occupied)
                .collect::<Vec<_>>()
        };
        assert_eq!(occupied(&m), vec![]);
        // A wall just inside the bound is one.
        let mut m = Mapper::new(1);
        scan.ranges = [MAX_RANGE; RANGES];
        scan.ranges[0] = 1.98; // east: x = 5.08 .. 5.14, column 20; y = 3.1 is row 12
        for _ in 0..2 {
            m.on_scan(&scan);
        }
        assert_eq!(occupied(&m), vec![(20, 12)]);
    }

    /// A robot standing in the maze with the sim's noise on every reading, its scans cleaned
    /// by the sensor filter as in the system: no block is called a wall that is not one. Before
    /// [`SAW_NOTHING_FROM`], every beam down an open corridor put a ghost at 2 m about every
    /// other scan.
    #[test]
    fn a_robot_standing_in_the_maze_sees_no_ghost_walls() {
        for maze in [1, 4, 15] {
            let mut sim = Sim::new(SimConfig {
                outlier_per_mille: 0,
                ..SimConfig::new(maze)
            });
            let mut filter = MedianFilter::new(3);
            let mut m = Mapper::new(5);
            for _ in 0..40 {
                m.on_scan(&filter.apply(&sim.scan()));
                sim.step(None);
            }
            let side = sim.world.side;
            let walls = (0..side)
                .flat_map(|cy| (0..side).map(move |cx| (cx, cy)))
                .filter(|&(cx, cy)| m.cell(cx, cy) == Cell::Occupied)
                .count();
            assert_eq!(ghost_blocks(&sim, &m), vec![], "maze {maze}: ghost walls");
            assert!(walls >= 8, "maze {maze}: only {walls} walls seen");
        }
    }

    #[test]
    fn the_map_of_a_real_scan_matches_the_world_and_follows_the_schedule() {
        let mut sim = Sim::new(SimConfig {
            outlier_per_mille: 0,
            ..SimConfig::new(4)
        });
        let mut m = Mapper::new(5);
        let mut sent = Vec::new();
        for _ in 0..11 {
            let scan = sim.scan();
            if let Some(u) = m.on_scan(&scan) {
                sent.push(u.seq);
            }
            sim.step(None);
        }
        assert_eq!(sent, vec![0, 5, 10]);
        // Every cell the map calls occupied is a wall in the world.
        let side = sim.world.side;
        let mut occupied = 0;
        for cy in 0..side {
            for cx in 0..side {
                if m.cell(cx, cy) == Cell::Occupied {
                    occupied += 1;
                    assert!(sim.world.is_wall(cx as i64, cy as i64), "({cx}, {cy})");
                }
            }
        }
        assert!(occupied > 10, "{occupied}");
    }
}
