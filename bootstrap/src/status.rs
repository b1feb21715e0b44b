//! What a person watching bootstrap sees: a live status while the system runs and a verdict
//! block when it has ended.
//!
//! - [`Tally`] counts the voters' events as they arrive (the events reader applies each one):
//!   faults by kind, recoveries by method, frames withheld for want of a majority, and which
//!   replica slots are down at the moment.
//! - [`Console`] shows the tally: on a terminal, one updating status line under the scrolling
//!   logs (every process's stderr is then read through bootstrap, line by line, and printed
//!   above the status line, so nothing writes over it); otherwise a plain line every few
//!   seconds.
//! - [`Verdict`] is the block printed at the end: the task's outcome (from the file a
//!   component wrote, `outcome` in the description), faults by kind and component, recoveries
//!   by method, frames withheld, what the injector did and whether the voters blamed anyone it
//!   did not hit (false positives), and where the files are.

use std::collections::{BTreeMap, BTreeSet};
use std::fmt::Write as _;
use std::fs::File;
use std::io::{BufRead, BufReader, Write as _};
use std::os::fd::OwnedFd;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, Instant};

use indicatif::{ProgressBar, ProgressStyle};
use serde::Deserialize;

use s3res_protocol::event::{Cause, Event, EventKind, RecoveryMethod};

use crate::outcome::{match_run, Fired, Outcome};
use crate::plan::SystemPlan;

/// How often the terminal status line is redrawn.
pub const TERMINAL_TICK: Duration = Duration::from_millis(250);
/// How often a plain status line is printed when stderr is not a terminal.
pub const PLAIN_EVERY: Duration = Duration::from_secs(5);
/// A fault event counts as an injection's consequence only this long after it (as campaigns).
const MATCH_WINDOW_NS: u64 = 2_000_000_000;

/// Counts of one component's events.
#[derive(Debug, Default, Clone, PartialEq, Eq)]
pub struct ComponentTally {
    /// Fault events by kind (`sdc`, `crash`, `hang`, `protocol`).
    pub faults: BTreeMap<&'static str, u64>,
    pub recovered_by_fork: u64,
    pub recovered_by_exec: u64,
    /// Recoveries that said the replica's state was lost: every exec, and a fork whose donor
    /// had itself been started afresh (it has no state to give).
    pub state_lost: u64,
    /// Of those, forks.
    pub state_lost_by_fork: u64,
    pub failed_recoveries: u64,
    /// Frames withheld: no majority, nothing forwarded (`no_majority`).
    pub withheld: u64,
    /// Frames forwarded as the bitwise majority of answers that all differed (`all_differ`):
    /// a frame no replica wrote. Many of them say the program is not deterministic.
    pub rebuilt: u64,
    /// Frames that never went out: no replica answered (`lost` events).
    pub lost: u64,
    pub anomalies: u64,
    /// Times the component's voter was replaced by one that adopted its replicas.
    pub voter_restarts: u64,
    /// Slots found faulty and not yet replaced (or lost for good).
    pub down: BTreeSet<usize>,
    /// Slots whose replica was started afresh, differed for its lost state, and was kept
    /// outvoted because no fork could give the state back (`diverged`), until a fault or a
    /// recovery of the slot.
    pub diverged: BTreeSet<usize>,
}

impl ComponentTally {
    pub fn fault_count(&self) -> u64 {
        self.faults.values().sum()
    }

    pub fn recoveries(&self) -> u64 {
        self.recovered_by_fork + self.recovered_by_exec
    }
}

/// Everything counted so far.
#[derive(Debug, Default, Clone)]
pub struct TallyData {
    pub per_component: BTreeMap<String, ComponentTally>,
    /// Fault and recovery events, for matching against the injector's log at the end.
    pub events: Vec<Event>,
}

/// The shared tally: the events reader writes it, the console and the verdict read it.
#[derive(Debug, Default, Clone)]
pub struct Tally(Arc<Mutex<TallyData>>);

impl Tally {
    /// Takes one event into account.
    pub fn apply(&self, e: &Event) {
        let mut d = self.0.lock().unwrap_or_else(|p| p.into_inner());
        let c = d.per_component.entry(e.component.clone()).or_default();
        match e.kind {
            EventKind::Start => return,
            EventKind::Sdc | EventKind::Crash | EventKind::Hang | EventKind::Protocol => {
                *c.faults.entry(kind_name(e.kind)).or_default() += 1;
                match (e.replica, e.cause) {
                    (Some(slot), _) => {
                        // A fault ends the replica there: whatever it was, it is down now.
                        c.down.insert(slot);
                        c.diverged.remove(&slot);
                    }
                    (None, Some(Cause::NoMajority)) => c.withheld += 1,
                    (None, Some(Cause::AllDiffer)) => c.rebuilt += 1,
                    (None, _) => {}
                }
            }
            EventKind::Recovery => {
                let by_fork = e.method != Some(RecoveryMethod::Exec);
                if by_fork {
                    c.recovered_by_fork += 1;
                } else {
                    c.recovered_by_exec += 1;
                }
                if e.state_lost == Some(true) {
                    c.state_lost += 1;
                    c.state_lost_by_fork += u64::from(by_fork);
                }
                if let Some(slot) = e.replica {
                    c.down.remove(&slot);
                    c.diverged.remove(&slot);
                }
            }
            EventKind::RecoveryFailed => c.failed_recoveries += 1,
            EventKind::Anomaly => c.anomalies += 1,
            EventKind::VoterRestart => c.voter_restarts += 1,
            EventKind::Lost => c.lost += 1,
            EventKind::Diverged => {
                if let Some(slot) = e.replica {
                    c.diverged.insert(slot);
                }
            }
        }
        d.events.push(e.clone());
    }

    pub fn snapshot(&self) -> TallyData {
        self.0.lock().unwrap_or_else(|p| p.into_inner()).clone()
    }
}

/// `sdc`, `crash`, … as the events spell them.
pub fn kind_name(kind: EventKind) -> &'static str {
    match kind {
        EventKind::Start => "start",
        EventKind::Sdc => "sdc",
        EventKind::Crash => "crash",
        EventKind::Hang => "hang",
        EventKind::Protocol => "protocol",
        EventKind::Recovery => "recovery",
        EventKind::RecoveryFailed => "recovery_failed",
        EventKind::Anomaly => "anomaly",
        EventKind::VoterRestart => "voter_restart",
        EventKind::Lost => "lost",
        EventKind::Diverged => "diverged",
    }
}

/// How a component of `replicas` is degraded, if it is: replicas down, and replicas that vote
/// with a state of their own (`diverged`: outvoted, so they mask no fault of the others). A
/// verdict said "degraded at the end: none" over a component two of whose three replicas had
/// diverged, its output standing on one.
fn degraded_how(c: &ComponentTally, replicas: usize) -> Option<String> {
    let mut how = Vec::new();
    if !c.down.is_empty() {
        how.push(format!("{} of {replicas} down", c.down.len()));
    }
    if !c.diverged.is_empty() {
        how.push(format!("{} of {replicas} diverged", c.diverged.len()));
    }
    (!how.is_empty()).then(|| how.join(", "))
}

/// The status of the moment, one line: `12.5 s · filter 3 faults/3 recovered · … · degraded:
/// none`. `failed` names the components that failed so far, with how (`loader (failed: exit
/// status 3)`): an unprotected component has no voter to send events, and the line said
/// "degraded: none" after one had died.
pub fn status_line(
    plan: &SystemPlan,
    t: &TallyData,
    elapsed: Duration,
    injected: u64,
    failed: &[String],
) -> String {
    let mut parts = vec![format!("{:5.1} s", elapsed.as_secs_f64())];
    let mut degraded = failed.to_vec();
    for c in plan.components.iter().filter(|c| c.is_protected()) {
        let ct = t.per_component.get(&c.name).cloned().unwrap_or_default();
        parts.push(format!(
            "{} {}/{}",
            c.name,
            ct.fault_count(),
            ct.recoveries()
        ));
        if let Some(how) = degraded_how(&ct, c.replicas) {
            degraded.push(format!("{} ({how})", c.name));
        }
    }
    let mut line = parts.join(" · ");
    line.push_str(" (faults/recovered)");
    if plan.inject.is_some() {
        line.push_str(&format!(" · injected {injected}"));
    }
    line.push_str(" · degraded: ");
    if degraded.is_empty() {
        line.push_str("none");
    } else {
        line.push_str(&degraded.join(", "));
    }
    line
}

/// The status line on a terminal, if one is shown; logs are printed above it.
static BAR: OnceLock<ProgressBar> = OnceLock::new();

/// Writes `bytes` to stderr above the status line (or plainly if there is none).
pub fn write_stderr(bytes: &[u8]) {
    let write = || {
        let mut err = std::io::stderr().lock();
        let _ = err.write_all(bytes);
        if !bytes.ends_with(b"\n") {
            let _ = err.write_all(b"\n");
        }
    };
    match BAR.get() {
        Some(bar) => bar.suspend(write),
        None => write(),
    }
}

/// A `tracing` writer that prints above the status line.
#[derive(Debug, Clone, Copy, Default)]
pub struct StatusAwareStderr;

impl std::io::Write for StatusAwareStderr {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        match BAR.get() {
            Some(bar) => bar.suspend(|| std::io::stderr().write_all(buf))?,
            None => std::io::stderr().write_all(buf)?,
        }
        Ok(buf.len())
    }

    fn flush(&mut self) -> std::io::Result<()> {
        std::io::stderr().flush()
    }
}

impl<'a> tracing_subscriber::fmt::MakeWriter<'a> for StatusAwareStderr {
    type Writer = StatusAwareStderr;
    fn make_writer(&'a self) -> Self::Writer {
        *self
    }
}

/// How the status is shown.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ConsoleMode {
    /// One updating line on the terminal; children's stderr is read through bootstrap.
    Terminal,
    /// A plain line every [`PLAIN_EVERY`].
    Plain,
    /// Nothing (`-q`).
    Off,
}

/// The live status while the system runs.
pub struct Console {
    mode: ConsoleMode,
    started: Instant,
    last_plain: Instant,
}

impl Console {
    /// Starts showing the status. In terminal mode the status line appears at once.
    pub fn start(mode: ConsoleMode) -> Console {
        if mode == ConsoleMode::Terminal {
            let bar = ProgressBar::new_spinner();
            bar.set_style(
                ProgressStyle::with_template("{spinner} {msg}")
                    .unwrap_or_else(|_| ProgressStyle::default_spinner()),
            );
            let _ = BAR.set(bar);
        }
        let now = Instant::now();
        Console {
            mode,
            started: now,
            last_plain: now,
        }
    }

    /// How often [`Console::tick`] wants to be called; `None` when never.
    pub fn period(&self) -> Option<Duration> {
        match self.mode {
            ConsoleMode::Terminal => Some(TERMINAL_TICK),
            ConsoleMode::Plain => Some(PLAIN_EVERY),
            ConsoleMode::Off => None,
        }
    }

    pub fn elapsed(&self) -> Duration {
        self.started.elapsed()
    }

    /// Shows the status of the moment (plain mode: only when [`PLAIN_EVERY`] has passed).
    pub fn tick(&mut self, line: impl FnOnce(Duration) -> String) {
        match self.mode {
            ConsoleMode::Terminal => {
                if let Some(bar) = BAR.get() {
                    bar.set_message(line(self.elapsed()));
                    bar.tick();
                }
            }
            ConsoleMode::Plain if self.last_plain.elapsed() >= PLAIN_EVERY => {
                self.last_plain = Instant::now();
                eprintln!("s3res-bootstrap: {}", line(self.elapsed()));
            }
            _ => {}
        }
    }

    /// Removes the status line (before the verdict is printed).
    pub fn finish(&self) {
        if let Some(bar) = BAR.get() {
            bar.finish_and_clear();
        }
    }
}

/// Reads children's stderr (one pipe, shared) line by line and prints every line whole above
/// the status line, until every writer has closed it. A last line without a newline (a
/// process that died mid-line) gets one. The receiver hears when it is done.
pub fn forward_stderr(pipe: OwnedFd) -> std::io::Result<std::sync::mpsc::Receiver<()>> {
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::Builder::new()
        .name("stderr".to_owned())
        .spawn(move || {
            let mut input = BufReader::new(File::from(pipe));
            let mut buf = Vec::with_capacity(4096);
            loop {
                buf.clear();
                match input.read_until(b'\n', &mut buf) {
                    Ok(0) | Err(_) => break,
                    Ok(_) => write_stderr(&buf),
                }
            }
            let _ = tx.send(());
        })?;
    Ok(rx)
}

/// One line of the injector's log (`s3res-inject storm --log`), as far as the verdict needs it.
#[derive(Debug, Clone, PartialEq, Deserialize)]
pub struct Injected {
    /// When the signal went out; absent if it did not (`miss` says why).
    #[serde(default)]
    pub ts_ns: Option<u64>,
    pub kind: String,
    pub component: String,
    #[serde(default)]
    pub replica: Option<usize>,
    #[serde(default)]
    pub pid: Option<i32>,
    #[serde(default)]
    pub miss: Option<String>,
}

/// Reads the injector's log; unreadable lines are skipped (and counted).
pub fn read_injections(path: &Path) -> (Vec<Injected>, usize) {
    let Ok(text) = std::fs::read_to_string(path) else {
        return (Vec::new(), 0);
    };
    let mut bad = 0;
    let list = text
        .lines()
        .filter(|l| !l.trim().is_empty())
        .filter_map(|l| serde_json::from_str(l).map_err(|_| bad += 1).ok())
        .collect();
    (list, bad)
}

/// The task's verdict, read from the `outcome` file.
#[derive(Debug, Clone, PartialEq)]
pub struct TaskOutcome {
    pub ok: bool,
    /// Its other top-level numbers, strings and booleans, `key value`.
    pub details: Vec<String>,
}

/// Reads an outcome file: a JSON object with `ok` or `success`. `Err` says why it cannot be
/// used.
pub fn read_outcome(path: &Path) -> Result<TaskOutcome, String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("not written ({e})"))?;
    let v: serde_json::Value =
        serde_json::from_str(&text).map_err(|e| format!("not JSON ({e})"))?;
    let obj = v.as_object().ok_or("not a JSON object")?;
    let ok = obj
        .get("ok")
        .or_else(|| obj.get("success"))
        .and_then(serde_json::Value::as_bool)
        .ok_or("has no `ok` or `success` field")?;
    let details = obj
        .iter()
        .filter(|(k, _)| !matches!(k.as_str(), "ok" | "success"))
        .filter_map(|(k, v)| {
            let shown = match v {
                serde_json::Value::String(s) => s.clone(),
                serde_json::Value::Bool(b) => b.to_string(),
                serde_json::Value::Number(n) => match n.as_f64() {
                    Some(f) if n.is_f64() => format!("{f:.2}"),
                    _ => n.to_string(),
                },
                _ => return None,
            };
            Some(format!("{k} {shown}"))
        })
        .collect();
    Ok(TaskOutcome { ok, details })
}

/// Where the run's files are; `None` for one not kept.
#[derive(Debug, Clone, Default)]
pub struct Files {
    pub events: Option<PathBuf>,
    /// The events file could not be written to the end: why, and how many events it lacks.
    pub events_unsaved: Option<(String, u64)>,
    pub state: Option<PathBuf>,
    pub injections: Option<PathBuf>,
    pub outcome: Option<PathBuf>,
}

/// Everything the verdict block says.
#[derive(Debug, Clone)]
pub struct Verdict {
    pub system: String,
    pub elapsed: Duration,
    pub exit_code: u8,
    /// `component: status` of every component that failed.
    pub failures: Vec<String>,
    pub outcome: Option<Result<TaskOutcome, String>>,
    pub tally: TallyData,
    /// The injector's log, if one ran.
    pub injections: Option<Vec<Injected>>,
    pub files: Files,
    /// Protected components, in description order, with their replica count.
    pub protected: Vec<(String, usize)>,
}

impl Verdict {
    /// What the run lost that its exit status does not say: frames withheld, lost or rebuilt,
    /// state lost at a recovery, replicas down or diverged at the end. A run that ended 0 with
    /// none of them ran clean (faults recovered with the state kept are what s3res is for);
    /// before, every run that ended 0 did — one whose every frame was withheld, or whose
    /// state was lost in thirty restarts, too.
    fn losses(&self) -> Vec<String> {
        let sum = |f: fn(&ComponentTally) -> u64| -> u64 {
            self.tally.per_component.values().map(f).sum()
        };
        let count = |f: fn(&ComponentTally) -> usize| -> usize {
            self.tally.per_component.values().map(f).sum()
        };
        [
            (sum(|c| c.withheld) as usize, "frame", "withheld"),
            (sum(|c| c.lost) as usize, "frame", "lost"),
            (sum(|c| c.rebuilt) as usize, "frame", "rebuilt bit by bit"),
            (
                sum(|c| c.state_lost) as usize,
                "recover",
                "with the state lost",
            ),
            (count(|c| c.down.len()), "replica", "down"),
            (count(|c| c.diverged.len()), "replica", "diverged"),
            (
                self.files
                    .events_unsaved
                    .as_ref()
                    .map_or(0, |u| u.1 as usize),
                "event line",
                "not saved in the events file",
            ),
        ]
        .into_iter()
        .filter(|&(n, ..)| n > 0)
        .map(|(n, noun, what)| {
            let noun = match (noun, n) {
                ("recover", 1) => "recovery".to_owned(),
                ("recover", _) => "recoveries".to_owned(),
                (noun, 1) => noun.to_owned(),
                (noun, _) => format!("{noun}s"),
            };
            format!("{n} {noun} {what}")
        })
        .collect()
    }

    /// The block, ready to print (each line ends with a newline).
    pub fn render(&self) -> String {
        let mut s = String::new();
        let rule = "─".repeat(72);
        let _ = writeln!(s, "{rule}");
        let losses = self.losses();
        let _ = writeln!(
            s,
            "{}: {} after {:.1} s",
            self.system,
            if self.exit_code != 0 {
                format!("exit status {}", self.exit_code)
            } else if losses.is_empty() {
                "ran clean".to_owned()
            } else {
                format!("ran to the end, with losses: {}", losses.join(", "))
            },
            self.elapsed.as_secs_f64()
        );
        let task_ok = match &self.outcome {
            Some(Ok(o)) => {
                let word = if o.ok { "succeeded" } else { "FAILED" };
                let _ = writeln!(s, "  outcome      {word}: {}", o.details.join(", "));
                o.ok
            }
            Some(Err(why)) => {
                let _ = writeln!(s, "  outcome      unknown: the outcome file is {why}");
                false
            }
            None => self.exit_code == 0,
        };
        for f in &self.failures {
            let _ = writeln!(s, "  failed       {f}");
        }

        // Faults by component and kind.
        let mut total = 0;
        let mut lines = Vec::new();
        for (name, _) in &self.protected {
            let Some(c) = self.tally.per_component.get(name) else {
                continue;
            };
            let n = c.fault_count();
            total += n;
            if n > 0 {
                let kinds: Vec<String> = c.faults.iter().map(|(k, v)| format!("{k} {v}")).collect();
                lines.push(format!("{name} {n} ({})", kinds.join(", ")));
            }
        }
        let _ = writeln!(
            s,
            "  faults       {total}{}{}",
            if lines.is_empty() { "" } else { ": " },
            lines.join(" · ")
        );

        let sum = |f: fn(&ComponentTally) -> u64| -> u64 {
            self.tally.per_component.values().map(f).sum()
        };
        let (fork, exec, failed) = (
            sum(|c| c.recovered_by_fork),
            sum(|c| c.recovered_by_exec),
            sum(|c| c.failed_recoveries),
        );
        let (lost, lost_by_fork) = (sum(|c| c.state_lost), sum(|c| c.state_lost_by_fork));
        // A fork carries its donor's state, and a donor started afresh has none to give: such
        // a fork is counted with the forks and with the states lost, and said so.
        let state = match (fork + exec, lost, lost_by_fork) {
            (0, _, _) => String::new(),
            (_, 0, _) => "; state kept in every one".to_owned(),
            (_, n, 0) => format!("; state lost in {n}"),
            (_, n, f) => format!("; state lost in {n} ({f} forked from a donor started afresh)"),
        };
        let _ = writeln!(
            s,
            "  recoveries   {fork} by fork, {exec} by exec, {failed} failed{state}"
        );
        let degraded: Vec<String> = self
            .protected
            .iter()
            .filter_map(|(name, n)| {
                let c = self.tally.per_component.get(name)?;
                degraded_how(c, *n).map(|how| format!("{name} ({how})"))
            })
            .collect();
        let (rebuilt, lost) = (sum(|c| c.rebuilt), sum(|c| c.lost));
        let _ = writeln!(
            s,
            "  frames       {} withheld (no majority){}{}; degraded at the end: {}",
            sum(|c| c.withheld),
            if lost == 0 {
                String::new()
            } else {
                format!(", {lost} lost (no replica answered)")
            },
            if rebuilt == 0 {
                String::new()
            } else {
                format!(
                    ", {rebuilt} rebuilt bit by bit from answers that all differed \
                     (is the program deterministic?)"
                )
            },
            if degraded.is_empty() {
                "none".to_owned()
            } else {
                degraded.join(", ")
            }
        );
        // Replicas that vote with a state of their own: the run's outputs stood on the others.
        let diverged: Vec<String> = self
            .protected
            .iter()
            .filter_map(|(name, n)| {
                let c = self.tally.per_component.get(name)?;
                (!c.diverged.is_empty()).then(|| {
                    let slots: Vec<String> = c.diverged.iter().map(usize::to_string).collect();
                    format!("{name} replica {} of {n}", slots.join(", "))
                })
            })
            .collect();
        if !diverged.is_empty() {
            let _ = writeln!(
                s,
                "  diverged     {}: started afresh with the state lost, which no fork could \
                 give back; kept and outvoted instead of restarted (see its `diverged` event)",
                diverged.join(" · ")
            );
        }
        // A voter replaced is no fault of a replica, and no frame lost: but the run was not
        // as quiet as its fault count says.
        let replaced: Vec<String> = self
            .protected
            .iter()
            .filter_map(|(name, _)| {
                let n = self.tally.per_component.get(name)?.voter_restarts;
                (n > 0).then(|| format!("{name} {n}"))
            })
            .collect();
        if !replaced.is_empty() {
            let _ = writeln!(
                s,
                "  voters       replaced (replicas adopted): {}",
                replaced.join(" · ")
            );
        }
        let anomalies = sum(|c| c.anomalies);
        if anomalies > 0 {
            let _ = writeln!(s, "  anomalies    {anomalies} detector alarm(s)");
        }

        if let Some(inj) = &self.injections {
            self.render_injections(&mut s, inj, task_ok);
        }

        let f = &self.files;
        let mut files = Vec::new();
        for (what, p) in [
            ("events", &f.events),
            ("state", &f.state),
            ("injections", &f.injections),
            ("outcome", &f.outcome),
        ] {
            if let Some(p) = p {
                let incomplete = match (&f.events_unsaved, what) {
                    (Some((why, n)), "events") => {
                        let lines = if *n == 1 { "line" } else { "lines" };
                        format!(" (incomplete: its last {n} {lines} not saved: {why})")
                    }
                    _ => String::new(),
                };
                files.push(format!("{what} {}{incomplete}", p.display()));
            }
        }
        if !files.is_empty() {
            let _ = writeln!(s, "  files        {}", files.join(" · "));
        }
        let _ = writeln!(s, "{rule}");
        s
    }

    fn render_injections(&self, s: &mut String, inj: &[Injected], task_ok: bool) {
        let delivered: Vec<&Injected> = inj.iter().filter(|i| i.ts_ns.is_some()).collect();
        let mut by_kind: BTreeMap<&str, u64> = BTreeMap::new();
        for i in &delivered {
            *by_kind.entry(i.kind.as_str()).or_default() += 1;
        }
        let fired: Vec<Fired> = delivered
            .iter()
            .filter_map(|i| {
                Some(Fired {
                    ts_ns: i.ts_ns?,
                    component: i.component.clone(),
                    slot: i.replica,
                    pid: i.pid?,
                })
            })
            .collect();
        let m = match_run(&fired, &self.tally.events, MATCH_WINDOW_NS, task_ok);
        let count = |o: Outcome| m.per_injection.iter().filter(|(x, _)| *x == o).count();
        let kinds: Vec<String> = by_kind.iter().map(|(k, v)| format!("{k} {v}")).collect();
        let _ = writeln!(
            s,
            "  injected     {} ({}); {} not delivered (target busy or gone)",
            delivered.len(),
            kinds.join(", "),
            inj.len() - delivered.len()
        );
        let _ = writeln!(
            s,
            "               {} detected and recovered, {} detected not recovered, {} not \
             detected ({} harmless), {} hit an already faulty process",
            count(Outcome::Recovered),
            count(Outcome::Unrecovered),
            count(Outcome::Undetected) + count(Outcome::Benign),
            count(Outcome::Benign),
            count(Outcome::Missed)
        );
        let _ = writeln!(
            s,
            "  false pos.   {} (faults blamed on a replica nobody injected)",
            m.false_positives
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn event(kind: EventKind, slot: Option<usize>) -> Event {
        let mut e = Event::new("s", "filter", kind);
        e.replica = slot;
        e
    }

    /// The verdict of a run that ended with status 0, of one TMR component `name`, with no
    /// injector and no files.
    fn clean_run_of(name: &str, t: &Tally) -> Verdict {
        Verdict {
            system: "robot".into(),
            elapsed: Duration::from_secs(3),
            exit_code: 0,
            failures: vec![],
            outcome: None,
            tally: t.snapshot(),
            injections: None,
            files: Files::default(),
            protected: vec![(name.into(), 3)],
        }
    }

    /// An events file that could not be written to the end is no clean run's record: the
    /// headline and the files line say so.
    #[test]
    fn an_incomplete_events_file_is_said() {
        let mut v = clean_run_of("filter", &Tally::default());
        v.files.events = Some("ev.jsonl".into());
        v.files.events_unsaved = Some(("No space left on device (os error 28)".into(), 6));
        let text = v.render();
        assert!(
            text.contains(
                "ran to the end, with losses: 6 event lines not saved in the events file"
            ),
            "{text}"
        );
        assert!(
            text.contains(
                "events ev.jsonl (incomplete: its last 6 lines not saved: No space left on \
                 device (os error 28))"
            ),
            "{text}"
        );
    }

    #[test]
    fn tally_counts_kinds_methods_and_down_slots() {
        let t = Tally::default();
        t.apply(&event(EventKind::Start, Some(0)));
        t.apply(&event(EventKind::Crash, Some(1)));
        let mut r = event(EventKind::Recovery, Some(1));
        r.method = Some(RecoveryMethod::Fork);
        t.apply(&r);
        let mut withheld = event(EventKind::Sdc, None);
        withheld.cause = Some(Cause::NoMajority);
        t.apply(&withheld);
        t.apply(&event(EventKind::Hang, Some(2)));
        let d = t.snapshot();
        let c = &d.per_component["filter"];
        assert_eq!(c.faults.get("crash"), Some(&1));
        assert_eq!((c.recovered_by_fork, c.withheld, c.rebuilt), (1, 1, 0));
        assert_eq!(c.down.iter().copied().collect::<Vec<_>>(), vec![2]);
        assert_eq!(d.events.len(), 4, "start events are not kept");
    }

    /// An `all_differ` frame was forwarded (rebuilt bit by bit), not withheld; a fork from a
    /// donor started afresh lost its state like the exec before it, and the verdict says both
    /// without contradicting itself; a replaced voter is named.
    #[test]
    fn verdict_tells_withheld_from_rebuilt_frames_and_forks_that_lost_state() {
        let t = Tally::default();
        for cause in [Cause::AllDiffer, Cause::AllDiffer, Cause::NoMajority] {
            let mut e = event(EventKind::Sdc, None);
            e.cause = Some(cause);
            t.apply(&e);
        }
        for (method, lost) in [
            (RecoveryMethod::Exec, true),
            (RecoveryMethod::Fork, true),
            (RecoveryMethod::Fork, false),
        ] {
            let mut r = event(EventKind::Recovery, Some(0));
            r.method = Some(method);
            r.state_lost = Some(lost);
            t.apply(&r);
        }
        t.apply(&event(EventKind::VoterRestart, None));
        t.apply(&event(EventKind::Lost, None));
        let text = clean_run_of("filter", &t).render();
        // Exit status 0, but not clean: the headline says what was lost.
        assert!(
            text.contains(
                "robot: ran to the end, with losses: 1 frame withheld, 1 frame lost, 2 frames \
                 rebuilt bit by bit, 2 recoveries with the state lost after 3.0 s"
            ),
            "{text}"
        );
        assert!(
            text.contains("voters       replaced (replicas adopted): filter 1"),
            "{text}"
        );
        assert!(
            text.contains(
                "frames       1 withheld (no majority), 1 lost (no replica answered), 2 rebuilt \
                 bit by bit"
            ),
            "{text}"
        );
        assert!(
            text.contains(
                "recoveries   2 by fork, 1 by exec, 0 failed; state lost in 2 \
                 (1 forked from a donor started afresh)"
            ),
            "{text}"
        );
    }

    /// A replica kept outvoted for a state no fork could give back is named at the end, and
    /// no longer once its slot had a fault or was replaced.
    #[test]
    fn verdict_names_replicas_that_diverged_until_replaced() {
        let t = Tally::default();
        t.apply(&event(EventKind::Diverged, Some(1)));
        t.apply(&event(EventKind::Diverged, Some(2)));
        let text = clean_run_of("filter", &t).render();
        assert!(
            text.contains("diverged     filter replica 1, 2 of 3: started afresh"),
            "{text}"
        );
        assert!(text.contains("faults       0"), "not a fault: {text}");
        assert!(
            text.contains("degraded at the end: filter (2 of 3 diverged)"),
            "{text}"
        );
        let mut r = event(EventKind::Recovery, Some(1));
        r.method = Some(RecoveryMethod::Fork);
        t.apply(&r);
        t.apply(&event(EventKind::Crash, Some(2)));
        let text = clean_run_of("filter", &t).render();
        assert!(!text.contains("diverged"), "{text}");
        assert!(text.contains("with losses: 1 replica down"), "{text}");
        // Faults recovered by fork, with the state kept: what s3res is for, a clean run.
        let t = Tally::default();
        t.apply(&event(EventKind::Crash, Some(0)));
        let mut r = event(EventKind::Recovery, Some(0));
        r.method = Some(RecoveryMethod::Fork);
        r.state_lost = Some(false);
        t.apply(&r);
        let text = clean_run_of("filter", &t).render();
        assert!(text.contains("robot: ran clean after 3.0 s"), "{text}");
    }

    #[test]
    fn outcome_file_reads_ok_or_success_and_scalars() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("m.json");
        std::fs::write(
            &p,
            r#"{"success":true,"outcome":"Goal","mission_time_s":66.25,"collisions":0,"trajectory":[[0,0,0]]}"#,
        )
        .unwrap();
        let o = read_outcome(&p).unwrap();
        assert!(o.ok);
        assert_eq!(
            o.details,
            vec!["collisions 0", "mission_time_s 66.25", "outcome Goal"]
        );
        std::fs::write(&p, r#"{"x":1}"#).unwrap();
        assert!(read_outcome(&p).unwrap_err().contains("no `ok`"));
        assert!(read_outcome(&dir.path().join("none.json"))
            .unwrap_err()
            .starts_with("not written"));
    }

    #[test]
    fn verdict_names_faults_recoveries_and_false_positives() {
        let t = Tally::default();
        let mut crash = event(EventKind::Crash, Some(1));
        crash.pid = Some(100);
        crash.ts_ns = 1_000;
        t.apply(&crash);
        let mut r = event(EventKind::Recovery, Some(1));
        r.method = Some(RecoveryMethod::Fork);
        r.pid = Some(100);
        r.ts_ns = 2_000;
        t.apply(&r);
        let mut stray = event(EventKind::Hang, Some(0));
        stray.pid = Some(200);
        stray.ts_ns = 3_000;
        t.apply(&stray);
        let v = Verdict {
            injections: Some(vec![Injected {
                ts_ns: Some(500),
                kind: "exec".into(),
                component: "filter".into(),
                replica: Some(1),
                pid: Some(100),
                miss: None,
            }]),
            files: Files {
                events: Some("out/events.jsonl".into()),
                ..Files::default()
            },
            ..clean_run_of("filter", &t)
        };
        let text = v.render();
        assert!(
            text.contains("faults       2: filter 2 (crash 1, hang 1)"),
            "{text}"
        );
        assert!(
            text.contains("1 by fork, 0 by exec, 0 failed; state kept in every one"),
            "{text}"
        );
        assert!(text.contains("injected     1 (exec 1)"), "{text}");
        assert!(text.contains("1 detected and recovered"), "{text}");
        assert!(text.contains("false pos.   1"), "{text}");
        assert!(text.contains("events out/events.jsonl"), "{text}");
        assert!(text.contains("filter (1 of 3 down)"), "{text}");
    }
}
