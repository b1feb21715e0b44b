//! The navigator: local navigation by artificial potential fields towards the current waypoint.
//!
//! The planner's path is followed with a look-ahead: the target is the first waypoint at least
//! [`NavParams::lookahead`] ahead of the robot (the last one near the end). The target attracts
//! with a constant pull; every beam shorter than [`NavParams::influence`] repels, with the
//! classic `k·(1/r − 1/d0)/r²` law, away from where it hit. The robot turns towards the sum of
//! the forces and drives forward only as much as it faces it and has room in front.
//!
//! Once per period (per scan) it produces one [`Cmd`] and one [`Request`] — exactly one frame on
//! each output, as a reactive round expects. Waypoints arrive on their own input without a
//! round; the component must take every waypoint frame already delivered before it handles the
//! next scan (see `docs/maze-robot.md`), which makes its outputs a function of the input
//! sequence alone.

use crate::mapper::SAW_NOTHING_FROM;
use crate::msg::{Cmd, Request, Scan, Waypoints, RANGES};
use crate::sim::wrap_angle;

/// Tuning of the navigator.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NavParams {
    pub v_max: f64,
    pub w_max: f64,
    /// Turn-rate gain on the heading error, 1/s.
    pub k_turn: f64,
    /// Distance ahead on the path to steer for, metres.
    pub lookahead: f64,
    /// Beams shorter than this repel, metres.
    pub influence: f64,
    /// Strength of the repulsion.
    pub k_rep: f64,
    /// Distance from the path that makes the navigator ask for a new plan, metres.
    pub off_path: f64,
    /// Periods to wait for an answer before asking again.
    pub request_every: u32,
    /// Periods after which a plan is asked for again even if the robot is on its path: a
    /// planner restarted with its state lost no longer knows the path it sent, so it cannot
    /// replan when the map blocks it; this bounds how long a stale plan is followed.
    pub refresh_every: u32,
    /// The robot's radius, metres (for the room in front).
    pub radius: f64,
    /// Seconds the robot must be able to keep its command without reaching a wall ahead: a
    /// command may stay in force for several periods when the next ones are late.
    pub stale_horizon: f64,
}

impl Default for NavParams {
    fn default() -> Self {
        NavParams {
            v_max: 0.6,
            w_max: 2.5,
            k_turn: 3.0,
            lookahead: 0.45,
            influence: 0.45,
            k_rep: 0.04,
            off_path: 0.6,
            request_every: 10,
            refresh_every: 100,
            radius: 0.15,
            stale_horizon: 0.8,
        }
    }
}

/// The navigator's state: the plan it follows and when it last asked for one.
#[derive(Debug, Clone)]
pub struct Navigator {
    p: NavParams,
    path: Vec<(f64, f64)>,
    plan: u32,
    /// The period the followed plan was made in.
    plan_seq: Option<u32>,
    last_request: Option<u32>,
}

impl Navigator {
    pub fn new(p: NavParams) -> Navigator {
        Navigator {
            p,
            path: Vec::new(),
            plan: 0,
            plan_seq: None,
            last_request: None,
        }
    }

    /// The plan being followed (0: none yet).
    pub fn plan(&self) -> u32 {
        self.plan
    }

    /// Takes a plan; older plans than the one followed are ignored.
    pub fn on_waypoints(&mut self, w: &Waypoints) {
        if w.plan > self.plan {
            self.plan = w.plan;
            self.plan_seq = Some(w.seq);
            self.path.clear();
            self.path.extend(
                w.points
                    .iter()
                    .filter(|(x, y)| x.is_finite() && y.is_finite()),
            );
        }
    }

    /// One control period: the command for the sim and the word for the planner.
    pub fn on_scan(&mut self, s: &Scan) -> (Cmd, Request) {
        let (x, y) = (s.x, s.y);
        let dist = |p: &(f64, f64)| ((p.0 - x).powi(2) + (p.1 - y).powi(2)).sqrt();

        // Drop the waypoints behind the one nearest to the robot (look near the front only,
        // so a path that loops back past the robot is not cut short).
        let window = self.path.len().min(12);
        if let Some((nearest, _)) = self.path[..window]
            .iter()
            .enumerate()
            .min_by(|a, b| dist(a.1).total_cmp(&dist(b.1)))
        {
            self.path.drain(..nearest);
        }
        let off_path = match self.path.first() {
            Some(p) => dist(p) > self.p.off_path,
            None => true,
        };
        let target = self
            .path
            .iter()
            .find(|p| dist(p) >= self.p.lookahead)
            .or(self.path.last())
            .copied();
        let near_end = self.path.len() <= 1 && self.path.first().is_some_and(|p| dist(p) < 0.2);
        let goal_dist = ((s.goal_x - x).powi(2) + (s.goal_y - y).powi(2)).sqrt();

        // Ask for a plan when there is none, the robot strayed, the path ran out short of the
        // goal, or the plan is `refresh_every` periods old; not more often than every
        // `request_every` periods.
        let stale = self
            .plan_seq
            .is_some_and(|made| s.seq.wrapping_sub(made) >= self.p.refresh_every);
        let need = self.path.is_empty() || off_path || (near_end && goal_dist > 0.3) || stale;
        let due = match self.last_request {
            Some(r) => s.seq.wrapping_sub(r) >= self.p.request_every,
            None => true,
        };
        let want = need && due;
        if want {
            self.last_request = Some(s.seq);
        }
        let request = Request {
            seq: s.seq,
            want,
            x,
            y,
            goal_x: s.goal_x,
            goal_y: s.goal_y,
        };

        let (v, w) = match target {
            Some(t) => self.steer(s, t),
            // No plan yet: stand still and wait for one.
            None => (0.0, 0.0),
        };
        (
            Cmd {
                seq: s.seq,
                v,
                w,
                plan: self.plan,
            },
            request,
        )
    }

    /// Potential-field steering towards `target`.
    fn steer(&self, s: &Scan, target: (f64, f64)) -> (f64, f64) {
        let (dx, dy) = (target.0 - s.x, target.1 - s.y);
        let d = (dx * dx + dy * dy).sqrt();
        let (mut fx, mut fy) = if d > 1e-9 {
            (dx / d, dy / d)
        } else {
            (0.0, 0.0)
        };
        let mut front: f64 = f64::INFINITY;
        let mut ahead: f64 = f64::INFINITY;
        for (i, &r) in s.ranges.iter().enumerate() {
            let a = s.theta + i as f64 * std::f64::consts::TAU / RANGES as f64;
            if i <= 2 || i >= RANGES - 2 {
                front = front.min(r);
            }
            if i <= 1 || i >= RANGES - 1 {
                ahead = ahead.min(r);
            }
            if r < self.p.influence {
                let r = r.max(0.05);
                let push = self.p.k_rep * (1.0 / r - 1.0 / self.p.influence) / (r * r);
                fx -= push * a.cos();
                fy -= push * a.sin();
            }
        }
        let heading = fy.atan2(fx);
        let err = wrap_angle(heading - s.theta);
        let w = (self.p.k_turn * err).clamp(-self.p.w_max, self.p.w_max);
        let facing = err.cos().max(0.0);
        let room = ((front - self.p.radius - 0.05) / 0.3).clamp(0.0, 1.0);
        let mut v = self.p.v_max * facing * facing * room;
        if err.abs() > std::f64::consts::FRAC_PI_3 {
            v = 0.0;
        }
        // Slow down on the last metre so the goal is not overshot.
        if d < 0.5 {
            v = v.min(0.2 + d);
        }
        // Safe if it stays in force: no wall ahead within `stale_horizon` at this speed, and the
        // arc it drives for that long keeps clear of every echo.
        v = v.min(((ahead - self.p.radius - 0.05) / self.p.stale_horizon).max(0.0));
        for _ in 0..4 {
            if self.arc_is_clear(s, v, w) {
                return (v, w);
            }
            v *= 0.5;
        }
        (0.0, w)
    }

    /// Whether driving `(v, w)` for `stale_horizon` seconds keeps the robot's body clear of every
    /// point where a beam hit, with a margin. Robot frame: the robot at the origin facing +x.
    fn arc_is_clear(&self, s: &Scan, v: f64, w: f64) -> bool {
        const STEPS: u32 = 10;
        let clearance = self.p.radius + 0.04;
        let h = self.p.stale_horizon / STEPS as f64;
        let (mut x, mut y, mut th) = (0.0f64, 0.0f64, 0.0f64);
        for _ in 0..STEPS {
            x += v * h * th.cos();
            y += v * h * th.sin();
            th += w * h;
            for (i, &r) in s.ranges.iter().enumerate() {
                if r >= SAW_NOTHING_FROM {
                    continue; // nothing seen on this beam
                }
                let a = i as f64 * std::f64::consts::TAU / RANGES as f64;
                let (px, py) = (r * a.cos(), r * a.sin());
                if (px - x).powi(2) + (py - y).powi(2) < clearance * clearance {
                    return false;
                }
            }
        }
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scan_at(x: f64, y: f64, theta: f64, ranges: [f64; RANGES]) -> Scan {
        Scan {
            seq: 0,
            grid_w: 40,
            grid_h: 40,
            block: 0.25,
            x,
            y,
            theta,
            goal_x: 9.0,
            goal_y: 0.0,
            ranges,
        }
    }

    #[test]
    fn without_obstacles_it_drives_straight_at_the_waypoint() {
        let mut nav = Navigator::new(NavParams::default());
        let s = scan_at(0.0, 0.0, 0.0, [2.0; RANGES]);
        let (cmd, req) = nav.on_scan(&s);
        assert_eq!((cmd.v, cmd.w), (0.0, 0.0), "no plan yet: wait");
        assert!(req.want, "and ask for one");
        nav.on_waypoints(&Waypoints {
            plan: 1,
            seq: 0,
            points: vec![(0.25, 0.0), (1.0, 0.0), (2.0, 0.0)],
        });
        let (cmd, req) = nav.on_scan(&Scan { seq: 11, ..s });
        assert!(!req.want);
        assert!((cmd.v - 0.6).abs() < 1e-9 && cmd.w.abs() < 1e-9, "{cmd:?}");
        assert_eq!(cmd.plan, 1);
    }

    #[test]
    fn the_field_steers_around_an_obstacle() {
        let mut nav = Navigator::new(NavParams::default());
        nav.on_waypoints(&Waypoints {
            plan: 1,
            seq: 0,
            points: vec![(2.0, 0.0)],
        });
        // An obstacle close on the front-left (beams 1 and 2, at +22.5° and +45°).
        let mut r = [2.0; RANGES];
        r[1] = 0.25;
        r[2] = 0.3;
        let (cmd, _) = nav.on_scan(&scan_at(0.0, 0.0, 0.0, r));
        assert!(cmd.w < -0.1, "turns right, away from it: {cmd:?}");
        // The same on the right: turns left.
        let mut r = [2.0; RANGES];
        r[15] = 0.25;
        r[14] = 0.3;
        let (cmd, _) = nav.on_scan(&scan_at(0.0, 0.0, 0.0, r));
        assert!(cmd.w > 0.1, "turns left: {cmd:?}");
        // A wall right in front: it does not drive into it.
        let mut r = [2.0; RANGES];
        r[0] = 0.2;
        let (cmd, _) = nav.on_scan(&scan_at(0.0, 0.0, 0.0, r));
        assert!(cmd.v < 0.05, "{cmd:?}");
    }

    #[test]
    fn commands_stay_safe_if_they_stay_in_force() {
        let p = NavParams::default();
        let mut nav = Navigator::new(p);
        nav.on_waypoints(&Waypoints {
            plan: 1,
            seq: 0,
            points: vec![(0.25, 0.0), (3.0, 0.0)],
        });
        // A wall 0.6 m ahead: the robot may not drive so fast that the command, kept for
        // `stale_horizon`, would take it into the wall.
        let mut r = [2.0; RANGES];
        r[0] = 0.6;
        r[1] = 0.6 / (std::f64::consts::PI / 8.0).cos();
        r[15] = r[1];
        let (cmd, _) = nav.on_scan(&scan_at(0.0, 0.0, 0.0, r));
        assert!(cmd.v > 0.0, "{cmd:?}");
        assert!(cmd.v * p.stale_horizon <= 0.6 - p.radius, "{cmd:?}");
        // An echo right where the arc would go: it slows down or stops.
        let mut r = [2.0; RANGES];
        r[1] = 0.35;
        let (cmd, _) = nav.on_scan(&scan_at(0.0, 0.0, 0.0, r));
        let clear = (0.35f64 - p.radius) / p.stale_horizon;
        assert!(cmd.v <= clear, "{cmd:?}");
    }

    #[test]
    fn a_corridor_keeps_it_in_the_middle() {
        let mut nav = Navigator::new(NavParams::default());
        nav.on_waypoints(&Waypoints {
            plan: 1,
            seq: 0,
            points: vec![(1.0, 0.1), (3.0, 0.1)],
        });
        // Walls at y = ±0.375; the robot is at y = 0.2, close to the left wall: the beam at
        // +90° (index 4) sees it at 0.175, the one at -90° (index 12) at 0.575.
        let mut r = [2.0; RANGES];
        r[3] = 0.175 / (3.0f64 * std::f64::consts::PI / 8.0).sin();
        r[4] = 0.175;
        r[5] = r[3];
        r[12] = 0.575;
        let (cmd, _) = nav.on_scan(&scan_at(0.0, 0.2, 0.0, r));
        assert!(cmd.w < 0.0, "pushed back to the middle: {cmd:?}");
    }

    #[test]
    fn old_plans_are_ignored_and_requests_are_rate_limited() {
        let mut nav = Navigator::new(NavParams::default());
        nav.on_waypoints(&Waypoints {
            plan: 2,
            seq: 0,
            points: vec![(1.0, 0.0)],
        });
        nav.on_waypoints(&Waypoints {
            plan: 1,
            seq: 0,
            points: vec![(5.0, 5.0)],
        });
        assert_eq!(nav.plan(), 2);
        // Far off the path: asks, then waits `request_every` periods before asking again.
        let mut asked = Vec::new();
        for seq in 0..25 {
            let (_, req) = nav.on_scan(&Scan {
                seq,
                ..scan_at(5.0, 5.0, 0.0, [2.0; RANGES])
            });
            if req.want {
                asked.push(seq);
            }
        }
        assert_eq!(asked, vec![0, 10, 20]);
    }

    #[test]
    fn a_plan_is_asked_for_again_when_it_gets_old() {
        let p = NavParams::default();
        let mut nav = Navigator::new(p);
        nav.on_waypoints(&Waypoints {
            plan: 7,
            seq: 50,
            points: vec![(0.1, 0.0), (0.5, 0.0), (1.0, 0.0), (3.0, 0.0)],
        });
        // On the path: no request until the plan is `refresh_every` periods old.
        let at = |seq| Scan {
            seq,
            ..scan_at(0.1, 0.0, 0.0, [2.0; RANGES])
        };
        assert!(!nav.on_scan(&at(51)).1.want);
        assert!(!nav.on_scan(&at(50 + p.refresh_every - 1)).1.want);
        assert!(nav.on_scan(&at(50 + p.refresh_every)).1.want);
    }
}
