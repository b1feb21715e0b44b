//! The picture of a mission: the maze, start and goal, and one or two trajectories, as SVG
//! text written by hand (no font, no library).
//!
//! The first trajectory is drawn blue (e.g. the golden run), the second one red and dashed (the
//! faulted run), as in MAVFI's Figure 13. A mission that ended on a collision has a cross where
//! it ended.

use std::fmt::Write;

use crate::sim::{Outcome, Summary};
use crate::world::World;

/// Pixels per metre.
const SCALE: f64 = 60.0;

/// Renders `first` (and `second`, if given, on the same maze) as an SVG document.
pub fn render(first: &Summary, second: Option<&Summary>) -> String {
    let world = World::generate(first.config.maze);
    let size = world.size_m() * SCALE;
    let b = world.spec.block * SCALE;
    // y grows upwards in the world and downwards in SVG.
    let px = |x: f64| x * SCALE;
    let py = |y: f64| size - y * SCALE;
    let mut s = String::new();
    let _ = writeln!(
        s,
        r#"<svg xmlns="http://www.w3.org/2000/svg" width="{size:.0}" height="{size:.0}" viewBox="0 0 {size:.1} {size:.1}">"#
    );
    let _ = writeln!(s, r##"<rect width="100%" height="100%" fill="#ffffff"/>"##);
    let _ = writeln!(s, r##"<g fill="#333333">"##);
    for by in 0..world.side {
        // One rectangle per run of wall blocks in a row keeps the file small.
        let mut bx = 0;
        while bx < world.side {
            if world.is_wall(bx as i64, by as i64) {
                let start = bx;
                while bx < world.side && world.is_wall(bx as i64, by as i64) {
                    bx += 1;
                }
                let _ = writeln!(
                    s,
                    r#"<rect x="{:.1}" y="{:.1}" width="{:.1}" height="{:.1}"/>"#,
                    start as f64 * b,
                    size - (by + 1) as f64 * b,
                    (bx - start) as f64 * b,
                    b
                );
            } else {
                bx += 1;
            }
        }
    }
    let _ = writeln!(s, "</g>");
    let (sx, sy) = world.start();
    let (gx, gy) = world.goal();
    let _ = writeln!(
        s,
        r##"<circle cx="{:.1}" cy="{:.1}" r="{:.1}" fill="#2ca02c"/>"##,
        px(sx),
        py(sy),
        0.12 * SCALE
    );
    let _ = writeln!(
        s,
        r##"<circle cx="{:.1}" cy="{:.1}" r="{:.1}" fill="none" stroke="#2ca02c" stroke-width="3"/>"##,
        px(gx),
        py(gy),
        first.config.goal_tolerance * SCALE
    );
    let mut draw = |sum: &Summary, colour: &str, dash: &str| {
        let mut points = String::new();
        for p in &sum.trajectory {
            let _ = write!(points, "{:.1},{:.1} ", px(p[0]), py(p[1]));
        }
        let _ = writeln!(
            s,
            r#"<polyline points="{}" fill="none" stroke="{colour}" stroke-width="2.5" stroke-linejoin="round"{dash}/>"#,
            points.trim_end()
        );
        if sum.outcome == Outcome::Collision {
            if let Some(last) = sum.trajectory.last() {
                let (x, y, r) = (px(last[0]), py(last[1]), 0.15 * SCALE);
                let _ = writeln!(
                    s,
                    r#"<path d="M{:.1},{:.1}L{:.1},{:.1}M{:.1},{:.1}L{:.1},{:.1}" stroke="{colour}" stroke-width="4"/>"#,
                    x - r,
                    y - r,
                    x + r,
                    y + r,
                    x - r,
                    y + r,
                    x + r,
                    y - r
                );
            }
        }
    };
    draw(first, "#1f77b4", "");
    if let Some(second) = second {
        draw(second, "#d62728", r#" stroke-dasharray="8 5""#);
    }
    let _ = writeln!(s, "</svg>");
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mission::{run_in_process, Controllers};
    use crate::sim::SimConfig;

    #[test]
    fn the_picture_has_the_maze_and_both_trajectories() {
        let golden = run_in_process(SimConfig::new(1), Controllers::default());
        let mut faulted = golden.clone();
        faulted.outcome = Outcome::Collision;
        faulted.trajectory.truncate(20);
        let svg = render(&golden, Some(&faulted));
        assert!(svg.starts_with("<svg"));
        assert!(svg.trim_end().ends_with("</svg>"));
        assert_eq!(svg.matches("<polyline").count(), 2);
        assert!(svg.contains("stroke-dasharray"));
        assert!(svg.contains("<path d=\"M"), "collision cross");
        assert!(svg.matches("<rect").count() > 20, "walls");
    }
}
