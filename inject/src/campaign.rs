//! A campaign: run the system N times with a schedule of injections, match each run's
//! injections with its voters' events, and write the records, the summary and the tables.

use std::collections::BTreeSet;
use std::io::{IsTerminal as _, Write as _};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{bail, Context as _};
use indicatif::{ProgressBar, ProgressStyle};

use replica_rt::machine::LoadAverage;

use crate::outcome::{match_run, Fired, Outcome};
use crate::report::{self, CampaignInfo, CampaignOutput, InjectionRecord, RunRecord, Summary};
use crate::runner::{run_once, RunResult, RunSetup};
use crate::schedule::{plan_run, run_seed, ScheduleParams};
use crate::scratch::ScratchDir;
use crate::stop::StopSignals;

/// How to run a campaign, beyond what `campaign.json` records.
#[derive(Debug, Clone)]
pub struct CampaignRun {
    pub info: CampaignInfo,
    pub bootstrap: PathBuf,
    pub out: PathBuf,
    /// Keep every run's folder (events, state, stdout, stderr) under `OUT/runs/`.
    pub keep_runs: bool,
    /// Continue the campaign `out` holds (same parameters): run only its missing runs.
    pub resume: bool,
    pub ready_limit: Duration,
}

impl CampaignRun {
    pub fn schedule_params(&self) -> ScheduleParams {
        schedule_params(&self.info)
    }
}

/// The schedule parameters recorded in `info`.
pub fn schedule_params(info: &CampaignInfo) -> ScheduleParams {
    ScheduleParams {
        fault: info.fault,
        rate_hz: info.rate_hz,
        arrival: info.arrival,
        window: Duration::from_millis(info.window_ms),
        components: info.components.clone(),
        var: info.var.clone(),
    }
}

/// Runs the campaign (or its shard) and writes its outputs into `c.out`. Returns the summary
/// and, if a stop signal cut it short, that signal (the outputs then hold the completed runs).
/// With `c.resume`, a folder that already holds this campaign keeps the runs it completed and
/// only the missing ones are run.
pub fn run(c: &CampaignRun, stop: &StopSignals) -> anyhow::Result<(Summary, Option<i32>)> {
    crate::scratch::check_out(&c.out, crate::scratch::OutKind::Campaign)?;
    std::fs::create_dir_all(&c.out)
        .with_context(|| format!("cannot create the output folder {}", c.out.display()))?;
    let _lock = crate::scratch::lock_and_sweep(&c.out)?;
    let (info, mut all_runs, mut all_inj) = prepare(c)?;
    if let Err(e) = replica_rt::sys::set_child_subreaper() {
        tracing::warn!(
            "cannot become a child subreaper ({e}): processes of a run whose parent died are \
             still killed, but reaped by init instead of by this process"
        );
    }
    let append = |name: &str| {
        std::fs::OpenOptions::new()
            .append(true)
            .open(c.out.join(name))
            .with_context(|| format!("cannot open {}", c.out.join(name).display()))
    };
    let mut inj_file = append("injections.jsonl")?;
    let mut runs_file = append("runs.jsonl")?;

    let params = c.schedule_params();
    let done: BTreeSet<u64> = all_runs.iter().map(|r| r.run).collect();
    let indices: Vec<u64> = c.info.run_indices().filter(|r| !done.contains(r)).collect();
    if !done.is_empty() {
        eprintln!(
            "s3res-inject: resuming: {} run(s) already done in {}, {} to go",
            done.len(),
            c.out.display(),
            indices.len()
        );
    }
    let mut progress = Progress::new(indices.len() as u64, &c.info);
    let stamp = std::process::id();
    let mut warned_missing = false;
    for &r in &indices {
        let schedule = plan_run(&params, c.info.seed, r).context("the injection schedule")?;
        let (dir, _tmp) = run_dir(c, r)?;
        let setup = RunSetup {
            bootstrap: c.bootstrap.clone(),
            system: c.info.system.clone(),
            dir: dir.clone(),
            mark: format!("{stamp}-{}-{r}", c.info.seed),
            targets: c.info.components.clone(),
            pick: c.info.pick,
            reg: c.info.reg.clone(),
            limit: Duration::from_millis(c.info.run_limit_ms),
            ready_limit: c.ready_limit,
        };
        let load_before = LoadAverage::now();
        let result = run_once(&setup, &schedule, &|| stop.requested().is_some());
        let load_after = LoadAverage::now();
        if result.interrupted {
            eprintln!(
                "s3res-inject: stopped by signal during run {}; that run is discarded, the {} \
                 completed run(s) are kept (the same command with --resume runs the rest)",
                r + 1,
                all_runs.len()
            );
            break;
        }
        let (mut run_rec, inj) = records(&c.info, r, &dir, &result);
        if let (Some(file), false) = (&c.info.task_summary, warned_missing) {
            if task_summary_missing(&dir, Some(file)) && ended_clean(&result) {
                warned_missing = true;
                tracing::warn!(
                    "run {} left no task summary {file} in its folder, so it counts as failed \
                     (said once; runs.jsonl's `error` says it of each run): is --task-summary \
                     the file the task writes?",
                    r + 1
                );
            }
        }
        run_rec.load_before = load_before;
        run_rec.load_after = load_after;
        let never_started = never_started(&result, &dir);
        if run_rec.error.is_none() {
            run_rec.error.clone_from(&never_started);
        }
        inj_file.write_all(report::jsonl(&inj)?.as_bytes())?;
        runs_file.write_all(report::jsonl(std::slice::from_ref(&run_rec))?.as_bytes())?;
        progress.run_done(&run_rec, &inj);
        all_runs.push(run_rec);
        all_inj.extend(inj);
        if let Some(why) = never_started {
            progress.finish();
            drop((inj_file, runs_file));
            let done = all_runs.len();
            write(c, info, all_runs, all_inj)?;
            bail!(
                "run {} never started its system, so the campaign stopped ({done} run(s) \
                 written to {}): {why}",
                r + 1,
                c.out.display()
            );
        }
    }
    progress.finish();
    drop((inj_file, runs_file));
    let summary = write(c, info, all_runs, all_inj)?;
    Ok((summary, stop.requested()))
}

/// The files of a campaign's output folder.
pub(crate) const OUTPUT_FILES: [&str; 5] = [
    "campaign.json",
    "injections.jsonl",
    "runs.jsonl",
    "summary.json",
    "table.md",
];

/// Prepares `c.out` and returns the parameters to record with the runs already done. A new
/// campaign writes its `campaign.json` and empty records. With `--resume`, a folder holding the
/// same campaign (the same parameters; the machine may differ) keeps its completed runs (a run
/// that never started its system is run again) with their injections, and its `campaign.json`
/// (the first start's machine and build).
fn prepare(
    c: &CampaignRun,
) -> anyhow::Result<(CampaignInfo, Vec<RunRecord>, Vec<InjectionRecord>)> {
    let found = if c.resume {
        CampaignOutput::read_partial(&c.out).map_err(anyhow::Error::msg)?
    } else {
        None
    };
    let Some(old) = found else {
        if let Some(f) = OUTPUT_FILES.iter().find(|f| c.out.join(f).exists()) {
            bail!(
                "{} already holds a campaign ({f}); give an empty or new --out folder, or \
                 --resume (with the same parameters) to finish its missing runs",
                c.out.display()
            );
        }
        let info_text = serde_json::to_string_pretty(&c.info)?;
        std::fs::write(c.out.join("campaign.json"), info_text + "\n")?;
        write_records(&c.out, &[], &[])?;
        return Ok((c.info.clone(), Vec::new(), Vec::new()));
    };
    let differ = differences(&old.info, &c.info)?;
    if !differ.is_empty() {
        bail!(
            "{} holds another campaign, so --resume cannot continue it: {} (folder vs \
             command line); resume with the command that started it, or give a new --out folder",
            c.out.display(),
            differ.join(", ")
        );
    }
    let wanted: BTreeSet<u64> = c.info.run_indices().collect();
    let mut kept = BTreeSet::new();
    let runs: Vec<RunRecord> = old
        .runs
        .into_iter()
        .filter(|r| (r.ready || r.exit_code == Some(0)) && wanted.contains(&r.run))
        .filter(|r| kept.insert(r.run))
        .collect();
    let inj: Vec<InjectionRecord> = old
        .injections
        .into_iter()
        .filter(|i| kept.contains(&i.run))
        .collect();
    write_records(&c.out, &runs, &inj)?;
    Ok((old.info, runs, inj))
}

/// The parameters (all but the machine) in which `old` and `new` differ, as `name: old vs new`.
/// The description's digest only if `old` has one (a campaign begun before it was recorded).
fn differences(old: &CampaignInfo, new: &CampaignInfo) -> anyhow::Result<Vec<String>> {
    let digest = old.system_digest.is_some();
    let value = |i: &CampaignInfo| {
        serde_json::to_value(CampaignInfo {
            machine: None,
            system_digest: i.system_digest.clone().filter(|_| digest),
            ..i.clone()
        })
    };
    Ok(report::field_differences(&value(old)?, &value(new)?))
}

/// Replaces the records files with `runs` and `injections` (each written whole, then renamed).
fn write_records(
    out: &Path,
    runs: &[RunRecord],
    injections: &[InjectionRecord],
) -> anyhow::Result<()> {
    for (name, text) in [
        ("injections.jsonl", report::jsonl(injections)?),
        ("runs.jsonl", report::jsonl(runs)?),
    ] {
        report::write_whole(&out.join(name), text.as_bytes())?;
    }
    Ok(())
}

/// Writes the campaign's outputs (the records in run order, `info` with the load at its end)
/// and returns its summary.
fn write(
    c: &CampaignRun,
    mut info: CampaignInfo,
    mut runs: Vec<RunRecord>,
    mut injections: Vec<InjectionRecord>,
) -> anyhow::Result<Summary> {
    if let Some(m) = &mut info.machine {
        m.load_at_end = LoadAverage::now();
    }
    runs.sort_by_key(|r| r.run);
    injections.sort_by_key(|i| (i.run, i.index));
    let out = CampaignOutput {
        info,
        runs,
        injections,
    };
    let summaries = report::write_outputs(&c.out, &[out])?;
    summaries
        .into_iter()
        .next()
        .context("one campaign gives one summary")
}

/// Why a run never started its system (bootstrap could not be started, or ended with an error
/// before every target ran, or they never all ran): the reason, with the end of bootstrap's
/// stderr. `None` if the system did start (or ended on its own successfully).
pub fn never_started(result: &RunResult, dir: &Path) -> Option<String> {
    if result.ready || result.status.is_some_and(|s| s.success()) {
        return None;
    }
    if let Some(e) = &result.error {
        return Some(e.clone());
    }
    let stderr = std::fs::read_to_string(dir.join("stderr")).unwrap_or_default();
    let tail: Vec<&str> = stderr.lines().rev().take(5).collect();
    let tail: Vec<&str> = tail.into_iter().rev().collect();
    let how = match result.status {
        Some(s) if !result.timed_out => {
            format!("s3res-bootstrap ended ({s}) before every target ran")
        }
        _ => "the targets did not all run before the start-up limit".to_owned(),
    };
    Some(if tail.is_empty() {
        how
    } else {
        format!("{how}; its stderr ends:\n{}", tail.join("\n"))
    })
}

/// The run's folder: under `OUT/runs/` if kept, else a scratch folder removed on drop (and by
/// the next start in `OUT` if this campaign is killed outright, see `scratch.rs`).
fn run_dir(c: &CampaignRun, r: u64) -> anyhow::Result<(PathBuf, Option<ScratchDir>)> {
    if c.keep_runs {
        let dir = c.out.join("runs").join(format!("run-{r:06}"));
        std::fs::create_dir_all(&dir)?;
        Ok((dir, None))
    } else {
        let tmp = ScratchDir::new(&c.out, "s3res-inject-")?;
        Ok((tmp.path().to_path_buf(), Some(tmp)))
    }
}

/// Reads the task's verdict file; `Some(ok)` if asked for (missing or unreadable: `false`).
/// Its verdict is `ok`, or `success` (the robot's `mission.json`), as bootstrap's `outcome`
/// reads it: before, a campaign read only `ok` and counted every successful mission failed.
pub fn task_summary_ok(dir: &Path, file: Option<&str>) -> Option<bool> {
    let file = file?;
    let ok = std::fs::read_to_string(dir.join(file))
        .ok()
        .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
        .and_then(|v| {
            v.get("ok")
                .or_else(|| v.get("success"))
                .and_then(serde_json::Value::as_bool)
        })
        .unwrap_or(false);
    Some(ok)
}

/// The task summary was asked for and the run left none in its folder.
pub fn task_summary_missing(dir: &Path, file: Option<&str>) -> bool {
    file.is_some_and(|f| !dir.join(f).exists())
}

/// Turns one run's result into its records (matching injections with events).
pub fn records(
    info: &CampaignInfo,
    r: u64,
    dir: &Path,
    result: &RunResult,
) -> (RunRecord, Vec<InjectionRecord>) {
    let summary_ok = task_summary_ok(dir, info.task_summary.as_deref());
    let exit_ok = result.status.is_some_and(|s| s.success());
    let task_ok = exit_ok && !result.timed_out && summary_ok != Some(false);
    let fired: Vec<Fired> = result
        .attempts
        .iter()
        .filter_map(|a| {
            Some(Fired {
                ts_ns: a.ts_ns?,
                component: a.planned.component.clone(),
                slot: a.slot,
                pid: a.pid?,
            })
        })
        .collect();
    let m = match_run(
        &fired,
        &result.events,
        info.match_window_ms * 1_000_000,
        task_ok,
    );
    let mut matched = m.per_injection.into_iter();
    let inj: Vec<InjectionRecord> = result
        .attempts
        .iter()
        .map(|a| {
            let (outcome, mt) = if a.ts_ns.is_some() && a.pid.is_some() {
                matched.next().expect("one match per fired injection")
            } else {
                (Outcome::Missed, Default::default())
            };
            InjectionRecord {
                config: info.config.clone(),
                seed: info.seed,
                run: r,
                index: a.planned.index,
                at_ns: a.planned.at_ns,
                ts_ns: a.ts_ns,
                action: a.planned.action.clone(),
                component: a.planned.component.clone(),
                replica: a.slot,
                pid: a.pid,
                outcome,
                miss: a.miss.clone().or_else(|| {
                    mt.already_hit_by.map(|k| {
                        format!("process already hit by injection {k} and not yet found faulty")
                    })
                }),
                matched: mt,
                injector: a.injector.clone(),
            }
        })
        .collect();
    let status = result.status.map(|s| {
        use std::os::unix::process::ExitStatusExt as _;
        (s.code(), s.signal())
    });
    let run_rec = RunRecord {
        config: info.config.clone(),
        seed: info.seed,
        run: r,
        run_seed: run_seed(info.seed, r),
        exit_code: status.and_then(|s| s.0),
        exit_signal: status.and_then(|s| s.1),
        timed_out: result.timed_out,
        ready: result.ready,
        task_summary_ok: summary_ok,
        task_ok,
        planned: result.attempts.len() as u64,
        injected: fired.len() as u64,
        false_positives: m.false_positives,
        events: result.events.len() as u64,
        duration_ms: result.duration.as_millis() as u64,
        error: result
            .error
            .clone()
            .or_else(|| {
                (result.leftovers > 0).then(|| {
                    format!(
                        "{} process(es) of the run outlived bootstrap and were killed",
                        result.leftovers
                    )
                })
            })
            .or_else(|| {
                // Missing, not `"ok": false`: `task_summary_ok` is false for both.
                let file = info.task_summary.as_deref();
                (ended_clean(result) && task_summary_missing(dir, file)).then(|| {
                    format!(
                        "no task summary {} in the run's folder (counted as failed)",
                        file.unwrap_or_default()
                    )
                })
            }),
        load_before: None,
        load_after: None,
    };
    (run_rec, inj)
}

/// A run whose system started and ended by itself with exit 0, within its time: only such a
/// run's missing task summary says something of the name given (one that timed out or whose
/// system failed may simply not have written it).
fn ended_clean(result: &RunResult) -> bool {
    result.ready && !result.timed_out && result.status.is_some_and(|s| s.success())
}

/// A progress bar with ETA on a terminal; otherwise a line at most every 10 s. Neither under
/// `-q` (info not logged: "only warnings and errors", which the lines ignored before).
pub struct Progress {
    bar: Option<ProgressBar>,
    shown: bool,
    total: u64,
    done: u64,
    injected: u64,
    errors: u64,
    fpos: u64,
    started: Instant,
    last_line: Instant,
    label: String,
}

impl Progress {
    pub fn new(total: u64, info: &CampaignInfo) -> Self {
        let label = format!("{} {}", info.config, info.fault);
        let shown = tracing::enabled!(tracing::Level::INFO);
        let bar = (shown && std::io::stderr().is_terminal()).then(|| {
            let b = ProgressBar::new(total);
            b.set_style(
                ProgressStyle::with_template(
                    "{prefix} [{bar:30}] {pos}/{len} runs, ETA {eta} {msg}",
                )
                .expect("a valid template")
                .progress_chars("=> "),
            );
            b.set_prefix(label.clone());
            b
        });
        Progress {
            bar,
            shown,
            total,
            done: 0,
            injected: 0,
            errors: 0,
            fpos: 0,
            started: Instant::now(),
            last_line: Instant::now(),
            label,
        }
    }

    fn run_done(&mut self, run: &RunRecord, inj: &[InjectionRecord]) {
        self.done += 1;
        // Counted as the table counts: delivered, matched injections (not `missed`).
        self.injected += inj.iter().filter(|i| i.outcome != Outcome::Missed).count() as u64;
        self.errors += inj.iter().filter(|i| i.outcome.is_error()).count() as u64;
        self.fpos += run.false_positives;
        let msg = format!(
            "| {} injected, {} errors, {} false positives",
            self.injected, self.errors, self.fpos
        );
        match &self.bar {
            Some(b) => {
                b.set_message(msg);
                b.inc(1);
            }
            None if !self.shown => {}
            None => {
                if self.last_line.elapsed() >= Duration::from_secs(10) || self.done == self.total {
                    let elapsed = self.started.elapsed().as_secs_f64();
                    let eta = elapsed / self.done as f64 * (self.total - self.done) as f64;
                    eprintln!(
                        "s3res-inject: {}: run {}/{} {msg}, ETA {:.0}s",
                        self.label, self.done, self.total, eta
                    );
                    self.last_line = Instant::now();
                }
            }
        }
    }

    fn finish(&self) {
        if let Some(b) = &self.bar {
            b.finish();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A task's verdict is `ok` or `success`, as bootstrap reads an `outcome`.
    #[test]
    fn a_task_summary_says_ok_or_success() {
        let dir = tempfile::tempdir().unwrap();
        for (text, want) in [
            (r#"{"ok": true}"#, true),
            (r#"{"success": true, "outcome": "goal"}"#, true),
            (r#"{"success": false}"#, false),
            (r#"{"outcome": "goal"}"#, false),
            ("not json", false),
        ] {
            std::fs::write(dir.path().join("t.json"), text).unwrap();
            assert_eq!(
                task_summary_ok(dir.path(), Some("t.json")),
                Some(want),
                "{text}"
            );
        }
        assert_eq!(task_summary_ok(dir.path(), Some("none.json")), Some(false));
        assert_eq!(task_summary_ok(dir.path(), None), None);
    }

    /// `--resume` after the description changed is refused, saying so; a campaign begun
    /// before the digest was recorded resumes as before.
    #[test]
    fn a_resume_across_a_changed_description_is_refused() {
        let with = |digest: Option<&str>| CampaignInfo {
            system_digest: digest.map(str::to_owned),
            ..crate::report::tests::info(None)
        };
        let differ = differences(&with(Some("a")), &with(Some("b"))).unwrap();
        assert_eq!(
            differ,
            ["the description's text (system_digest: \"a\" vs \"b\")"]
        );
        assert!(differences(&with(None), &with(Some("b")))
            .unwrap()
            .is_empty());
        assert!(differences(&with(Some("a")), &with(Some("a")))
            .unwrap()
            .is_empty());
    }
}
