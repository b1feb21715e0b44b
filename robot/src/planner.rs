//! The planner: A* on the mapper's occupancy grid.
//!
//! Costs are integers (1000 per straight step, 1414 per diagonal step), so that every replica
//! finds the same path, ties included. Unknown cells are planned through (optimistically, with a
//! small extra cost): the robot explores. Occupied cells are never entered, nor passed diagonally
//! at a corner. A cell next to an occupied one costs extra ([`INFLATED_COST`]): paths keep to the
//! middle of corridors, where the robot's body clears both walls.
//!
//! [`Planner`] answers requests and replans when a map update blocks the path it last sent.
//! When the map has no way to the goal, it plans through the occupied blocks the robot does not
//! see now ([`Grid::unseen_from`]), and failing that through all but the nearest
//! ([`Grid::near_only`]): the robot goes to look again rather than wait for ever.
//! It must see map updates and requests in `seq` order (an update of `seq` v before a request
//! of `seq` k ≥ v); [`Planner::needs_map_before`] tells the component which input to read next,
//! so that the order — and with it every output — is the same in every replica whatever the
//! timing (see `docs/maze-robot.md`, "Determinism").

use std::cmp::Reverse;
use std::collections::BinaryHeap;

use crate::mapper::MAX_RANGE;
use crate::msg::{Cell, MapUpdate, Request, Waypoints};

pub const STRAIGHT: u32 = 1000;
pub const DIAGONAL: u32 = 1414;
/// Extra cost of entering a cell next to an occupied one.
pub const INFLATED_COST: u32 = 4000;
/// Extra cost of entering a cell nobody has seen.
pub const UNKNOWN_COST: u32 = 200;
/// Occupied blocks within this distance of the robot, metres, stay walls whatever the map
/// says elsewhere ([`Grid::near_only`]).
pub const NEAR: f64 = 0.5;

/// An occupancy grid to plan on.
#[derive(Debug, Clone, PartialEq)]
pub struct Grid {
    pub w: usize,
    pub h: usize,
    pub cells: Vec<Cell>,
}

impl Grid {
    pub fn new(w: usize, h: usize) -> Grid {
        Grid {
            w,
            h,
            cells: vec![Cell::Unknown; w * h],
        }
    }

    /// A grid from rows of text, top row first: `#` occupied, `.` free, `?` unknown.
    pub fn from_rows(rows: &[&str]) -> Grid {
        let h = rows.len();
        let w = rows.first().map_or(0, |r| r.len());
        let mut g = Grid::new(w, h);
        for (i, row) in rows.iter().enumerate() {
            let cy = h - 1 - i;
            for (cx, ch) in row.bytes().enumerate().take(w) {
                g.cells[cy * w + cx] = match ch {
                    b'#' => Cell::Occupied,
                    b'.' => Cell::Free,
                    _ => Cell::Unknown,
                };
            }
        }
        g
    }

    /// This grid with the occupied blocks the robot at `(x, y)` does not see now taken as
    /// unknown: every one farther than `range`, or hidden behind another occupied block.
    ///
    /// Why: the mapper can mark a block occupied that is not (a spurious echo the filter let
    /// through). If such a ghost closes the only way to the goal, A* finds no path, the
    /// navigator keeps the plan it has, and a robot that stands where it cannot see the ghost
    /// waits for a plan until the time limit: nothing ever makes the mapper look again.
    /// Planning through what the robot cannot see sends it to look (a mobile robot's
    /// "conservative reset" of its obstacle map when it is stuck). The blocks in sight stay
    /// walls, so a real wall is approached only until it is in sight.
    pub fn unseen_from(&self, x: f64, y: f64, block: f64, range: f64) -> Grid {
        self.forgetting(x, y, block, |cell, d| {
            d <= range && self.in_sight(x, y, block, cell)
        })
    }

    /// This grid with every occupied block farther than `near` from `(x, y)` taken as unknown:
    /// the last resort when even [`Grid::unseen_from`] leaves no way (a ghost in sight that no
    /// beam of a robot standing still crosses). The robot moves, and its beams sweep what lies
    /// on its way.
    pub fn near_only(&self, x: f64, y: f64, block: f64, near: f64) -> Grid {
        self.forgetting(x, y, block, |_, d| d <= near)
    }

    /// A copy in which every occupied block for which `keep(block, distance of its centre
    /// from (x, y))` is false is unknown.
    fn forgetting(
        &self,
        x: f64,
        y: f64,
        block: f64,
        keep: impl Fn((usize, usize), f64) -> bool,
    ) -> Grid {
        let mut g = self.clone();
        for (i, c) in g.cells.iter_mut().enumerate() {
            let cell = (i % self.w, i / self.w);
            let (cx, cy) = centre(cell, block);
            let (dx, dy) = (cx - x, cy - y);
            if *c == Cell::Occupied && !keep(cell, (dx * dx + dy * dy).sqrt()) {
                *c = Cell::Unknown;
            }
        }
        g
    }

    /// Whether the straight line from `(x, y)` to the centre of `cell` crosses no other
    /// occupied block (sampled every quarter block, as the mapper traces its beams).
    fn in_sight(&self, x: f64, y: f64, block: f64, cell: (usize, usize)) -> bool {
        let (tx, ty) = centre(cell, block);
        let d = ((tx - x).powi(2) + (ty - y).powi(2)).sqrt();
        let steps = (d / (block / 4.0)) as usize;
        (0..steps).all(|k| {
            let t = k as f64 / steps as f64;
            let (px, py) = ((x + t * (tx - x)) / block, (y + t * (ty - y)) / block);
            let (cx, cy) = (px.floor() as i64, py.floor() as i64);
            (cx, cy) == (cell.0 as i64, cell.1 as i64) || self.at(cx, cy) != Cell::Occupied
        })
    }

    fn at(&self, cx: i64, cy: i64) -> Cell {
        if cx < 0 || cy < 0 || cx as usize >= self.w || cy as usize >= self.h {
            return Cell::Occupied;
        }
        self.cells[cy as usize * self.w + cx as usize]
    }

    /// Next to an occupied cell of the grid (outside the grid is impassable, not a wall).
    fn inflated(&self, cx: i64, cy: i64) -> bool {
        (-1..=1).any(|dy| {
            (-1..=1).any(|dx| {
                let (x, y) = (cx + dx, cy + dy);
                x >= 0
                    && y >= 0
                    && (x as usize) < self.w
                    && (y as usize) < self.h
                    && self.cells[y as usize * self.w + x as usize] == Cell::Occupied
            })
        })
    }

    fn enter_cost(&self, cx: i64, cy: i64) -> u32 {
        let mut c = 0;
        if self.inflated(cx, cy) {
            c += INFLATED_COST;
        }
        if self.at(cx, cy) == Cell::Unknown {
            c += UNKNOWN_COST;
        }
        c
    }
}

/// The centre of block `cell`, metres.
fn centre(cell: (usize, usize), block: f64) -> (f64, f64) {
    ((cell.0 as f64 + 0.5) * block, (cell.1 as f64 + 0.5) * block)
}

/// Octile distance: admissible for the step costs above (extra costs only add).
fn heuristic(a: (i64, i64), b: (i64, i64)) -> u32 {
    let (dx, dy) = ((a.0 - b.0).unsigned_abs(), (a.1 - b.1).unsigned_abs());
    let (lo, hi) = (dx.min(dy) as u32, dx.max(dy) as u32);
    STRAIGHT * (hi - lo) + DIAGONAL * lo
}

/// A shortest path from `start` to `goal` (cells), both included, with its cost; `None` if the
/// goal cannot be reached. The start cell may be occupied or inflated (the robot is where it
/// is); the goal must not be occupied.
pub fn astar(
    grid: &Grid,
    start: (usize, usize),
    goal: (usize, usize),
) -> Option<(Vec<(usize, usize)>, u32)> {
    let (w, h) = (grid.w, grid.h);
    if start.0 >= w || start.1 >= h || goal.0 >= w || goal.1 >= h {
        return None;
    }
    let idx = |c: (i64, i64)| c.1 as usize * w + c.0 as usize;
    let s = (start.0 as i64, start.1 as i64);
    let g = (goal.0 as i64, goal.1 as i64);
    if grid.at(g.0, g.1) == Cell::Occupied {
        return None;
    }
    let mut best = vec![u32::MAX; w * h];
    let mut came = vec![usize::MAX; w * h];
    let mut closed = vec![false; w * h];
    // (f, h, cell index): ties broken by the heuristic, then the index — deterministic.
    let mut open = BinaryHeap::new();
    best[idx(s)] = 0;
    open.push(Reverse((heuristic(s, g), heuristic(s, g), idx(s))));
    while let Some(Reverse((_, _, i))) = open.pop() {
        if closed[i] {
            continue;
        }
        closed[i] = true;
        let c = ((i % w) as i64, (i / w) as i64);
        if c == g {
            let mut path = vec![(c.0 as usize, c.1 as usize)];
            let mut j = i;
            while came[j] != usize::MAX {
                j = came[j];
                path.push((j % w, j / w));
            }
            path.reverse();
            return Some((path, best[i]));
        }
        for (dx, dy) in [
            (1, 0),
            (-1, 0),
            (0, 1),
            (0, -1),
            (1, 1),
            (1, -1),
            (-1, 1),
            (-1, -1),
        ] {
            let n = (c.0 + dx, c.1 + dy);
            if grid.at(n.0, n.1) == Cell::Occupied {
                continue;
            }
            let diagonal = dx != 0 && dy != 0;
            if diagonal
                && (grid.at(c.0 + dx, c.1) == Cell::Occupied
                    || grid.at(c.0, c.1 + dy) == Cell::Occupied)
            {
                continue;
            }
            let step = if diagonal { DIAGONAL } else { STRAIGHT };
            let cost = best[i]
                .saturating_add(step)
                .saturating_add(grid.enter_cost(n.0, n.1));
            let ni = idx(n);
            if cost < best[ni] {
                best[ni] = cost;
                came[ni] = i;
                let hh = heuristic(n, g);
                open.push(Reverse((cost.saturating_add(hh), hh, ni)));
            }
        }
    }
    None
}

/// Answers requests and replans on map updates; see the module docs for the order it needs.
#[derive(Debug, Clone)]
pub struct Planner {
    grid: Option<(Grid, f64)>,
    next_map: u32,
    plans: u32,
    /// The cells of the last plan sent, for checking whether an update blocks it.
    last_path: Vec<(usize, usize)>,
    goal: (f64, f64),
}

impl Default for Planner {
    fn default() -> Self {
        Planner::new()
    }
}

impl Planner {
    pub fn new() -> Planner {
        Planner {
            grid: None,
            next_map: 0,
            plans: 0,
            last_path: Vec::new(),
            goal: (0.0, 0.0),
        }
    }

    /// Whether the map update the mapper sends next must be taken before the request of period
    /// `request_seq`.
    pub fn needs_map_before(&self, request_seq: u32) -> bool {
        request_seq >= self.next_map
    }

    /// Plans made so far.
    pub fn plans(&self) -> u32 {
        self.plans
    }

    /// Takes a map update; returns a new plan if the update blocks the last one.
    pub fn on_map(&mut self, m: &MapUpdate) -> Option<Waypoints> {
        self.next_map = m.next.max(m.seq.saturating_add(1));
        let grid = Grid {
            w: m.w as usize,
            h: m.h as usize,
            cells: m.cells.clone(),
        };
        let blocked = self.last_path.iter().any(|&(cx, cy)| {
            let (cx, cy) = (cx as i64, cy as i64);
            grid.at(cx, cy) == Cell::Occupied
        });
        self.grid = Some((grid, m.block));
        self.goal = (m.goal_x, m.goal_y);
        if blocked {
            self.plan(m.seq, PlanCause::Map, m.x, m.y)
        } else {
            None
        }
    }

    /// Takes a request; answers it with a plan if it asks for one and a path exists.
    pub fn on_request(&mut self, r: &Request) -> Option<Waypoints> {
        if !r.want {
            return None;
        }
        self.goal = (r.goal_x, r.goal_y);
        self.plan(r.seq, PlanCause::Request, r.x, r.y)
    }

    fn plan(&mut self, seq: u32, cause: PlanCause, x: f64, y: f64) -> Option<Waypoints> {
        let (grid, block) = self.grid.as_ref()?;
        let cell = |px: f64, py: f64| -> Option<(usize, usize)> {
            let (cx, cy) = ((px / block).floor(), (py / block).floor());
            (px.is_finite()
                && py.is_finite()
                && cx >= 0.0
                && cy >= 0.0
                && cx < grid.w as f64
                && cy < grid.h as f64)
                .then_some((cx as usize, cy as usize))
        };
        let start = cell(x, y)?;
        let goal = cell(self.goal.0, self.goal.1)?;
        let (path, _) = astar(grid, start, goal)
            .or_else(|| astar(&grid.unseen_from(x, y, *block, MAX_RANGE), start, goal))
            .or_else(|| astar(&grid.near_only(x, y, *block, NEAR), start, goal))?;
        let points = path
            .iter()
            .skip(1)
            .map(|&cell| centre(cell, *block))
            .collect();
        self.plans += 1;
        self.last_path = path;
        Some(Waypoints {
            plan: plan_id(seq, cause),
            seq,
            points,
        })
    }
}

/// What made the planner plan.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum PlanCause {
    Map,
    Request,
}

/// A plan's id, from the period it was made in, not from a count: a planner restarted with
/// its state lost must not number its plans from 1 again, or the navigator (which ignores
/// plans older than the one it follows) would ignore every one of them. In one period the map
/// update is taken before the request, so a request's plan gets the larger id. Never 0 ("no
/// plan yet").
fn plan_id(seq: u32, cause: PlanCause) -> u32 {
    let base = seq.saturating_mul(2);
    match cause {
        PlanCause::Map => base.saturating_add(1),
        PlanCause::Request => base.saturating_add(2),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn open_grid_shortest_paths_are_straight_or_diagonal() {
        let g = Grid::from_rows(&[".....", ".....", ".....", ".....", "....."]);
        let (p, cost) = astar(&g, (0, 0), (4, 0)).unwrap();
        assert_eq!(p, vec![(0, 0), (1, 0), (2, 0), (3, 0), (4, 0)]);
        assert_eq!(cost, 4 * STRAIGHT);
        let (p, cost) = astar(&g, (0, 0), (4, 4)).unwrap();
        assert_eq!(p.len(), 5, "a diagonal: {p:?}");
        assert_eq!(cost, 4 * DIAGONAL);
    }

    #[test]
    fn finds_the_way_around_a_wall_and_the_shortest_of_two() {
        // Rows top first. The wall in the middle column has gaps at the top and bottom; the
        // bottom one is nearer.
        let g = Grid::from_rows(&[
            ".......", //
            "...#...", "...#...", "...#...", "...#...", ".......",
        ]);
        let (p, _) = astar(&g, (0, 1), (6, 1)).unwrap();
        assert!(p
            .iter()
            .all(|&(x, y)| g.at(x as i64, y as i64) != Cell::Occupied));
        assert!(
            p.contains(&(3, 0)),
            "goes through the near (bottom) gap: {p:?}"
        );
        assert_eq!(*p.first().unwrap(), (0, 1));
        assert_eq!(*p.last().unwrap(), (6, 1));
    }

    #[test]
    fn exact_cost_on_a_known_corridor() {
        // A U-shaped free corridor in occupied rock: the only path has 8 straight steps.
        let g = Grid::from_rows(&[
            "#####", //
            "#...#", "#.#.#", "#.#.#", "#####",
        ]);
        let (p, cost) = astar(&g, (1, 1), (3, 1)).unwrap();
        assert_eq!(
            p,
            vec![(1, 1), (1, 2), (1, 3), (2, 3), (3, 3), (3, 2), (3, 1)]
        );
        // Every cell of this corridor touches rock: each step costs STRAIGHT + INFLATED_COST.
        assert_eq!(cost, 6 * (STRAIGHT + INFLATED_COST));
    }

    #[test]
    fn no_corner_cutting_and_unreachable_goals() {
        let g = Grid::from_rows(&[
            "..#", //
            "#..",
        ]);
        // (0,0) is the bottom-left '#'. From (0,1) to (1,0) diagonally would cut a corner.
        let (p, _) = astar(&g, (0, 1), (1, 0)).unwrap();
        assert_eq!(p, vec![(0, 1), (1, 1), (1, 0)]);
        let walled = Grid::from_rows(&["..#..", "..#..", "..#.."]);
        assert!(astar(&walled, (0, 0), (4, 0)).is_none());
        assert!(astar(&walled, (0, 0), (2, 0)).is_none(), "goal in a wall");
        assert!(astar(&walled, (0, 0), (9, 0)).is_none(), "goal outside");
    }

    #[test]
    fn unknown_is_planned_through_and_corridor_middles_are_preferred() {
        let g = Grid::from_rows(&["?????", "?????", "?????"]);
        assert_eq!(astar(&g, (0, 1), (4, 1)).unwrap().0.len(), 5);
        // A corridor three cells wide: the path keeps to the middle row.
        let g = Grid::from_rows(&[
            "#########", //
            ".........",
            ".........",
            ".........",
            "#########",
        ]);
        let (p, _) = astar(&g, (0, 2), (8, 2)).unwrap();
        assert!(p.iter().all(|&(_, y)| y == 2), "{p:?}");
    }

    /// An open 5 × 3 map (robot at the west end, goal at the east end) as update `seq 0`.
    fn open_map() -> MapUpdate {
        MapUpdate {
            seq: 0,
            next: 5,
            w: 5,
            h: 3,
            block: 1.0,
            x: 0.5,
            y: 1.5,
            goal_x: 4.5,
            goal_y: 1.5,
            cells: Grid::from_rows(&[".....", ".....", "....."]).cells,
        }
    }

    /// A request for a plan in period `seq`, from the robot's place on [`open_map`].
    fn request(seq: u32) -> Request {
        Request {
            seq,
            want: true,
            x: 0.5,
            y: 1.5,
            goal_x: 4.5,
            goal_y: 1.5,
        }
    }

    #[test]
    fn a_restarted_planner_numbers_its_plans_above_the_old_ones() {
        let m = open_map();
        let req = request;
        let mut old = Planner::new();
        old.on_map(&m);
        let before = old.on_request(&req(3)).unwrap().plan;
        // State lost: a fresh planner, later in the mission.
        let mut fresh = Planner::new();
        fresh.on_map(&m);
        let after = fresh.on_request(&req(4)).unwrap().plan;
        assert!(after > before, "{after} > {before}");
        assert!(plan_id(0, PlanCause::Map) > 0);
    }

    /// What the robot "sees" for the planner's fallbacks: blocks within range and not behind
    /// another occupied block.
    #[test]
    fn blocks_out_of_range_or_hidden_are_forgotten_first_and_all_but_the_nearest_last() {
        // 0.25 m blocks; the robot in block (0, 1). Walls at (1, 0) (0.35 m away), (5, 1)
        // (1.25 m), (6, 1) (behind the last) and (10, 1) (2.5 m: out of range).
        let g = Grid::from_rows(&[
            "............", //
            ".....##...#.",
            ".#..........",
        ]);
        let (x, y) = (0.125, 0.375);
        let kept = |g: &Grid| -> Vec<(usize, usize)> {
            (0..g.w * g.h)
                .map(|i| (i % g.w, i / g.w))
                .filter(|&(cx, cy)| g.at(cx as i64, cy as i64) == Cell::Occupied)
                .collect()
        };
        assert_eq!(
            kept(&g),
            vec![(1, 0), (5, 1), (6, 1), (10, 1)],
            "the map as drawn"
        );
        assert_eq!(
            kept(&g.unseen_from(x, y, 0.25, MAX_RANGE)),
            vec![(1, 0), (5, 1)]
        );
        assert_eq!(kept(&g.near_only(x, y, 0.25, NEAR)), vec![(1, 0)]);
    }

    /// A wall across the whole map whose only gap the mapper has marked occupied: the planner
    /// does not leave the robot without a plan, but keeps a wall right in front of it a wall,
    /// and takes any real way around first.
    #[test]
    fn a_map_without_a_way_to_the_goal_is_planned_through_where_the_robot_cannot_see() {
        let rows = ["..........#.", "..........#.", "..........#."];
        let mut m = MapUpdate {
            block: 0.25,
            w: 12,
            x: 0.125,
            y: 0.375,
            goal_x: 2.875,
            goal_y: 0.375,
            cells: Grid::from_rows(&rows).cells,
            ..open_map()
        };
        let at = |x: f64| Request {
            x,
            y: 0.375,
            goal_x: 2.875,
            goal_y: 0.375,
            ..request(1)
        };
        let mut p = Planner::new();
        p.on_map(&m);
        for x in [0.125, 1.125, 2.125] {
            let w = p
                .on_request(&at(x))
                .expect("a plan through the wall not in front");
            assert_eq!(*w.points.last().unwrap(), (2.875, 0.375));
        }
        // 0.375 m from the wall: it stays a wall (the navigator keeps the plan it has).
        assert_eq!(p.on_request(&at(2.25)), None);
        // A way around, even a long one, is taken before any occupied block.
        m.h = 4;
        m.cells = Grid::from_rows(&["............", rows[0], rows[1], rows[2]]).cells;
        p.on_map(&m);
        let w = p.on_request(&at(0.125)).unwrap();
        assert!(w.points.iter().any(|&(_, y)| y > 0.75), "{:?}", w.points);
    }

    #[test]
    fn planner_orders_inputs_and_replans_when_blocked() {
        let mut m = open_map();
        let mut p = Planner::new();
        assert!(p.needs_map_before(0));
        assert_eq!(p.on_map(&m), None);
        assert!(!p.needs_map_before(4) && p.needs_map_before(5));
        let req = request(1);
        let w = p.on_request(&req).unwrap();
        assert_eq!(
            w.plan, 4,
            "ids come from the period (1), a request's after a map's"
        );
        assert_eq!(*w.points.last().unwrap(), (4.5, 1.5));
        assert_eq!(p.on_request(&Request { want: false, ..req }), None);
        // An update that does not touch the path: no replan. One that does: a new plan.
        m.seq = 5;
        m.next = 10;
        m.cells = Grid::from_rows(&["#....", ".....", "....."]).cells;
        assert_eq!(p.on_map(&m), None);
        m.seq = 10;
        m.next = 15;
        m.cells = Grid::from_rows(&["#....", "..#..", "....."]).cells;
        let w = p.on_map(&m).expect("blocked path is replanned");
        assert_eq!((w.plan, w.seq), (21, 10));
    }
}
