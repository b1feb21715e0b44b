//! The 2-D world: a maze generated from a seed, drawn on a grid of square blocks.
//!
//! A maze of `n × n` cells becomes a grid of `n·(c+1)+1` blocks a side: every cell is a
//! `c × c` square of free blocks (the corridor), every wall between two cells is one block
//! thick, and the outer wall closes the arena. Block (0, 0) is at the origin; x grows to the
//! east (columns), y to the north (rows). The start is the centre of cell (0, 0), the goal the
//! centre of cell (n-1, n-1): opposite corners.
//!
//! The maze is carved by a randomized depth-first search (a spanning tree of the cells, so
//! every cell — the goal too — is reachable: solvable by construction), then a fraction of the
//! remaining inner walls is removed ("braiding"), which makes loops, so that a blocked route
//! has an alternative and the planner has something to replan.

use s3res_protocol::rng::SplitMix64;

/// Parameters that, with the seed, fix the world.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct MazeSpec {
    pub seed: u64,
    /// Cells per side.
    pub cells: usize,
    /// Free blocks per corridor width.
    pub corridor: usize,
    /// Block side, metres.
    pub block: f64,
    /// Share of the remaining inner walls removed after carving, in percent.
    pub braid_percent: u32,
}

impl MazeSpec {
    /// The default world: 8 × 8 cells, corridors 0.75 m wide, walls 0.25 m thick.
    pub fn new(seed: u64) -> MazeSpec {
        MazeSpec {
            seed,
            cells: 8,
            corridor: 3,
            block: 0.25,
            braid_percent: 15,
        }
    }
}

/// The world: which blocks are wall.
#[derive(Debug, Clone, PartialEq)]
pub struct World {
    pub spec: MazeSpec,
    /// Blocks per side.
    pub side: usize,
    /// `side*side` blocks, row-major, `true` = wall.
    wall: Vec<bool>,
}

impl World {
    /// Generates the world of `spec` (deterministic: the same spec gives the same world).
    pub fn generate(spec: MazeSpec) -> World {
        let n = spec.cells.max(1);
        let c = spec.corridor.max(1);
        let pitch = c + 1;
        let side = n * pitch + 1;
        let mut world = World {
            spec,
            side,
            wall: vec![true; side * side],
        };
        let mut rng = SplitMix64::new(spec.seed);
        // Open every cell's corridor square.
        for cy in 0..n {
            for cx in 0..n {
                for by in 0..c {
                    for bx in 0..c {
                        world.set(1 + cx * pitch + bx, 1 + cy * pitch + by, false);
                    }
                }
            }
        }
        // Randomized DFS over the cells.
        let mut visited = vec![false; n * n];
        let mut stack = vec![(0usize, 0usize)];
        visited[0] = true;
        while let Some(&(cx, cy)) = stack.last() {
            let mut options = [(0usize, 0usize); 4];
            let mut k = 0;
            for (dx, dy) in [(1i64, 0i64), (-1, 0), (0, 1), (0, -1)] {
                let (nx, ny) = (cx as i64 + dx, cy as i64 + dy);
                if nx >= 0 && ny >= 0 && (nx as usize) < n && (ny as usize) < n {
                    let (nx, ny) = (nx as usize, ny as usize);
                    if !visited[ny * n + nx] {
                        options[k] = (nx, ny);
                        k += 1;
                    }
                }
            }
            if k == 0 {
                stack.pop();
                continue;
            }
            let (nx, ny) = options[rng.below(k as u64) as usize];
            world.open_between((cx, cy), (nx, ny));
            visited[ny * n + nx] = true;
            stack.push((nx, ny));
        }
        // Braid: remove a share of the inner walls still standing, in a seeded order.
        let mut standing = Vec::new();
        for cy in 0..n {
            for cx in 0..n {
                if cx + 1 < n && world.wall_between((cx, cy), (cx + 1, cy)) {
                    standing.push(((cx, cy), (cx + 1, cy)));
                }
                if cy + 1 < n && world.wall_between((cx, cy), (cx, cy + 1)) {
                    standing.push(((cx, cy), (cx, cy + 1)));
                }
            }
        }
        let remove = standing.len() * spec.braid_percent.min(100) as usize / 100;
        for _ in 0..remove {
            let i = rng.below(standing.len() as u64) as usize;
            let (a, b) = standing.swap_remove(i);
            world.open_between(a, b);
        }
        world
    }

    fn set(&mut self, bx: usize, by: usize, wall: bool) {
        self.wall[by * self.side + bx] = wall;
    }

    /// Whether block (bx, by) is wall; outside the grid counts as wall.
    pub fn is_wall(&self, bx: i64, by: i64) -> bool {
        if bx < 0 || by < 0 || bx as usize >= self.side || by as usize >= self.side {
            return true;
        }
        self.wall[by as usize * self.side + bx as usize]
    }

    /// The block rows of the wall between two neighbouring cells.
    fn wall_blocks(&self, a: (usize, usize), b: (usize, usize)) -> Vec<(usize, usize)> {
        let c = self.spec.corridor.max(1);
        let pitch = c + 1;
        let (lo, hi) = if (a.0, a.1) < (b.0, b.1) {
            (a, b)
        } else {
            (b, a)
        };
        if lo.1 == hi.1 {
            // East-west neighbours: a vertical wall column.
            let bx = (lo.0 + 1) * pitch;
            (0..c).map(|i| (bx, 1 + lo.1 * pitch + i)).collect()
        } else {
            let by = (lo.1 + 1) * pitch;
            (0..c).map(|i| (1 + lo.0 * pitch + i, by)).collect()
        }
    }

    fn open_between(&mut self, a: (usize, usize), b: (usize, usize)) {
        for (bx, by) in self.wall_blocks(a, b) {
            self.set(bx, by, false);
        }
    }

    fn wall_between(&self, a: (usize, usize), b: (usize, usize)) -> bool {
        self.wall_blocks(a, b)
            .iter()
            .all(|&(bx, by)| self.is_wall(bx as i64, by as i64))
    }

    /// Side of the arena, metres.
    pub fn size_m(&self) -> f64 {
        self.side as f64 * self.spec.block
    }

    /// Centre of maze cell (cx, cy), metres.
    pub fn cell_centre(&self, cx: usize, cy: usize) -> (f64, f64) {
        let pitch = (self.spec.corridor.max(1) + 1) as f64;
        let c = self.spec.corridor.max(1) as f64;
        let b = self.spec.block;
        (
            (1.0 + cx as f64 * pitch + c / 2.0) * b,
            (1.0 + cy as f64 * pitch + c / 2.0) * b,
        )
    }

    pub fn start(&self) -> (f64, f64) {
        self.cell_centre(0, 0)
    }

    pub fn goal(&self) -> (f64, f64) {
        let n = self.spec.cells.max(1);
        self.cell_centre(n - 1, n - 1)
    }

    /// Distance from (x, y) along direction `angle` to the first wall, at most `max`. Walks the
    /// grid block by block (Amanatides–Woo), so it never misses a thin corner.
    pub fn raycast(&self, x: f64, y: f64, angle: f64, max: f64) -> f64 {
        let b = self.spec.block;
        let (dx, dy) = (angle.cos(), angle.sin());
        let (mut bx, mut by) = ((x / b).floor() as i64, (y / b).floor() as i64);
        if self.is_wall(bx, by) {
            return 0.0;
        }
        let step_x: i64 = if dx > 0.0 { 1 } else { -1 };
        let step_y: i64 = if dy > 0.0 { 1 } else { -1 };
        let next_edge = |p: f64, cell: i64, step: i64| {
            if step > 0 {
                (cell + 1) as f64 * b - p
            } else {
                p - cell as f64 * b
            }
        };
        let mut t_max_x = if dx.abs() < 1e-12 {
            f64::INFINITY
        } else {
            next_edge(x, bx, step_x) / dx.abs()
        };
        let mut t_max_y = if dy.abs() < 1e-12 {
            f64::INFINITY
        } else {
            next_edge(y, by, step_y) / dy.abs()
        };
        let t_dx = if dx.abs() < 1e-12 {
            f64::INFINITY
        } else {
            b / dx.abs()
        };
        let t_dy = if dy.abs() < 1e-12 {
            f64::INFINITY
        } else {
            b / dy.abs()
        };
        loop {
            let t = if t_max_x < t_max_y {
                bx += step_x;
                let t = t_max_x;
                t_max_x += t_dx;
                t
            } else {
                by += step_y;
                let t = t_max_y;
                t_max_y += t_dy;
                t
            };
            if t >= max {
                return max;
            }
            if self.is_wall(bx, by) {
                return t;
            }
        }
    }

    /// Whether a disc of `radius` at (x, y) overlaps any wall block.
    pub fn disc_hits_wall(&self, x: f64, y: f64, radius: f64) -> bool {
        let b = self.spec.block;
        let (x0, x1) = (
            ((x - radius) / b).floor() as i64,
            ((x + radius) / b).floor() as i64,
        );
        let (y0, y1) = (
            ((y - radius) / b).floor() as i64,
            ((y + radius) / b).floor() as i64,
        );
        for by in y0..=y1 {
            for bx in x0..=x1 {
                if !self.is_wall(bx, by) {
                    continue;
                }
                let cx = x.clamp(bx as f64 * b, (bx + 1) as f64 * b);
                let cy = y.clamp(by as f64 * b, (by + 1) as f64 * b);
                if (x - cx).powi(2) + (y - cy).powi(2) < radius * radius {
                    return true;
                }
            }
        }
        false
    }

    /// Shortest number of cell steps from start to goal (breadth-first over the cells; for
    /// tests and the summary's context).
    pub fn cell_distance_start_to_goal(&self) -> Option<usize> {
        let n = self.spec.cells.max(1);
        let mut dist = vec![usize::MAX; n * n];
        let mut queue = std::collections::VecDeque::new();
        dist[0] = 0;
        queue.push_back((0usize, 0usize));
        while let Some((cx, cy)) = queue.pop_front() {
            let d = dist[cy * n + cx];
            let mut next = Vec::new();
            if cx + 1 < n {
                next.push((cx + 1, cy));
            }
            if cx > 0 {
                next.push((cx - 1, cy));
            }
            if cy + 1 < n {
                next.push((cx, cy + 1));
            }
            if cy > 0 {
                next.push((cx, cy - 1));
            }
            for (nx, ny) in next {
                if !self.wall_between((cx, cy), (nx, ny)) && dist[ny * n + nx] == usize::MAX {
                    dist[ny * n + nx] = d + 1;
                    queue.push_back((nx, ny));
                }
            }
        }
        let d = dist[n * n - 1];
        (d != usize::MAX).then_some(d)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn same_seed_same_maze_and_every_maze_is_solvable() {
        for seed in 0..50 {
            let w = World::generate(MazeSpec::new(seed));
            assert_eq!(w, World::generate(MazeSpec::new(seed)));
            assert!(
                w.cell_distance_start_to_goal().unwrap() >= 14,
                "seed {seed}"
            );
            let (sx, sy) = w.start();
            assert!(!w.disc_hits_wall(sx, sy, 0.3));
            let (gx, gy) = w.goal();
            assert!(!w.disc_hits_wall(gx, gy, 0.3));
        }
        assert_ne!(
            World::generate(MazeSpec::new(1)),
            World::generate(MazeSpec::new(2))
        );
    }

    #[test]
    fn raycast_measures_the_distance_to_the_outer_wall() {
        let w = World::generate(MazeSpec::new(3));
        let (sx, sy) = w.start();
        // The start cell touches the outer wall on the west and the south: 1.5 blocks away.
        let west = w.raycast(sx, sy, std::f64::consts::PI, 5.0);
        assert!((west - 1.5 * 0.25).abs() < 1e-9, "{west}");
        let south = w.raycast(sx, sy, -std::f64::consts::FRAC_PI_2, 5.0);
        assert!((south - 1.5 * 0.25).abs() < 1e-9, "{south}");
        // Capped at the range.
        assert!(w.raycast(sx, sy, 0.0, 0.1) == 0.1);
    }

    #[test]
    fn collisions_need_overlap() {
        let w = World::generate(MazeSpec::new(3));
        let (sx, sy) = w.start();
        assert!(!w.disc_hits_wall(sx, sy, 0.37));
        assert!(w.disc_hits_wall(sx, sy, 0.38));
        assert!(w.disc_hits_wall(0.1, 0.1, 0.01));
    }
}
