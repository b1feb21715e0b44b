//! What a campaign writes, and how summaries and tables are computed from it. Everything here
//! is a function of the records alone, so `merge` of shards computes exactly what one machine
//! would have.

use std::fmt::Write as _;
use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::fault::FaultKind;
use crate::interval::Rate;
use crate::outcome::{Match, Outcome};
use crate::runner::SYSTEM_ENDED;

pub use s3res_protocol::campaign::{CampaignInfo, InjectionRecord, MachineInfo, RunRecord};

/// Distribution of a latency, microseconds.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Stats {
    pub n: u64,
    pub mean: f64,
    pub p50: u64,
    pub p90: u64,
    pub p99: u64,
    pub max: u64,
}

impl Stats {
    /// Percentiles from an HDR histogram, exact below 2¹⁸ µs (262 ms) and within 8 ppm above.
    /// The rank of quantile `q` among `n` values is the nearest one to `q · (n − 1)`, counted
    /// from 0 (the upper median for an even `n`), as campaign tables have always used.
    pub fn of(v: Vec<u64>) -> Stats {
        let n = v.len() as u64;
        if n == 0 {
            return Stats::default();
        }
        // 5 significant figures: every value below 2¹⁸ has a bucket of its own.
        let mut h = hdrhistogram::Histogram::<u64>::new(5).expect("5 significant figures");
        h.auto(true);
        for &x in &v {
            h.record(x)
                .expect("an auto-resizing histogram takes any u64");
        }
        // hdrhistogram returns the value of rank ceil(q' · n) (counted from 1); ask for the
        // middle of the wanted rank so that rounding of q' cannot move it.
        // Above 2¹⁸ µs a bucket's value may lie past every value in it (p99 695103 µs of a
        // max of 695100): a percentile is kept within the values' range.
        let (min, max) = (
            v.iter().copied().min().unwrap_or(0),
            v.iter().copied().max().unwrap_or(0),
        );
        let at = |q: f64| {
            let rank = ((n - 1) as f64 * q).round() + 1.0;
            h.value_at_quantile((rank - 0.5) / n as f64).clamp(min, max)
        };
        Stats {
            n,
            mean: v.iter().sum::<u64>() as f64 / n as f64,
            p50: at(0.5),
            p90: at(0.9),
            p99: at(0.99),
            max,
        }
    }
}

/// One element of `summary.json` (a list: one per campaign, several after a `merge` of
/// different campaigns).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Summary {
    pub config: String,
    pub fault: FaultKind,
    pub system: String,
    pub seed: u64,
    /// Runs of the campaign, and how many of them are in these records.
    pub runs: u64,
    pub runs_done: u64,
    pub successful_runs: u64,
    pub timed_out_runs: u64,
    pub planned: u64,
    /// Delivered injections (planned minus missed).
    pub injected: u64,
    pub missed: u64,
    /// Of the missed: planned after the run had ended (a window longer than the mission). Not
    /// a miss of the target; the table's "Missed" leaves them out (this count's `missed`
    /// holds them). Found by their reason, [`SYSTEM_ENDED`], word for word.
    #[serde(default)]
    pub after_end: u64,
    pub recovered: u64,
    pub unrecovered: u64,
    pub undetected: u64,
    pub benign: u64,
    /// (unrecovered + undetected) / injected × 100; `null` when nothing was injected.
    pub pct_error: Option<f64>,
    /// The same rate with what it rests on: `k` = unrecovered + undetected, `n` = injected, and
    /// its exact 95 % (Clopper–Pearson) interval `lower_pct`..`upper_pct`; `null` when nothing
    /// was injected.
    #[serde(default)]
    pub error_rate: Option<Rate>,
    /// Successful runs over the runs in these records, with its 95 % interval; `null` without
    /// runs.
    #[serde(default)]
    pub success_rate: Option<Rate>,
    pub false_positives: u64,
    pub detection_latency_us: Stats,
    pub recovery_us: Stats,
    pub recovered_after_us: Stats,
}

/// Computes the summary of `info`'s campaign from its records.
pub fn summarise(info: &CampaignInfo, runs: &[RunRecord], inj: &[InjectionRecord]) -> Summary {
    let count = |o: Outcome| inj.iter().filter(|r| r.outcome == o).count() as u64;
    let missed = count(Outcome::Missed);
    let injected = inj.len() as u64 - missed;
    let after_end = inj
        .iter()
        .filter(|r| r.outcome == Outcome::Missed && r.miss.as_deref() == Some(SYSTEM_ENDED))
        .count() as u64;
    let (recovered, unrecovered, undetected, benign) = (
        count(Outcome::Recovered),
        count(Outcome::Unrecovered),
        count(Outcome::Undetected),
        count(Outcome::Benign),
    );
    let successful_runs = runs.iter().filter(|r| r.task_ok).count() as u64;
    let collect = |f: fn(&Match) -> Option<u64>| {
        Stats::of(inj.iter().filter_map(|r| f(&r.matched)).collect())
    };
    Summary {
        config: info.config.clone(),
        fault: info.fault,
        system: info.system_name.clone(),
        seed: info.seed,
        runs: info.runs,
        runs_done: runs.len() as u64,
        successful_runs,
        timed_out_runs: runs.iter().filter(|r| r.timed_out).count() as u64,
        planned: inj.len() as u64,
        injected,
        missed,
        after_end,
        recovered,
        unrecovered,
        undetected,
        benign,
        pct_error: (injected > 0)
            .then(|| (unrecovered + undetected) as f64 * 100.0 / injected as f64),
        error_rate: Rate::of(unrecovered + undetected, injected),
        success_rate: Rate::of(successful_runs, runs.len() as u64),
        false_positives: runs.iter().map(|r| r.false_positives).sum(),
        detection_latency_us: collect(|m| m.detection_latency_us),
        recovery_us: collect(|m| m.recovery_us),
        recovered_after_us: collect(|m| m.recovered_after_us),
    }
}

fn ms(us: u64) -> String {
    format!("{:.1}", us as f64 / 1000.0)
}

/// The markdown tables, in the layout of the S³RES paper's Tables 2 and 3.
pub fn markdown(summaries: &[Summary]) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "Injections (S³RES Table 2 layout): % error = injections not followed by a recovery of \
         the injected replica (undetected in a failed run, or detected and not recovered), \
         over delivered injections, with its exact 95 % (Clopper–Pearson) interval and the \
         count it rests on. Missed: not counted — not delivered (the replica was being \
         replaced or gone, or never seen running by a register flip), or delivered into a \
         replica already hit and not yet found faulty (its effect cannot be told apart); \
         after end: planned after the run had ended (neither injected nor missed).\n"
    );
    let _ = writeln!(
        s,
        "| Config | Fault | Runs | Injected | % Error [95 % CI] of injected | F Pos. | Recovered | Unrecovered | Undetected | Benign | Missed | After end | Detect p50 / p99 (ms) | Recovery p50 / p99 (ms) |"
    );
    let _ = writeln!(
        s,
        "|---|---|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|"
    );
    for x in summaries {
        let pct = x
            .error_rate
            .map_or_else(|| "NA".to_owned(), |r| r.to_string());
        let lat = |st: &Stats| {
            if st.n == 0 {
                "–".to_owned()
            } else {
                format!("{} / {}", ms(st.p50), ms(st.p99))
            }
        };
        let _ = writeln!(
            s,
            "| {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} |",
            x.config,
            x.fault,
            x.runs_done,
            x.injected,
            pct,
            x.false_positives,
            x.recovered,
            x.unrecovered,
            x.undetected,
            x.benign,
            x.missed.saturating_sub(x.after_end),
            x.after_end,
            lat(&x.detection_latency_us),
            lat(&x.recovery_us),
        );
    }
    // Table 3: successful runs, fault × config.
    let mut configs: Vec<&str> = summaries.iter().map(|x| x.config.as_str()).collect();
    configs.sort_unstable();
    configs.dedup();
    let mut faults: Vec<FaultKind> = summaries.iter().map(|x| x.fault).collect();
    faults.sort_unstable();
    faults.dedup();
    let _ = writeln!(
        s,
        "\nSuccessful runs (S³RES Table 3 layout): runs whose task succeeded / runs, and the \
         success rate with its exact 95 % (Clopper–Pearson) interval.\n"
    );
    let _ = writeln!(s, "| Fault | {} |", configs.join(" | "));
    let _ = writeln!(s, "|---|{}", "--:|".repeat(configs.len()));
    for f in faults {
        let cells: Vec<String> = configs
            .iter()
            .map(|c| {
                let rows: Vec<&Summary> = summaries
                    .iter()
                    .filter(|x| x.fault == f && x.config == *c)
                    .collect();
                if rows.is_empty() {
                    "–".to_owned()
                } else {
                    let ok: u64 = rows.iter().map(|x| x.successful_runs).sum();
                    let n: u64 = rows.iter().map(|x| x.runs_done).sum();
                    success_cell(ok, n)
                }
            })
            .collect();
        let _ = writeln!(s, "| {f} | {} |", cells.join(" | "));
    }
    s
}

/// `9/12: 75.00 % [42.81, 94.51]`: successful runs of runs, the rate and its 95 % interval.
pub fn success_cell(ok: u64, n: u64) -> String {
    match Rate::of(ok, n) {
        Some(r) => format!("{ok}/{n}: {:.2} % {}", r.pct, r.interval()),
        None => format!("{ok}/{n}"),
    }
}

/// A campaign's output folder, read back.
#[derive(Debug, Clone)]
pub struct CampaignOutput {
    pub info: CampaignInfo,
    pub runs: Vec<RunRecord>,
    pub injections: Vec<InjectionRecord>,
}

fn read_text(path: &Path) -> Result<String, String> {
    std::fs::read_to_string(path).map_err(|e| format!("cannot read {}: {e}", path.display()))
}

/// The fields of two JSON objects that differ, as `key: OLD vs NEW` (`-`: absent), in key
/// order; what a refused `--resume` or `merge` names. Values that are not objects differ as
/// a whole (`value: OLD vs NEW`).
pub(crate) fn field_differences(old: &serde_json::Value, new: &serde_json::Value) -> Vec<String> {
    let show = |v: Option<&serde_json::Value>| v.map_or("-".to_owned(), |v| v.to_string());
    let (Some(o), Some(n)) = (old.as_object(), new.as_object()) else {
        if old == new {
            return Vec::new();
        }
        return vec![format!("value: {} vs {}", show(Some(old)), show(Some(new)))];
    };
    let keys: std::collections::BTreeSet<&String> = o.keys().chain(n.keys()).collect();
    keys.into_iter()
        .filter(|k| o.get(*k) != n.get(*k))
        .map(|k| match k.as_str() {
            "system_digest" => format!(
                "the description's text (system_digest: {} vs {})",
                show(o.get(k)),
                show(n.get(k))
            ),
            _ => format!("{k}: {} vs {}", show(o.get(k)), show(n.get(k))),
        })
        .collect()
}

/// Replaces `path` with `bytes` whole: written beside it, then renamed over it, so that a
/// kill or a full disk leaves the old file or the new one, never a cut one.
pub(crate) fn write_whole(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let mut tmp = path.as_os_str().to_owned();
    tmp.push(".tmp");
    std::fs::write(&tmp, bytes)?;
    std::fs::rename(&tmp, path)
}

/// One record per non-blank line of `text`; `label` names the file in errors. With `cut_ok`, a
/// last line that is not a whole record (the writer was killed in the middle of it: no
/// newline after it) is left out.
pub(crate) fn parse_jsonl<T: serde::de::DeserializeOwned>(
    label: &str,
    text: &str,
    cut_ok: bool,
) -> Result<Vec<T>, String> {
    let cut = if cut_ok && !text.ends_with('\n') {
        text.lines().count()
    } else {
        0
    };
    text.lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty())
        .filter_map(|(i, l)| match serde_json::from_str(l) {
            Ok(r) => Some(Ok(r)),
            Err(_) if i + 1 == cut => None,
            Err(e) => Some(Err(format!("{label}:{}: not a record: {e}", i + 1))),
        })
        .collect()
}

impl CampaignOutput {
    /// Reads the folder a campaign (or a shard of one) wrote.
    pub fn read(dir: &Path) -> Result<Self, String> {
        let (info, runs, inj) = (
            dir.join("campaign.json"),
            dir.join("runs.jsonl"),
            dir.join("injections.jsonl"),
        );
        CampaignOutput::parse(
            [&info, &runs, &inj].map(|p| p.display().to_string()),
            [read_text(&info)?, read_text(&runs)?, read_text(&inj)?].each_ref(),
        )
    }

    /// The same from the texts of `campaign.json`, `runs.jsonl` and `injections.jsonl`, in
    /// that order; `labels` name them in errors.
    pub fn parse(labels: [String; 3], texts: [&String; 3]) -> Result<Self, String> {
        let info = serde_json::from_str(texts[0])
            .map_err(|e| format!("{}: not a campaign description: {e}", labels[0]))?;
        Ok(CampaignOutput {
            info,
            runs: parse_jsonl(&labels[1], texts[1], false)?,
            injections: parse_jsonl(&labels[2], texts[2], false)?,
        })
    }

    /// Reads what a campaign interrupted at any point left in `dir`: a missing records file is
    /// empty, and a record cut short by a kill is left out. `None` if `dir` holds no campaign.
    pub fn read_partial(dir: &Path) -> Result<Option<Self>, String> {
        let info_path = dir.join("campaign.json");
        if !info_path.exists() {
            return Ok(None);
        }
        let text = std::fs::read_to_string(&info_path)
            .map_err(|e| format!("cannot read {}: {e}", info_path.display()))?;
        let info = serde_json::from_str(&text)
            .map_err(|e| format!("{}: not a campaign description: {e}", info_path.display()))?;
        let records = |name: &str| {
            let path = dir.join(name);
            match std::fs::read_to_string(&path) {
                Ok(text) => Ok(text),
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(String::new()),
                Err(e) => Err(format!("cannot read {}: {e}", path.display())),
            }
            .map(|text| (path, text))
        };
        let (runs_path, runs) = records("runs.jsonl")?;
        let (inj_path, inj) = records("injections.jsonl")?;
        Ok(Some(CampaignOutput {
            info,
            runs: parse_jsonl(&runs_path.display().to_string(), &runs, true)?,
            injections: parse_jsonl(&inj_path.display().to_string(), &inj, true)?,
        }))
    }

    pub fn summary(&self) -> Summary {
        summarise(&self.info, &self.runs, &self.injections)
    }
}

/// Merges campaign outputs: shards of the same campaign become one; different campaigns stay
/// side by side (in the order first seen). Errors on a run present twice.
pub fn merge(parts: Vec<CampaignOutput>) -> Result<Vec<CampaignOutput>, String> {
    let mut merged: Vec<CampaignOutput> = Vec::new();
    for p in parts {
        let id = p.info.identity();
        match merged.iter_mut().find(|m| m.info.identity() == id) {
            Some(m) => {
                for r in &p.runs {
                    if m.runs.iter().any(|x| x.run == r.run) {
                        return Err(format!(
                            "run {} of campaign {} ({}) appears in two inputs",
                            r.run, m.info.config, m.info.fault
                        ));
                    }
                }
                m.runs.extend(p.runs);
                m.injections.extend(p.injections);
            }
            None => merged.push(CampaignOutput {
                info: CampaignInfo {
                    machine: p.info.machine.clone(),
                    system: p.info.system.clone(),
                    ..id
                },
                runs: p.runs,
                injections: p.injections,
            }),
        }
    }
    // Two campaigns of one row (configuration and fault) would be pooled in the tables as if
    // they were one, and each would look like a campaign with shards missing.
    for (i, a) in merged.iter().enumerate() {
        if let Some(b) = merged[i + 1..]
            .iter()
            .find(|b| (&b.info.config, b.info.fault) == (&a.info.config, a.info.fault))
        {
            let value = |c: &CampaignOutput| serde_json::to_value(c.info.identity());
            let differ = field_differences(
                &value(a).map_err(|e| e.to_string())?,
                &value(b).map_err(|e| e.to_string())?,
            );
            return Err(format!(
                "the inputs hold two campaigns of row {} {} that differ in {}: merge joins the \
                 shards of one campaign, or campaigns of other rows (give one its own --label)",
                a.info.config,
                a.info.fault,
                differ.join(", ")
            ));
        }
    }
    for m in &mut merged {
        m.runs.sort_by_key(|r| r.run);
        m.injections.sort_by_key(|r| (r.run, r.index));
    }
    Ok(merged)
}

/// `records` as JSON lines, one per record.
pub fn jsonl<T: Serialize>(records: &[T]) -> std::io::Result<String> {
    let mut text = String::new();
    for r in records {
        text.push_str(&serde_json::to_string(r).map_err(std::io::Error::other)?);
        text.push('\n');
    }
    Ok(text)
}

/// Writes `injections.jsonl`, `runs.jsonl`, `summary.json`, `table.md` (and, for a single
/// campaign, `campaign.json`) into `dir`.
pub fn write_outputs(dir: &Path, outputs: &[CampaignOutput]) -> std::io::Result<Vec<Summary>> {
    std::fs::create_dir_all(dir)?;
    let mut inj = String::new();
    let mut runs = String::new();
    for o in outputs {
        inj.push_str(&jsonl(&o.injections)?);
        runs.push_str(&jsonl(&o.runs)?);
    }
    std::fs::write(dir.join("injections.jsonl"), inj)?;
    std::fs::write(dir.join("runs.jsonl"), runs)?;
    if let [one] = outputs {
        let text = serde_json::to_string_pretty(&one.info).map_err(std::io::Error::other)?;
        std::fs::write(dir.join("campaign.json"), text + "\n")?;
    }
    let summaries: Vec<Summary> = outputs.iter().map(CampaignOutput::summary).collect();
    let text = serde_json::to_string_pretty(&summaries).map_err(std::io::Error::other)?;
    std::fs::write(dir.join("summary.json"), text + "\n")?;
    std::fs::write(dir.join("table.md"), markdown(&summaries))?;
    Ok(summaries)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use s3res_protocol::campaign::{Action, Arrival, Pick, RegOptions, VarField, VarSpec};
    use std::collections::BTreeMap;

    pub(crate) fn info(shard: Option<(u64, u64)>) -> CampaignInfo {
        CampaignInfo {
            config: "tmr".into(),
            system: "s.json".into(),
            system_digest: Some("fnv1a64:0".into()),
            system_name: "s".into(),
            fault: FaultKind::Exec,
            rate_hz: 2.0,
            arrival: Arrival::Exponential,
            window_ms: 1000,
            runs: 4,
            seed: 1,
            shard,
            pick: Pick::Uniform,
            components: vec!["echo".into()],
            var: VarSpec {
                offset: 0,
                field: VarField::Byte,
                flips: 1,
                bits: None,
            },
            reg: RegOptions::default(),
            match_window_ms: 2000,
            run_limit_ms: 60000,
            task_summary: None,
            redundancy: BTreeMap::new(),
            machine: None,
        }
    }

    fn run(r: u64, ok: bool, fp: u64) -> RunRecord {
        RunRecord {
            config: "tmr".into(),
            seed: 1,
            run: r,
            run_seed: r,
            exit_code: Some(if ok { 0 } else { 1 }),
            exit_signal: None,
            timed_out: false,
            ready: true,
            task_summary_ok: None,
            task_ok: ok,
            planned: 1,
            injected: 1,
            false_positives: fp,
            events: 0,
            duration_ms: 1,
            error: None,
            load_before: None,
            load_after: None,
        }
    }

    fn inj(r: u64, outcome: Outcome, lat: Option<u64>) -> InjectionRecord {
        InjectionRecord {
            config: "tmr".into(),
            seed: 1,
            run: r,
            index: 0,
            at_ns: 5,
            ts_ns: Some(10),
            action: Action::Exec,
            component: "echo".into(),
            replica: Some(0),
            pid: Some(3),
            outcome,
            miss: None,
            matched: Match {
                detection_latency_us: lat,
                ..Match::default()
            },
            injector: None,
        }
    }

    /// The percentiles as they were computed by hand before hdrhistogram (sorted, nearest rank).
    fn stats_by_hand(mut v: Vec<u64>) -> (u64, u64, u64, u64) {
        v.sort_unstable();
        let at = |q: f64| v[((v.len() - 1) as f64 * q).round() as usize];
        (at(0.5), at(0.9), at(0.99), *v.last().unwrap())
    }

    #[test]
    fn percentiles_are_the_figures_computed_by_hand() {
        let mut rng = s3res_protocol::rng::SplitMix64::new(17);
        for n in (1..=40).chain([99, 100, 101, 1000, 4321]) {
            for spread in [10, 5_000, 262_143] {
                let v: Vec<u64> = (0..n).map(|_| rng.below(spread)).collect();
                let s = Stats::of(v.clone());
                assert_eq!((s.p50, s.p90, s.p99, s.max), stats_by_hand(v), "n = {n}");
                assert_eq!(s.n, n);
            }
        }
        // Above 2^18 µs a percentile may round up, by at most 8 ppm.
        let v: Vec<u64> = (0..500).map(|_| rng.below(5_000_000_000)).collect();
        let s = Stats::of(v.clone());
        let (p50, p90, p99, max) = stats_by_hand(v);
        for (got, want) in [(s.p50, p50), (s.p90, p90), (s.p99, p99)] {
            assert!(
                got >= want && (got - want) as f64 <= want as f64 * 8e-6,
                "{got} vs {want}"
            );
        }
        assert_eq!(s.max, max);
        assert_eq!(Stats::of(Vec::new()), Stats::default());
    }

    /// A percentile rounded up by its bucket stayed past the max (p99 695103 µs of a max of
    /// 695100 in a campaign's summary.json): every percentile is within min..=max.
    #[test]
    fn a_percentile_never_exceeds_the_max() {
        for v in [
            vec![695_100],
            vec![1, 695_100],
            vec![695_100, 695_100, 695_100],
            vec![300_001, 300_002],
        ] {
            let s = Stats::of(v.clone());
            let (min, max) = (*v.iter().min().unwrap(), *v.iter().max().unwrap());
            for p in [s.p50, s.p90, s.p99] {
                assert!((min..=max).contains(&p), "{p} of {v:?}: {s:?}");
            }
        }
    }

    #[test]
    fn records_round_trip_through_json() {
        let r = inj(0, Outcome::Recovered, Some(4));
        let line = serde_json::to_string(&r).unwrap();
        assert!(line.contains("\"kind\":\"exec\""), "{line}");
        assert_eq!(serde_json::from_str::<InjectionRecord>(&line).unwrap(), r);
    }

    #[test]
    fn summary_counts_and_error_rate() {
        let runs = vec![run(0, true, 0), run(1, false, 2)];
        let injs = vec![
            inj(0, Outcome::Recovered, Some(1000)),
            inj(0, Outcome::Benign, None),
            inj(1, Outcome::Undetected, None),
            inj(1, Outcome::Missed, None),
            InjectionRecord {
                miss: Some(SYSTEM_ENDED.into()),
                ..inj(1, Outcome::Missed, None)
            },
        ];
        let s = summarise(&info(None), &runs, &injs);
        assert_eq!((s.injected, s.missed, s.false_positives), (3, 2, 2));
        assert_eq!(s.after_end, 1);
        // Campaign folders already written hold this reason word for word: `merge` finds
        // their after-the-end injections by it.
        assert_eq!(SYSTEM_ENDED, "the system had ended (or hit the time limit)");
        assert!((s.pct_error.unwrap() - 100.0 / 3.0).abs() < 1e-9);
        assert_eq!(s.successful_runs, 1);
        assert_eq!(s.detection_latency_us.p50, 1000);
        let e = s.error_rate.unwrap();
        assert_eq!((e.k, e.n), (1, 3));
        assert!((e.lower_pct - 0.840_3).abs() < 1e-3, "{e:?}");
        assert!((e.upper_pct - 90.57).abs() < 1e-2, "{e:?}");
        let ok = s.success_rate.unwrap();
        assert_eq!((ok.k, ok.n), (1, 2));
        let json = serde_json::to_value(&s).unwrap();
        for (field, n) in [("error_rate", 3), ("success_rate", 2)] {
            let r = &json[field];
            assert_eq!(r["n"], n, "{json}");
            assert!(r["lower_pct"].is_f64() && r["upper_pct"].is_f64(), "{json}");
        }
        let md = markdown(&[s]);
        assert!(
            md.contains(
                "| tmr | exec | 2 | 3 | 33.33 % [0.84, 90.57] of 3 | 2 | 1 | 0 | 1 | 1 | 1 | 1 |"
            ),
            "{md}"
        );
        assert!(md.contains("| exec | 1/2: 50.00 % [1.26, 98.74] |"), "{md}");
    }

    #[test]
    fn shards_merge_into_the_whole_and_duplicates_are_refused() {
        let whole = CampaignOutput {
            info: info(None),
            runs: (0..4).map(|r| run(r, r != 2, r)).collect(),
            injections: (0..4)
                .map(|r| inj(r, Outcome::Recovered, Some(r)))
                .collect(),
        };
        let shard = |k: u64| {
            let i = info(Some((k, 2)));
            let runs: Vec<u64> = i.run_indices().collect();
            CampaignOutput {
                runs: whole
                    .runs
                    .iter()
                    .filter(|r| runs.contains(&r.run))
                    .cloned()
                    .collect(),
                injections: whole
                    .injections
                    .iter()
                    .filter(|r| runs.contains(&r.run))
                    .cloned()
                    .collect(),
                info: i,
            }
        };
        let merged = merge(vec![shard(2), shard(1)]).unwrap();
        assert_eq!(merged.len(), 1);
        assert_eq!(merged[0].summary(), whole.summary());
        assert_eq!(merged[0].runs, whole.runs);
        assert!(merge(vec![shard(1), shard(1)]).is_err());
    }

    /// Shards of two campaigns of one row (another seed, another description) are refused,
    /// naming the difference: they were pooled in the tables as one campaign, each warned of
    /// as missing shards. Campaigns of other rows (another label) are merged side by side.
    #[test]
    fn two_campaigns_of_one_row_are_not_pooled() {
        let of = |shard: (u64, u64), seed: u64, digest: &str, config: &str| CampaignOutput {
            info: CampaignInfo {
                seed,
                system_digest: Some(digest.into()),
                config: config.into(),
                ..info(Some(shard))
            },
            runs: Vec::new(),
            injections: Vec::new(),
        };
        let e = merge(vec![of((1, 2), 5, "d", "tmr"), of((2, 2), 6, "d", "tmr")]).unwrap_err();
        assert!(
            e.contains("two campaigns of row tmr exec that differ in seed: 5 vs 6"),
            "{e}"
        );
        let e = merge(vec![of((1, 2), 5, "d", "tmr"), of((2, 2), 5, "e", "tmr")]).unwrap_err();
        assert!(
            e.contains("the description's text (system_digest: \"d\" vs \"e\")"),
            "{e}"
        );
        let rows = merge(vec![of((1, 2), 5, "d", "tmr"), of((2, 2), 6, "d", "tmr-b")]).unwrap();
        assert_eq!(rows.len(), 2);
        // One campaign's shards run from two checkouts: one campaign.
        let mut elsewhere = of((2, 2), 5, "d", "tmr");
        elsewhere.info.system = "/elsewhere/s.json".into();
        let one = merge(vec![of((1, 2), 5, "d", "tmr"), elsewhere]).unwrap();
        assert_eq!(one.len(), 1);
        assert_eq!(one[0].info.system, std::path::PathBuf::from("s.json"));
    }

    #[test]
    fn a_partial_campaign_reads_without_its_cut_last_record() {
        let dir = tempfile::tempdir().unwrap();
        assert!(CampaignOutput::read_partial(dir.path()).unwrap().is_none());
        let text = serde_json::to_string(&info(Some((1, 2)))).unwrap();
        std::fs::write(dir.path().join("campaign.json"), text).unwrap();
        // Killed in the middle of the third line: no injections file yet.
        let whole = jsonl(&[run(0, true, 0), run(2, false, 1)]).unwrap();
        let cut = jsonl(&[run(4, true, 0)]).unwrap();
        let runs = format!("{whole}{}", &cut[..cut.len() / 2]);
        std::fs::write(dir.path().join("runs.jsonl"), &runs).unwrap();
        let p = CampaignOutput::read_partial(dir.path()).unwrap().unwrap();
        assert_eq!(p.runs, vec![run(0, true, 0), run(2, false, 1)]);
        assert!(p.injections.is_empty());
        assert_eq!(p.info, info(Some((1, 2))));
        // A bad line that is not the last, or a cut line in a finished file, is an error.
        std::fs::write(dir.path().join("runs.jsonl"), format!("{runs}\n")).unwrap();
        let e = CampaignOutput::read_partial(dir.path()).unwrap_err();
        assert!(e.contains("runs.jsonl:3"), "{e}");
        assert!(CampaignOutput::read(dir.path()).is_err());
    }
}
