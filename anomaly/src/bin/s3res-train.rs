//! `s3res-train`: learns an anomaly-detection model from fault-free frames.

#![forbid(unsafe_code)]

use anyhow::{bail, Context, Result};
use clap::{Args, Parser, Subcommand, ValueEnum};
use s3res_anomaly::capture::{for_each_frame, write_frames};
use s3res_anomaly::model::DEFAULT_N_SIGMA;
use s3res_anomaly::network::Sgd;
use s3res_anomaly::stats::DEFAULT_SIGMA_FLOOR_REL;
use s3res_anomaly::synthetic::{robot_layout, Robot};
use s3res_anomaly::train::DEFAULT_MARGIN;
use s3res_anomaly::{
    AutoencoderConfig, Detector, FieldLayout, FloatRepr, Model, Preprocess, Trainer,
};
use std::path::{Path, PathBuf};

/// Learn an anomaly-detection model for one s3res output channel from fault-free frames.
///
/// Frames come from files in the s3res framing (4-byte little-endian length, then the
/// payload), as captured from a channel; each file is one stream, and deltas are taken between
/// consecutive frames of a stream. The layout file names the numeric fields to monitor, as a
/// JSON array: [{"name":"x","type":"f64","offset":8}, ...] (types f64 f32 i64 u64 i32 u32 i16
/// u16 i8 u8, little-endian).
///
/// Typical use:
///
///   s3res-train gaussian    --layout L.json --frames run1.bin --frames run2.bin --out g.json
///
///   s3res-train autoencoder --layout L.json --frames run1.bin --out ae.json --seed 1
///
///   s3res-train check --model ae.json --frames held-out.bin   (false alarms on fault-free data)
///
/// See docs/anomaly-detection.md.
#[derive(Parser)]
#[command(name = "s3res-train", version, verbatim_doc_comment)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Per-field Gaussian model of each field's change: alarm beyond --sigmas σ.
    Gaussian {
        #[command(flatten)]
        input: Input,
        /// Alarm when a field's change is more than this many σ from its mean.
        #[arg(long, default_value_t = DEFAULT_N_SIGMA)]
        sigmas: f64,
    },
    /// Dense autoencoder over all fields: alarm when the reconstruction error exceeds the
    /// threshold (--margin × the largest error on the training frames).
    Autoencoder {
        #[command(flatten)]
        input: Input,
        /// Seed of the weight initialisation and batch order (the run is deterministic).
        #[arg(long, default_value_t = 0)]
        seed: u64,
        #[arg(long, default_value_t = Sgd::default().epochs)]
        epochs: usize,
        #[arg(long, default_value_t = Sgd::default().batch)]
        batch: usize,
        #[arg(long, default_value_t = Sgd::default().learning_rate)]
        learning_rate: f64,
        /// Hidden layer widths, comma-separated (default: ⌊n/2⌋,⌊n/4⌋ for n fields, MAVFI's
        /// 13 → 6 → 3 → 13).
        #[arg(long, value_delimiter = ',')]
        hidden: Option<Vec<usize>>,
        /// Threshold = margin × the largest reconstruction error seen in training (≥ 1).
        #[arg(long, default_value_t = DEFAULT_MARGIN)]
        margin: f64,
    },
    /// Runs a model over frame files and reports alarms (on fault-free frames: false alarms).
    Check {
        #[arg(long)]
        model: PathBuf,
        /// Frame file (repeat for more streams).
        #[arg(long = "frames", required = true)]
        frames: Vec<PathBuf>,
        #[arg(long, default_value_t = replica_rt::frame::DEFAULT_MAX_FRAME)]
        max_frame: usize,
    },
    /// Writes synthetic robot telemetry (13 fields) and its layout, to try the tools out.
    Synthetic {
        #[arg(long, default_value_t = 0)]
        seed: u64,
        #[arg(long, default_value_t = 10_000)]
        count: usize,
        /// Frame file to write.
        #[arg(long)]
        out: PathBuf,
        /// Layout file to write.
        #[arg(long)]
        layout_out: PathBuf,
    },
}

#[derive(Args)]
struct Input {
    /// JSON layout of the monitored fields.
    #[arg(long)]
    layout: PathBuf,
    /// Fault-free frame file, one stream (repeat for more streams).
    #[arg(long = "frames", required = true)]
    frames: Vec<PathBuf>,
    /// Where to write the model (JSON).
    #[arg(long)]
    out: PathBuf,
    /// Feed float fields as their value, or only their sign and exponent bits.
    #[arg(long, value_enum, default_value_t = Floats::Value)]
    floats: Floats,
    /// Score the fields' values instead of their change from the previous frame.
    #[arg(long)]
    values: bool,
    /// σ floor relative to a float field's largest training magnitude.
    #[arg(long, default_value_t = DEFAULT_SIGMA_FLOOR_REL)]
    sigma_floor: f64,
    /// The channel's maximum frame size: longer length prefixes are errors.
    #[arg(long, default_value_t = replica_rt::frame::DEFAULT_MAX_FRAME)]
    max_frame: usize,
}

#[derive(Clone, Copy, ValueEnum)]
enum Floats {
    Value,
    SignExponent,
}

fn main() {
    replica_rt::init_cli_logging(false, 0);
    if let Err(e) = run(Cli::parse()) {
        eprintln!("s3res-train: {e:#}");
        std::process::exit(1);
    }
}

fn run(cli: Cli) -> Result<()> {
    match cli.command {
        Command::Gaussian { input, sigmas } => {
            let trainer = ingest(&input)?;
            let model = trainer.gaussian(sigmas, input.sigma_floor)?;
            save(&model, &input.out)?;
            say_training_alarms(&model, &input, "--sigmas")
        }
        Command::Autoencoder {
            input,
            seed,
            epochs,
            batch,
            learning_rate,
            hidden,
            margin,
        } => {
            let trainer = ingest(&input)?;
            let config = AutoencoderConfig {
                hidden,
                sgd: Sgd {
                    epochs,
                    batch,
                    learning_rate,
                },
                seed,
                margin,
                sigma_floor_rel: input.sigma_floor,
            };
            tracing::info!(seed, epochs, "training the autoencoder");
            let model = trainer.autoencoder(&config)?;
            if let s3res_anomaly::model::DetectorModel::Autoencoder(a) = &model.detector {
                tracing::info!(
                    first_loss = a.training.first_loss,
                    final_loss = a.training.final_loss,
                    max_error = a.training.max_error,
                    threshold = a.threshold,
                    "trained"
                );
            }
            save(&model, &input.out)?;
            say_training_alarms(&model, &input, "--margin")
        }
        Command::Check {
            model,
            frames,
            max_frame,
        } => check(&model, &frames, max_frame),
        Command::Synthetic {
            seed,
            count,
            out,
            layout_out,
        } => {
            let frames = Robot::new(seed).frames(count);
            write_frames(&out, frames.iter().map(|f| &f[..]))
                .with_context(|| format!("cannot write {}", out.display()))?;
            let layout = serde_json::to_string_pretty(&robot_layout())?;
            std::fs::write(&layout_out, layout + "\n")
                .with_context(|| format!("cannot write {}", layout_out.display()))?;
            println!(
                "wrote {count} frames (seed {seed}) to {} and their layout to {}",
                out.display(),
                layout_out.display()
            );
            Ok(())
        }
    }
}

/// Reads a layout file: a JSON array of fields, or an object with a `fields` array (a channel
/// entry of a system description).
fn read_layout(path: &Path, max_frame: usize) -> Result<FieldLayout> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("cannot read layout {}", path.display()))?;
    let layout =
        FieldLayout::from_json(&text).with_context(|| format!("layout {}", path.display()))?;
    layout
        .within(max_frame)
        .with_context(|| format!("layout {}", path.display()))?;
    Ok(layout)
}

fn ingest(input: &Input) -> Result<Trainer> {
    let layout = read_layout(&input.layout, input.max_frame)?;
    let preprocess = Preprocess {
        delta: !input.values,
        floats: match input.floats {
            Floats::Value => FloatRepr::Value,
            Floats::SignExponent => FloatRepr::SignExponent,
        },
    };
    let min_frame = layout.min_frame();
    let mut trainer = Trainer::new(layout, preprocess);
    for path in &input.frames {
        trainer.begin_stream();
        let count = for_each_frame(path, input.max_frame, |frame| {
            // Short frames are counted by the trainer and reported below.
            let _ = trainer.push(frame);
        })?;
        tracing::info!(file = %path.display(), frames = count, "read");
    }
    if trainer.short > 0 || trainer.non_finite > 0 {
        tracing::warn!(
            short = trainer.short,
            non_finite = trainer.non_finite,
            "skipped frames that are too short for the layout or hold NaN/Inf"
        );
    }
    if trainer.frames > 0 && trainer.short == trainer.frames {
        bail!(
            "every frame is shorter than the layout needs ({} bytes): wrong layout or wrong file?",
            min_frame
        );
    }
    Ok(trainer)
}

fn save(model: &Model, out: &Path) -> Result<()> {
    model.save(out)?;
    println!("wrote {} model to {}", model.kind(), out.display());
    Ok(())
}

/// A model's alarms over frame files.
struct Alarms {
    frames: u64,
    alarms: u64,
    worst: f64,
    threshold: f64,
}

impl Alarms {
    fn per_10000(&self) -> f64 {
        self.alarms as f64 * 1e4 / self.frames.max(1) as f64
    }
}

/// Runs `model` over `files` (each one stream), printing a line per alarm if `print`.
fn alarms_over(model: &Model, files: &[PathBuf], max_frame: usize, print: bool) -> Result<Alarms> {
    let mut detector = Detector::new(model, 1)?;
    let (mut frames, mut alarms, mut worst) = (0u64, 0u64, 0.0f64);
    for path in files {
        detector.reset_stream(0);
        for_each_frame(path, max_frame, |frame| {
            let verdict = detector.observe(0, frame);
            frames += 1;
            worst = worst.max(verdict.score);
            if verdict.alarm {
                alarms += 1;
                if print {
                    let field = verdict.field.map_or("-", |i| detector.field_name(i));
                    println!(
                        "alarm: {} frame {} score {:.4} (threshold {:.4}) field {} ({:?})",
                        path.display(),
                        frames,
                        verdict.score,
                        verdict.threshold,
                        field,
                        verdict.cause
                    );
                }
            }
        })?;
    }
    Ok(Alarms {
        frames,
        alarms,
        worst,
        threshold: detector.threshold(),
    })
}

/// Above this share of its own fault-free training frames flagged, a model is said unusable.
const TRAINING_ALARMS_AT_MOST: f64 = 0.01;

/// Says how often the model just trained alarms on its own training frames, and warns when it
/// is more than [`TRAINING_ALARMS_AT_MOST`]: `--sigmas 0.01` (or `1e-300`) was accepted and
/// wrote a model that calls most normal frames faults, without a word until a run restarted
/// replicas for it.
fn say_training_alarms(model: &Model, input: &Input, knob: &str) -> Result<()> {
    let a = alarms_over(model, &input.frames, input.max_frame, false)?;
    if a.frames == 0 {
        // Read once already (a pipe, `<(zcat …)`): nothing to say, rather than "0 frames".
        return Ok(());
    }
    println!(
        "on its {} training frames it alarms on {} ({:.2} per 10000)",
        a.frames,
        a.alarms,
        a.per_10000()
    );
    if a.alarms as f64 > a.frames as f64 * TRAINING_ALARMS_AT_MOST {
        tracing::warn!(
            "this model flags {:.1} % of its own fault-free training frames: it will call normal \
             frames faults; give a larger {knob}",
            a.alarms as f64 * 100.0 / a.frames.max(1) as f64
        );
    }
    Ok(())
}

fn check(model_path: &Path, files: &[PathBuf], max_frame: usize) -> Result<()> {
    let model = Model::load(model_path)?;
    let a = alarms_over(&model, files, max_frame, true)?;
    println!(
        "{} model: {} frames, {} alarms ({:.2} per 10000), highest score {:.4}, threshold {:.4}",
        model.kind(),
        a.frames,
        a.alarms,
        a.per_10000(),
        a.worst,
        a.threshold
    );
    Ok(())
}
