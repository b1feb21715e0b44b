//! The simulated robot and its mission: a differential-drive disc in a [`World`], a ring of 16
//! range sensors, and the bookkeeping that decides the mission (goal, collision, time limit).
//!
//! Time is discrete: period `k` lasts `dt` simulated seconds. At the start of period `k` the
//! sim produces scan `k`; the command answering scan `k` (its `seq` is `k`) is in force for the
//! period if it arrived before the period's end, else the previous command stays in force and
//! the period counts as late. The pose is integrated in sub-steps, each checked for contact.
//! Nothing here reads a clock: the same seed and the same commands give the same trajectory.

use serde::{Deserialize, Serialize};

use crate::msg::{Cmd, Scan, Telemetry, RANGES};
use crate::world::{MazeSpec, World};
use s3res_protocol::rng::SplitMix64;

/// Everything that fixes a mission besides the commands.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SimConfig {
    pub maze: MazeSpec,
    /// Simulated seconds per period.
    pub dt: f64,
    /// Simulated seconds before the mission fails.
    pub time_limit_s: f64,
    /// Robot radius, metres.
    pub radius: f64,
    /// Sensor range, metres.
    pub max_range: f64,
    /// Fastest forward speed the drive accepts, m/s (commands are saturated to it).
    pub v_max: f64,
    /// Fastest turn the drive accepts, rad/s.
    pub w_max: f64,
    /// Chance, in per mille, that a range reading is an outlier (a spurious echo near the robot
    /// or a missed one at full range).
    pub outlier_per_mille: u32,
    /// Uniform noise on every range reading, ± metres.
    pub noise_m: f64,
    /// Distance to the goal that counts as reached, metres.
    pub goal_tolerance: f64,
}

impl SimConfig {
    pub fn new(seed: u64) -> SimConfig {
        SimConfig {
            maze: MazeSpec::new(seed),
            dt: 0.05,
            time_limit_s: 120.0,
            radius: 0.15,
            max_range: 2.0,
            v_max: 0.6,
            w_max: 2.5,
            outlier_per_mille: 20,
            noise_m: 0.01,
            goal_tolerance: 0.25,
        }
    }
}

/// How a mission ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Outcome {
    /// Still running.
    Running,
    Goal,
    Collision,
    TimeLimit,
    /// The controller went away (its command channel closed) and the sim was told to stop.
    Aborted,
}

/// The mission summary the sim writes as JSON (and `render` draws).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Summary {
    pub success: bool,
    pub outcome: Outcome,
    pub config: SimConfig,
    /// Control rate the mission ran at (periods per wall-clock second); 0 for an in-process run.
    pub hz: f64,
    pub periods: u32,
    /// Simulated seconds from start to the end of the mission.
    pub mission_time_s: f64,
    pub path_length_m: f64,
    pub collisions: u32,
    /// Periods whose command did not arrive in time (the previous one stayed in force).
    pub late_periods: u32,
    /// Plans followed after the first one.
    pub replans: u32,
    /// Wall-clock seconds the mission took (0 for an in-process run).
    pub wall_time_s: f64,
    /// Pose at the start of every period and at the end: `[x, y, theta]`.
    pub trajectory: Vec<[f64; 3]>,
}

/// The simulated robot in its world.
#[derive(Debug, Clone)]
pub struct Sim {
    pub world: World,
    pub cfg: SimConfig,
    pub x: f64,
    pub y: f64,
    pub theta: f64,
    /// Command in force.
    pub cmd: Cmd,
    seq: u32,
    outcome: Outcome,
    path_len: f64,
    late: u32,
    collisions: u32,
    replans: u32,
    last_plan: u32,
    noise: SplitMix64,
    trajectory: Vec<[f64; 3]>,
}

/// Sub-steps per period for integration and contact checks.
const SUBSTEPS: u32 = 10;

fn finite_or_zero(v: f64) -> f64 {
    if v.is_finite() {
        v
    } else {
        0.0
    }
}

impl Sim {
    pub fn new(cfg: SimConfig) -> Sim {
        let world = World::generate(cfg.maze);
        let (x, y) = world.start();
        // Facing north-east, towards the goal's corner.
        let theta = std::f64::consts::FRAC_PI_4;
        Sim {
            world,
            cfg,
            x,
            y,
            theta,
            cmd: Cmd {
                seq: 0,
                v: 0.0,
                w: 0.0,
                plan: 0,
            },
            seq: 0,
            outcome: Outcome::Running,
            path_len: 0.0,
            late: 0,
            collisions: 0,
            replans: 0,
            last_plan: 0,
            noise: SplitMix64::new(cfg.maze.seed ^ 0x5e45_0a5e_5e45_0a5e),
            trajectory: vec![[x, y, theta]],
        }
    }

    /// The current period.
    pub fn seq(&self) -> u32 {
        self.seq
    }

    pub fn outcome(&self) -> Outcome {
        self.outcome
    }

    pub fn is_running(&self) -> bool {
        self.outcome == Outcome::Running
    }

    /// The scan of the current period: true ranges with the configured noise and outliers.
    pub fn scan(&mut self) -> Scan {
        let mut ranges = [0.0; RANGES];
        for (i, r) in ranges.iter_mut().enumerate() {
            let a = self.theta + i as f64 * std::f64::consts::TAU / RANGES as f64;
            let truth = self.world.raycast(self.x, self.y, a, self.cfg.max_range);
            let u = self.noise.unit();
            let roll = self.noise.below(1000);
            let value = if roll < self.cfg.outlier_per_mille as u64 / 2 {
                // Spurious echo close to the robot.
                0.05 + 0.1 * u
            } else if roll < self.cfg.outlier_per_mille as u64 {
                self.cfg.max_range
            } else {
                truth + (2.0 * u - 1.0) * self.cfg.noise_m
            };
            *r = value.clamp(0.0, self.cfg.max_range);
        }
        let (gx, gy) = self.world.goal();
        Scan {
            seq: self.seq,
            grid_w: self.world.side as u16,
            grid_h: self.world.side as u16,
            block: self.world.spec.block,
            x: self.x,
            y: self.y,
            theta: self.theta,
            goal_x: gx,
            goal_y: gy,
            ranges,
        }
    }

    /// The telemetry of the current period.
    pub fn telemetry(&self) -> Telemetry {
        Telemetry {
            seq: self.seq,
            x: self.x,
            y: self.y,
            theta: self.theta,
            v: self.cmd.v,
            w: self.cmd.w,
        }
    }

    /// Ends the current period: `cmd` is the freshest command that came during it (`None`: no
    /// new command, the previous one stays in force). The period is late unless `cmd` answers
    /// this period's scan; a command answering an earlier scan, which came late, still replaces
    /// an older one in force. Integrates the pose and decides the mission.
    pub fn step(&mut self, cmd: Option<Cmd>) -> Outcome {
        if !self.is_running() {
            return self.outcome;
        }
        if !matches!(cmd, Some(c) if c.seq == self.seq) {
            self.late += 1;
        }
        if let Some(c) = cmd {
            self.cmd = Cmd {
                seq: c.seq,
                v: finite_or_zero(c.v).clamp(-self.cfg.v_max, self.cfg.v_max),
                w: finite_or_zero(c.w).clamp(-self.cfg.w_max, self.cfg.w_max),
                plan: c.plan,
            };
            if c.plan != self.last_plan {
                if self.last_plan != 0 {
                    self.replans += 1;
                }
                self.last_plan = c.plan;
            }
        }
        let h = self.cfg.dt / SUBSTEPS as f64;
        for _ in 0..SUBSTEPS {
            let (x0, y0) = (self.x, self.y);
            // Exact for constant v over the sub-step with the heading at its middle.
            let mid = self.theta + self.cmd.w * h / 2.0;
            self.x += self.cmd.v * h * mid.cos();
            self.y += self.cmd.v * h * mid.sin();
            self.theta = wrap_angle(self.theta + self.cmd.w * h);
            self.path_len += ((self.x - x0).powi(2) + (self.y - y0).powi(2)).sqrt();
            if self.world.disc_hits_wall(self.x, self.y, self.cfg.radius) {
                self.collisions += 1;
                self.outcome = Outcome::Collision;
                break;
            }
        }
        self.seq += 1;
        self.trajectory.push([self.x, self.y, self.theta]);
        if self.outcome == Outcome::Running {
            let (gx, gy) = self.world.goal();
            if ((self.x - gx).powi(2) + (self.y - gy).powi(2)).sqrt() <= self.cfg.goal_tolerance {
                self.outcome = Outcome::Goal;
            } else if self.time() >= self.cfg.time_limit_s - 1e-9 {
                self.outcome = Outcome::TimeLimit;
            }
        }
        self.outcome
    }

    /// Simulated seconds elapsed.
    pub fn time(&self) -> f64 {
        self.seq as f64 * self.cfg.dt
    }

    /// Stops a running mission as aborted (the controller is gone).
    pub fn abort(&mut self) {
        if self.is_running() {
            self.outcome = Outcome::Aborted;
        }
    }

    pub fn summary(&self, hz: f64, wall_time_s: f64) -> Summary {
        Summary {
            success: self.outcome == Outcome::Goal,
            outcome: self.outcome,
            config: self.cfg,
            hz,
            periods: self.seq,
            mission_time_s: self.time(),
            path_length_m: self.path_len,
            collisions: self.collisions,
            late_periods: self.late,
            replans: self.replans,
            wall_time_s,
            trajectory: self.trajectory.clone(),
        }
    }
}

/// `a` wrapped into (-π, π].
pub fn wrap_angle(a: f64) -> f64 {
    let tau = std::f64::consts::TAU;
    let mut a = a % tau;
    if a > std::f64::consts::PI {
        a -= tau;
    } else if a <= -std::f64::consts::PI {
        a += tau;
    }
    a
}

impl Summary {
    /// The one-line summary the sim prints at the end.
    pub fn line(&self) -> String {
        format!(
            "mission {}: {:?} seed={} time={:.1}s path={:.2}m periods={} late={} collisions={} replans={} wall={:.1}s",
            if self.success { "succeeded" } else { "FAILED" },
            self.outcome,
            self.config.maze.seed,
            self.mission_time_s,
            self.path_length_m,
            self.periods,
            self.late_periods,
            self.collisions,
            self.replans,
            self.wall_time_s,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn driving_straight_into_a_wall_is_a_collision() {
        let mut sim = Sim::new(SimConfig::new(1));
        sim.theta = std::f64::consts::PI; // west: the outer wall, 0.375 m away
        let cmd = Cmd {
            seq: 0,
            v: 0.5,
            w: 0.0,
            plan: 0,
        };
        let mut outcome = Outcome::Running;
        for _ in 0..20 {
            outcome = sim.step(Some(cmd));
            if outcome != Outcome::Running {
                break;
            }
        }
        assert_eq!(outcome, Outcome::Collision);
        assert_eq!(sim.summary(0.0, 0.0).collisions, 1);
        // About 0.375 - 0.15 = 0.225 m travelled.
        assert!((sim.summary(0.0, 0.0).path_length_m - 0.225).abs() < 0.05);
    }

    #[test]
    fn a_missing_command_keeps_the_last_and_counts_late() {
        let mut sim = Sim::new(SimConfig::new(1));
        let cmd = Cmd {
            seq: 0,
            v: 0.0,
            w: 1.0,
            plan: 1,
        };
        sim.step(Some(cmd));
        let t1 = sim.theta;
        sim.step(None);
        assert!((wrap_angle(sim.theta - t1) - sim.cfg.dt).abs() < 1e-9);
        let s = sim.summary(0.0, 0.0);
        assert_eq!((s.late_periods, s.periods), (1, 2));
        // The answer to scan 1 arrives during period 2: it replaces the command in force, and
        // period 2 is late all the same.
        sim.step(Some(Cmd {
            seq: 1,
            w: -1.0,
            ..cmd
        }));
        assert_eq!(sim.cmd.w, -1.0);
        assert_eq!(sim.summary(0.0, 0.0).late_periods, 2);
        // Garbage commands are saturated, NaN is stopped.
        sim.step(Some(Cmd {
            seq: 3,
            v: f64::NAN,
            w: 1e300,
            plan: 2,
        }));
        assert_eq!(sim.cmd.v, 0.0);
        assert_eq!(sim.cmd.w, sim.cfg.w_max);
        assert_eq!(sim.summary(0.0, 0.0).replans, 1);
    }

    #[test]
    fn time_limit_ends_the_mission() {
        let mut cfg = SimConfig::new(1);
        cfg.time_limit_s = 1.0;
        let mut sim = Sim::new(cfg);
        let mut n = 0;
        while sim.step(None) == Outcome::Running {
            n += 1;
        }
        assert_eq!(n, (1.0 / sim.cfg.dt).round() as usize - 1);
        assert_eq!(sim.outcome(), Outcome::TimeLimit);
    }

    #[test]
    fn scans_are_deterministic_and_in_range() {
        let mut a = Sim::new(SimConfig::new(9));
        let mut b = Sim::new(SimConfig::new(9));
        for _ in 0..50 {
            let (sa, sb) = (a.scan(), b.scan());
            assert_eq!(sa, sb);
            assert!(sa.ranges.iter().all(|r| (0.0..=2.0).contains(r)));
            a.step(None);
            b.step(None);
        }
    }
}
