//! # s3res-robot
//!
//! The maze-robot control system of s3res (after the S³RES paper's evaluation): a simulator that
//! is also the benchmarker, and the control components it drives, each a real algorithm.
//!
//! | module | component | algorithm |
//! |---|---|---|
//! | [`world`], [`sim`] | `s3res-sim` | seeded maze, differential drive, 16 range sensors, mission verdict |
//! | [`filter`] | `s3res-sensor-filter` | per-beam running median |
//! | [`navigator`] | `s3res-navigator` | artificial potential fields towards a look-ahead waypoint |
//! | [`mapper`] | `s3res-mapper` | log-odds occupancy grid |
//! | [`planner`] | `s3res-planner` | A* on the occupancy grid, replanning when blocked |
//! | [`load`] | `s3res-load` | fixed CPU-bound work per tick |
//! | — | `s3res-logger` | records pose and speed |
//!
//! [`msg`] defines every frame; [`mission`] runs a whole mission in one process (the golden run);
//! [`svg`] draws a mission. Every algorithm is a deterministic function of its inputs — no
//! clock, no randomness outside the simulator's seeded world, no hash-map order — so replicas
//! produce byte-identical frames. See `docs/maze-robot.md`.

#![forbid(unsafe_code)]

pub mod component;
pub mod filter;
pub mod load;
pub mod mapper;
pub mod mission;
pub mod msg;
pub mod navigator;
pub mod planner;
pub mod sim;
pub mod svg;
pub mod world;
