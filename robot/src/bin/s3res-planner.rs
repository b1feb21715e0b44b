//! `s3res-planner`: A* on the occupancy grid. See `--help`.

#![forbid(unsafe_code)]

use std::collections::VecDeque;

use anyhow::{Context, Result};
use clap::Parser;
use replica_rt::{wait_any, TryRecv};
use s3res_robot::component::{drain, Downstream};
use s3res_robot::msg::{MapUpdate, Request};
use s3res_robot::planner::Planner;

/// The robot's planner (written for stream mode): plans with A* on the mapper's occupancy grid
/// from the robot to the goal, answers the navigator's requests (input `request`) with a plan
/// on output `waypoints`, and replans on its own when a map update (input `map`) blocks the
/// plan it last sent.
///
/// It takes its two inputs in period order — the map update of period v before the request of
/// any period k ≥ v, waiting for that update when it has not arrived — so that its plans depend
/// on its inputs only, never on which pipe happened to be read first: replicas agree.
///
/// When the map ends (the mission is over) it closes `waypoints` at once, then reads both
/// inputs to their end. Frames of the wrong type are skipped (logged).
#[derive(Parser)]
#[command(name = "s3res-planner", version, verbatim_doc_comment)]
struct Cli {}

fn main() -> Result<()> {
    replica_rt::init_logging("planner");
    let _cli = Cli::parse();
    let mut rt = replica_rt::init().context("starting the s3res runtime")?;
    let mut requests = rt.input("request").context("opening input request")?;
    let mut maps = rt.input("map").context("opening input map")?;
    let mut waypoints = Downstream::new(Some(
        rt.output("waypoints").context("opening output waypoints")?,
    ));
    let mut planner = Planner::new();
    let mut buf = Vec::new();
    // Map updates read ahead of the request that needs them, in arrival order (= seq order).
    let mut pending: VecDeque<MapUpdate> = VecDeque::new();
    let mut maps_open = true;
    let take_map = |frame: &[u8], pending: &mut VecDeque<MapUpdate>| match MapUpdate::decode(frame)
    {
        Ok(update) => pending.push_back(update),
        Err(e) => tracing::warn!(error = %e, "not a map update; skipped"),
    };
    loop {
        // Watch the map too: its end (the mission's) must be seen while no request comes, so
        // that `waypoints` closes without waiting for `request` to end.
        let ready = if maps_open {
            wait_any(&[&requests, &maps], None)
        } else {
            wait_any(&[&requests], None)
        }
        .context("waiting for input")?;
        if maps_open && ready.is_ready(1) {
            maps_open = drain(&mut maps, |f| take_map(f, &mut pending))?;
        }
        if !maps_open && pending.is_empty() {
            // No map any more: the mission is over. Let the navigator finish.
            break;
        }
        if !ready.is_ready(0) {
            continue;
        }
        let request = match requests.try_recv().context("receiving a request")? {
            TryRecv::Frame(frame) => match Request::decode(frame) {
                Ok(r) => r,
                Err(e) => {
                    tracing::warn!(error = %e, "not a request; skipped");
                    continue;
                }
            },
            TryRecv::Empty => continue,
            TryRecv::Closed => break,
        };
        // Every map update up to this request's period comes first, waiting for it if need be.
        while planner.needs_map_before(request.seq) {
            let update = match pending.pop_front() {
                Some(u) => u,
                None if maps_open => match maps.recv().context("receiving a map update")? {
                    Some(frame) => {
                        take_map(frame, &mut pending);
                        continue;
                    }
                    None => {
                        maps_open = false;
                        break;
                    }
                },
                None => break,
            };
            if let Some(plan) = planner.on_map(&update) {
                plan.encode(&mut buf);
                waypoints.send(&buf)?;
            }
        }
        if planner.needs_map_before(request.seq) {
            // The map ended before this period's update: the mission is over.
            break;
        }
        if let Some(plan) = planner.on_request(&request) {
            plan.encode(&mut buf);
            waypoints.send(&buf)?;
        }
    }
    waypoints.close();
    // Read both inputs to their end, so nobody upstream writes into a closed pipe.
    while requests.recv().context("receiving a request")?.is_some() {}
    while maps_open && maps.recv().context("receiving a map update")?.is_some() {}
    tracing::info!(plans = planner.plans(), "end of input");
    Ok(())
}
