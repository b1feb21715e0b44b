//! Anomaly detectors on the component's outputs, and frame capture for training them.
//!
//! One [`s3res_anomaly::Detector`] per monitored output, made at start-up (every buffer is
//! allocated then); every replica's answer frame on that output is observed once, as it
//! arrives, without allocating. What an alarm *does* is the voter's business (see
//! [`crate::reactive`], [`crate::stream`] and `docs/anomaly-detection.md`): this module keeps the detectors, their
//! last verdicts, and the streams in step with recoveries.

use std::fs::File;
use std::io::{BufWriter, Write};

use s3res_anomaly::model::DetectorModel;
use s3res_anomaly::{Cause, Detector, Model, Verdict};

use crate::clock::Instant;
use crate::core::VoterError;
use crate::plan::VoterPlan;

/// A detector on one output.
struct Monitor {
    detector: Detector,
    /// Per replica: the verdict on its latest frame on this output.
    last: Box<[Option<Verdict>]>,
}

/// The detectors of a component, indexed by output.
pub(crate) struct Monitors {
    by_output: Vec<Option<Monitor>>,
    /// Frames observed and the time spent in `observe`, on the voter's clock (logged at the
    /// end: the detector's cost per frame inside the voter).
    observed: u64,
    busy: std::time::Duration,
}

/// What an alarm is about, for the `anomaly` event.
pub(crate) struct Alarm {
    pub(crate) field: Option<String>,
    pub(crate) score: Option<f64>,
    pub(crate) threshold: f64,
    pub(crate) cause: &'static str,
}

impl Monitors {
    /// Loads every monitored output's model and checks it against the declared fields.
    pub(crate) fn load(plan: &VoterPlan) -> Result<Monitors, VoterError> {
        let mut by_output: Vec<Option<Monitor>> = plan.outputs.iter().map(|_| None).collect();
        for m in &plan.monitors {
            let plan_err =
                |what: String| VoterError::Plan(format!("output `{}`: {what}", m.output));
            let Some(o) = plan.outputs.iter().position(|p| p.name == m.output) else {
                return Err(plan_err("is not an output of the component".into()));
            };
            if by_output[o].is_some() {
                return Err(plan_err("has two detectors".into()));
            }
            let mut model = Model::load(&m.model).map_err(|e| plan_err(e.to_string()))?;
            model
                .check_layout(&m.fields)
                .map_err(|e| plan_err(e.to_string()))?;
            if let Some(t) = m.threshold {
                if !(t.is_finite() && t > 0.0) {
                    return Err(plan_err(format!("threshold {t} must be a positive number")));
                }
                match &mut model.detector {
                    DetectorModel::Gaussian(g) => g.n_sigma = t,
                    DetectorModel::Autoencoder(a) => a.threshold = t,
                }
            }
            let detector =
                Detector::new(&model, plan.replicas).map_err(|e| plan_err(e.to_string()))?;
            by_output[o] = Some(Monitor {
                detector,
                last: vec![None; plan.replicas].into_boxed_slice(),
            });
        }
        Ok(Monitors {
            by_output,
            observed: 0,
            busy: std::time::Duration::ZERO,
        })
    }

    pub(crate) fn is_empty(&self) -> bool {
        self.by_output.iter().all(Option::is_none)
    }

    /// Scores replica `r`'s frame on output `o`; `None` if `o` is not monitored. No allocation.
    pub(crate) fn observe(&mut self, r: usize, o: usize, frame: &[u8]) -> Option<Verdict> {
        let m = self.by_output.get_mut(o)?.as_mut()?;
        let start = Instant::now();
        let v = m.detector.observe(r, frame);
        self.busy += Instant::now().saturating_duration_since(start);
        self.observed += 1;
        m.last[r] = Some(v);
        Some(v)
    }

    /// Whether replica `r`'s latest frame on `o` alarmed.
    pub(crate) fn alarmed(&self, r: usize, o: usize) -> bool {
        self.verdict(r, o).is_some_and(|v| v.alarm)
    }

    fn verdict(&self, r: usize, o: usize) -> Option<Verdict> {
        self.by_output.get(o)?.as_ref()?.last.get(r).copied()?
    }

    /// The specifics of replica `r`'s latest verdict on `o`, for an event.
    pub(crate) fn alarm(&self, r: usize, o: usize) -> Option<Alarm> {
        let m = self.by_output.get(o)?.as_ref()?;
        let v = m.last.get(r).copied()??;
        Some(Alarm {
            field: v.field.map(|i| m.detector.field_name(i).to_owned()),
            score: v.score.is_finite().then_some(v.score),
            threshold: v.threshold,
            cause: match v.cause {
                Cause::Normal | Cause::Warmup => "normal",
                Cause::Deviation => "the change of the field is beyond what the model learned",
                Cause::NonFinite => "the field is NaN or infinite",
                Cause::ShortFrame => "the frame is shorter than the monitored fields",
            },
        })
    }

    /// Forgets every verdict (a new round begins).
    pub(crate) fn clear_verdicts(&mut self) {
        for m in self.by_output.iter_mut().flatten() {
            m.last.fill(None);
        }
    }

    /// Logs how many frames were observed and the mean time per frame.
    pub(crate) fn log_cost(&self) {
        if self.observed > 0 {
            tracing::info!(
                frames = self.observed,
                mean_ns = self.busy.as_nanos() as u64 / self.observed,
                "anomaly detectors: frames observed and mean time per frame (timer included)"
            );
        }
    }

    /// Slot `to` was replaced by a fork of `from`: its streams continue `from`'s. The verdict
    /// on the old process's last frame is forgotten.
    pub(crate) fn copy_stream(&mut self, from: usize, to: usize) {
        for m in self.by_output.iter_mut().flatten() {
            m.detector.copy_stream(from, to);
            m.last[to] = None;
        }
    }

    /// Slot `slot` was restarted by exec: its next frames are warm-ups.
    pub(crate) fn reset_stream(&mut self, slot: usize) {
        for m in self.by_output.iter_mut().flatten() {
            m.detector.reset_stream(slot);
            m.last[slot] = None;
        }
    }
}

/// Voted frames of some outputs, written to files in the s3res framing.
pub(crate) struct Captures {
    by_output: Vec<Option<(BufWriter<File>, String)>>,
}

impl Captures {
    pub(crate) fn open(plan: &VoterPlan) -> Result<Captures, VoterError> {
        let mut by_output: Vec<Option<(BufWriter<File>, String)>> =
            plan.outputs.iter().map(|_| None).collect();
        for c in &plan.captures {
            let Some(o) = plan.outputs.iter().position(|p| p.name == c.output) else {
                return Err(VoterError::Plan(format!(
                    "capture of `{}`: not an output of the component",
                    c.output
                )));
            };
            let file = File::create(&c.path).map_err(crate::core::io_err(format!(
                "creating capture file {}",
                c.path.display()
            )))?;
            by_output[o] = Some((
                BufWriter::with_capacity(64 * 1024, file),
                c.path.display().to_string(),
            ));
        }
        Ok(Captures { by_output })
    }

    /// Appends `frame` (a voted frame of output `o`) to its capture file, if it has one.
    /// A write error stops that capture (said once); the component carries on.
    pub(crate) fn record(&mut self, o: usize, frame: &[u8]) {
        let Some(Some((w, path))) = self.by_output.get_mut(o) else {
            return;
        };
        let len = (frame.len() as u32).to_le_bytes();
        if let Err(e) = w.write_all(&len).and_then(|()| w.write_all(frame)) {
            tracing::warn!(path = %path, error = %e, "capture failed; no more frames are captured");
            self.by_output[o] = None;
        }
    }

    /// Writes out what is buffered.
    pub(crate) fn flush(&mut self) {
        for (w, path) in self.by_output.iter_mut().flatten() {
            if let Err(e) = w.flush() {
                tracing::warn!(path = %path, error = %e, "capture could not be written");
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn plan(mode: &str, output: &str) -> VoterPlan {
        let json = format!(
            r#"{{"system":"s","component":"c","exec":"/bin/true","args":[],"replicas":2,
            "timeout_us":1000,"inputs":[{{"name":"in","fd":3,"max_frame":64}}],
            "outputs":[{{"name":"out","fd":4,"max_frame":64}}],"rounds":[],"events_fd":null,
            "socket_path":"/tmp/x.sock","mode":"{mode}",
            "monitors":[{{"output":"{output}","fields":[{{"name":"x","type":"f64","offset":0}}],
                          "model":"/nonexistent/model.json"}}]}}"#
        );
        VoterPlan::from_json(&json).unwrap()
    }

    #[test]
    fn bad_monitors_are_refused_before_anything_runs() {
        let err = |p: &VoterPlan| Monitors::load(p).err().unwrap().to_string();
        assert!(err(&plan("stream", "nope")).contains("`nope`: is not an output"));
        assert!(err(&plan("reactive", "nope")).contains("`nope`: is not an output"));
        let e = err(&plan("reactive", "out"));
        assert!(
            e.contains("cannot read model /nonexistent/model.json"),
            "{e}"
        );
        // Stream mode runs detectors too: the plan is valid, only the model is missing.
        crate::core::validate(&plan("stream", "out")).unwrap();
        let e = err(&plan("stream", "out"));
        assert!(e.contains("cannot read model"), "{e}");
    }
}
