//! One mission in one process, and what its map called a wall where the world has none (a
//! *ghost* block):
//!
//!     cargo run --release -p s3res-robot --example ghost_trace -- MAZE RUN DELAY [PERIOD ...]
//!
//! flies the maze of seed MAZE with plans up to DELAY periods late (delay seed 7919·RUN + 1, as
//! `delay_sweep` numbers its runs; time limit 240 s), prints the map against the world at each
//! map update of the PERIODs given (updates come every 5 periods), and at the end how many
//! blocks were ghosts, and in how many of the map updates. In the picture: `#` a wall the map
//! has, `+` a wall it does not know yet, `!` a wall it calls free, `G` a ghost, `.` free, a
//! blank unknown, `R` the robot; north is up.

use std::collections::BTreeMap;

use s3res_robot::mission::{ghost_blocks, run_watched, Controllers, MapUpdated};
use s3res_robot::msg::Cell;
use s3res_robot::sim::SimConfig;

fn picture(u: &MapUpdated) -> String {
    let (sim, side) = (u.sim, u.sim.world.side);
    let b = sim.world.spec.block;
    let robot = ((sim.x / b) as usize, (sim.y / b) as usize);
    let mut out = format!(
        "period {}: robot at ({:.2}, {:.2}), block {:?}, heading {:.2}\n",
        sim.seq(),
        sim.x,
        sim.y,
        robot,
        sim.theta
    );
    for cy in (0..side).rev() {
        for cx in 0..side {
            let wall = sim.world.is_wall(cx as i64, cy as i64);
            out.push(match (wall, u.mapper.cell(cx, cy)) {
                _ if (cx, cy) == robot => 'R',
                (true, Cell::Occupied) => '#',
                (true, Cell::Free) => '!',
                (true, Cell::Unknown) => '+',
                (false, Cell::Occupied) => 'G',
                (false, Cell::Free) => '.',
                (false, Cell::Unknown) => ' ',
            });
        }
        out.push('\n');
    }
    out
}

fn main() {
    let args: Result<Vec<u64>, _> = std::env::args().skip(1).map(|a| a.parse()).collect();
    let (maze, run, delay, periods) = match args.as_deref() {
        Ok([m, r, d, p @ ..]) => (*m, *r, *d, p.to_vec()),
        _ => {
            eprintln!(
                "usage: ghost_trace MAZE RUN DELAY [PERIOD ...] (whole numbers; see the source)"
            );
            std::process::exit(2);
        }
    };
    let mut cfg = SimConfig::new(maze);
    cfg.time_limit_s = 240.0;
    let ctl = Controllers {
        plan_delay_max: delay.try_into().unwrap_or(u32::MAX),
        plan_delay_seed: run * 7919 + 1,
        ..Controllers::default()
    };
    // Per ghost block, the map updates that had it.
    let mut ghosts: BTreeMap<(usize, usize), u32> = BTreeMap::new();
    let mut updates = 0u32;
    let summary = run_watched(cfg, ctl, |u| {
        updates += 1;
        for block in ghost_blocks(u.sim, u.mapper) {
            *ghosts.entry(block).or_default() += 1;
        }
        if periods.contains(&u64::from(u.sim.seq())) {
            print!("{}", picture(u));
        }
    });
    println!("{}", summary.line());
    let more_than = |n: u32| ghosts.values().filter(|&&k| k > n).count();
    println!(
        "ghost blocks: {} in some of the {updates} map updates, {} in more than 50, {} in more than 700",
        ghosts.len(),
        more_than(50),
        more_than(700)
    );
}
