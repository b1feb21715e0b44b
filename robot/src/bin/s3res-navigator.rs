//! `s3res-navigator`: local navigation by potential fields. See `--help`.

#![forbid(unsafe_code)]

use anyhow::{Context, Result};
use clap::Parser;
use replica_rt::{wait_any, TryRecv};
use s3res_robot::component::{drain, optional_input, Downstream};
use s3res_robot::msg::{Cmd, Request, Scan, Waypoints};
use s3res_robot::navigator::{NavParams, Navigator};

/// The robot's navigator (reactive): for every cleaned scan on input `sensors` it sends one
/// velocity command on `cmd` and one word to the planner on `request` (asking for a plan or
/// not) — exactly one frame on each, so a reactive round is
/// `{"input": "sensors", "outputs": ["cmd", "request"]}`.
///
/// It steers by artificial potential fields: the waypoint --lookahead metres ahead on the
/// current plan attracts, walls closer than --influence metres repel. Plans arrive on input
/// `waypoints` without a round; before it handles a scan the navigator takes every plan already
/// delivered, so its answers depend on the order of its inputs only, never on timing: replicas
/// agree byte for byte.
///
/// A frame on `sensors` that is not a scan is answered with a stop command and no request
/// (logged).
#[derive(Parser)]
#[command(name = "s3res-navigator", version, verbatim_doc_comment)]
struct Cli {
    /// Fastest forward speed commanded, m/s.
    #[arg(long, default_value_t = NavParams::default().v_max)]
    v_max: f64,
    /// Distance ahead on the path to steer for, metres.
    #[arg(long, default_value_t = NavParams::default().lookahead)]
    lookahead: f64,
    /// Walls closer than this repel, metres.
    #[arg(long, default_value_t = NavParams::default().influence)]
    influence: f64,
}

fn main() -> Result<()> {
    replica_rt::init_logging("navigator");
    let cli = Cli::parse();
    let params = NavParams {
        v_max: cli.v_max,
        lookahead: cli.lookahead,
        influence: cli.influence,
        ..NavParams::default()
    };
    let mut rt = replica_rt::init().context("starting the s3res runtime")?;
    let mut sensors = rt.input("sensors").context("opening input sensors")?;
    let mut waypoints = optional_input(&mut rt, "waypoints")?;
    let mut cmd_out = Downstream::new(Some(rt.output("cmd").context("opening output cmd")?));
    let mut request_out = Downstream::new(Some(
        rt.output("request").context("opening output request")?,
    ));
    let mut nav = Navigator::new(params);
    let mut buf = Vec::with_capacity(128);
    let mut periods = 0u64;
    let take_plans = |port: &mut Option<replica_rt::InPort>, nav: &mut Navigator| -> Result<()> {
        if let Some(p) = port.as_mut() {
            let open = drain(p, |frame| match Waypoints::decode(frame) {
                Ok(w) => nav.on_waypoints(&w),
                Err(e) => tracing::warn!(error = %e, "not a plan; skipped"),
            })?;
            if !open {
                *port = None;
            }
        }
        Ok(())
    };
    loop {
        let ready = match waypoints.as_ref() {
            Some(w) => wait_any(&[&sensors, w], None),
            None => wait_any(&[&sensors], None),
        }
        .context("waiting for input")?;
        if ready.is_ready(1) {
            take_plans(&mut waypoints, &mut nav)?;
        }
        if !ready.is_ready(0) {
            continue;
        }
        // Plans delivered before this scan are in the pipe already: take them all first.
        take_plans(&mut waypoints, &mut nav)?;
        let (cmd, request) = match sensors.try_recv().context("receiving a scan")? {
            TryRecv::Frame(frame) => match Scan::decode(frame) {
                Ok(scan) => nav.on_scan(&scan),
                Err(e) => {
                    tracing::warn!(error = %e, "not a scan; answering with a stop");
                    stop(nav.plan())
                }
            },
            TryRecv::Empty => continue,
            TryRecv::Closed => break,
        };
        cmd.encode(&mut buf);
        cmd_out.send(&buf)?;
        request.encode(&mut buf);
        request_out.send(&buf)?;
        periods += 1;
    }
    tracing::info!(periods, plan = nav.plan(), "end of input");
    Ok(())
}

/// The answer to a frame that is not a scan: stand still, ask for nothing. Its `seq` matches no
/// period, so the sim counts the period late.
fn stop(plan: u32) -> (Cmd, Request) {
    (
        Cmd {
            seq: u32::MAX,
            v: 0.0,
            w: 0.0,
            plan,
        },
        Request {
            seq: u32::MAX,
            want: false,
            x: 0.0,
            y: 0.0,
            goal_x: 0.0,
            goal_y: 0.0,
        },
    )
}
