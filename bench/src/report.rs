//! Results: HDR histograms of nanoseconds, one [`Row`] per configuration, printed as a table
//! or as JSON lines.

use hdrhistogram::Histogram;
use s3res_protocol::machine::{ticks_to_ms, CpuTimes, Cpus};
use serde::Serialize;

/// A histogram of durations in nanoseconds, 1 ns to 100 s, 3 significant digits.
pub fn histogram() -> Histogram<u64> {
    Histogram::new_with_bounds(1, 100_000_000_000, 3).expect("valid histogram bounds")
}

/// Summary figures of one histogram, in microseconds.
#[derive(Debug, Clone, Copy, Default, Serialize, PartialEq)]
pub struct Summary {
    pub count: u64,
    pub median_us: f64,
    pub p99_us: f64,
    pub p999_us: f64,
    pub max_us: f64,
    pub min_us: f64,
}

impl Summary {
    pub fn of(h: &Histogram<u64>) -> Summary {
        let us = |ns: u64| ns as f64 / 1000.0;
        Summary {
            count: h.len(),
            median_us: us(h.value_at_quantile(0.5)),
            p99_us: us(h.value_at_quantile(0.99)),
            p999_us: us(h.value_at_quantile(0.999)),
            max_us: us(h.max()),
            min_us: us(h.min()),
        }
    }
}

/// One configuration's result. Optional fields are left out of the JSON when absent.
#[derive(Debug, Clone, Serialize)]
pub struct Row {
    pub bench: &'static str,
    /// What was measured, when a bench measures several things (e.g. `crash`, `hang`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub what: Option<String>,
    /// 0 = no voter (the component alone), 1 SMR, 2 DMR, 3 TMR.
    pub replicas: usize,
    /// Frame payload bytes (echo), or resident state bytes (restart).
    pub size: u64,
    /// Samples measured.
    pub count: u64,
    pub median_us: f64,
    pub p99_us: f64,
    pub p999_us: f64,
    pub max_us: f64,
    /// `plain`, `rr` or `rr-pinned` (see `--setup`).
    pub setup: &'static str,
    /// Round deadline of the voter, microseconds.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub timeout_us: Option<u64>,
    /// Median of the floor (restart: fork + touch every page of the same size).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub floor_us: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub floor_p99_us: Option<f64>,
    /// median / baseline median (echo: the no-voter row of the same size and setup; restart:
    /// the floor).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub ratio: Option<f64>,
    /// Fault events the voter reported while measuring (should be 0 without injection).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub faults: Option<u64>,
    /// Free-form figures of the bench (memory sizes, counts).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub extra: Option<serde_json::Value>,
    /// The machine it ran on, one line (`replica_rt::machine::Machine::one_line`, load at the
    /// bench's start); figures print it in their subtitle.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub machine: Option<String>,
    /// `poll` when the voters kept idle CPUs polling (`--cpu-idle poll`); absent: `halt`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub cpu_idle: Option<&'static str>,
    /// How long the voter could spin for an answer (`--spin-us`), where it could: a voter
    /// pinned apart from its replicas (`rr-pinned`); absent elsewhere.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub spin_us: Option<u32>,
    /// `static` when the component measured (`s3res-echo`, `s3res-ballast`) was statically
    /// linked (`--component-dir`); absent: dynamically, as the workspace builds it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub linking: Option<&'static str>,
    /// Milliseconds the hypervisor took this machine's CPUs while the row was measured
    /// ([`Steal`]); absent where `/proc/stat` could not be read.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub steal_ms: Option<u64>,
}

/// The host's steal over one measurement: time the hypervisor ran something else while this
/// guest's CPUs had work to do (`/proc/stat`'s `steal`, every CPU summed; 10 ms ticks). To
/// the guest it is a stall of everything on that CPU — the voter, a replica, the bench's
/// client — that no figure of its own tells from the system's latency: on the VM of
/// docs/results.md (stop 54) a round-trip run's 100 ms maximum was the host's, and idle CPUs
/// kept polling (`--cpu-idle poll`) are taken more often than halting ones. 0 on bare metal.
#[derive(Debug)]
pub struct Steal(Option<CpuTimes>);

impl Steal {
    /// Starts counting now.
    pub fn start() -> Steal {
        Steal(CpuTimes::now(Cpus::All))
    }

    /// Milliseconds stolen since [`Steal::start`]; `None` if `/proc/stat` could not be read.
    pub fn ms(&self) -> Option<u64> {
        let (before, after) = (self.0?, CpuTimes::now(Cpus::All)?);
        Some(ticks_to_ms(after.steal.saturating_sub(before.steal)))
    }
}

impl Row {
    pub fn new(bench: &'static str, replicas: usize, size: u64, s: Summary) -> Row {
        Row {
            bench,
            what: None,
            replicas,
            size,
            count: s.count,
            median_us: s.median_us,
            p99_us: s.p99_us,
            p999_us: s.p999_us,
            max_us: s.max_us,
            setup: "plain",
            timeout_us: None,
            floor_us: None,
            floor_p99_us: None,
            ratio: None,
            faults: None,
            extra: None,
            machine: None,
            cpu_idle: None,
            spin_us: None,
            linking: None,
            steal_ms: None,
        }
    }

    pub fn to_json(&self) -> String {
        serde_json::to_string(self).expect("a row always serializes")
    }

    /// An `echo` or `restart` row back from its JSON line (for replotting); `None` for other
    /// benches or a line without the keys a plot needs.
    pub fn from_json(v: &serde_json::Value) -> Option<Row> {
        let bench = match v.get("bench")?.as_str()? {
            "echo" => "echo",
            "restart" => "restart",
            _ => return None,
        };
        let setup = crate::system::Setup::parse(v.get("setup")?.as_str()?)
            .ok()?
            .name();
        let num = |k: &str| v.get(k).and_then(serde_json::Value::as_f64);
        let s = Summary {
            count: v.get("count")?.as_u64()?,
            median_us: num("median_us")?,
            p99_us: num("p99_us")?,
            p999_us: num("p999_us").unwrap_or(f64::NAN),
            max_us: num("max_us")?,
            min_us: f64::NAN,
        };
        let mut row = Row::new(
            bench,
            v.get("replicas")?.as_u64()? as usize,
            v.get("size")?.as_u64()?,
            s,
        );
        row.setup = setup;
        row.floor_us = num("floor_us");
        row.ratio = num("ratio");
        row.machine = v.get("machine").and_then(|m| m.as_str()).map(str::to_owned);
        Some(row)
    }
}

/// `none`, `smr`, `dmr`, `tmr`, or `nmr(n)`.
pub fn level_name(replicas: usize) -> String {
    match replicas {
        0 => "none".into(),
        1 => "smr".into(),
        2 => "dmr".into(),
        3 => "tmr".into(),
        n => format!("{n}mr"),
    }
}

/// `8 B`, `4 KiB`, `64 MiB`.
pub fn bytes_name(n: u64) -> String {
    if n >= 1 << 20 && n & ((1 << 20) - 1) == 0 {
        format!("{} MiB", n >> 20)
    } else if n >= 1 << 10 && n & ((1 << 10) - 1) == 0 {
        format!("{} KiB", n >> 10)
    } else {
        format!("{n} B")
    }
}

/// A plain text table: a header and rows of cells, columns right-aligned but the first.
pub fn table(header: &[&str], rows: &[Vec<String>]) -> String {
    let mut widths: Vec<usize> = header.iter().map(|h| h.chars().count()).collect();
    for r in rows {
        for (w, c) in widths.iter_mut().zip(r) {
            *w = (*w).max(c.chars().count());
        }
    }
    let line = |cells: &mut dyn Iterator<Item = &str>| {
        let mut s = String::new();
        for (i, (c, w)) in cells.zip(&widths).enumerate() {
            let pad = w - c.chars().count();
            if i == 0 {
                s.push_str(c);
                s.push_str(&" ".repeat(pad));
            } else {
                s.push_str("  ");
                s.push_str(&" ".repeat(pad));
                s.push_str(c);
            }
        }
        s.push('\n');
        s
    };
    let mut out = line(&mut header.iter().copied());
    out.push_str(&line(
        &mut widths
            .iter()
            .map(|&w| "-".repeat(w))
            .collect::<Vec<_>>()
            .iter()
            .map(String::as_str),
    ));
    for r in rows {
        out.push_str(&line(&mut r.iter().map(String::as_str)));
    }
    out
}

/// `12.3`, with one decimal.
pub fn us(v: f64) -> String {
    format!("{v:.1}")
}

/// Prints rows as JSON lines (`json`) or hands them to `render` for a table.
pub fn emit(rows: &[Row], json: bool, render: impl Fn(&[Row]) -> String) {
    if json {
        for r in rows {
            println!("{}", r.to_json());
        }
    } else {
        print!("{}", render(rows));
        print!("{}", steal_notes(rows));
    }
}

/// A line under the table for every row the host took CPUs from while it was measured.
pub fn steal_notes(rows: &[Row]) -> String {
    let mut notes = String::new();
    for r in rows {
        let Some(ms) = r.steal_ms.filter(|&ms| ms > 0) else {
            continue;
        };
        let what = r
            .what
            .as_deref()
            .map(|w| format!(" {w}"))
            .unwrap_or_default();
        let size = match r.bench {
            "echo" | "restart" => format!(" {}", bytes_name(r.size)),
            _ => String::new(),
        };
        notes.push_str(&format!(
            "note: the host took this machine's CPUs for {ms} ms while {}{what} {}{size} ran \
             (steal, /proc/stat): a stall there is the host's, not the system's\n",
            r.bench,
            level_name(r.replicas),
        ));
    }
    notes
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn summary_in_microseconds() {
        let mut h = histogram();
        for ns in [1_000u64, 2_000, 3_000, 4_000, 100_000] {
            h.record(ns).unwrap();
        }
        let s = Summary::of(&h);
        assert_eq!(s.count, 5);
        assert!((s.median_us - 3.0).abs() < 0.01, "{s:?}");
        assert!((s.max_us - 100.0).abs() < 0.1, "{s:?}");
    }

    #[test]
    fn a_row_the_host_took_cpus_from_says_so_under_the_table() {
        let mut quiet = Row::new("echo", 3, 8, Summary::default());
        quiet.steal_ms = Some(0);
        let mut unknown = Row::new("echo", 3, 4096, Summary::default());
        unknown.steal_ms = None;
        let mut taken = Row::new("detect", 3, 8, Summary::default());
        taken.what = Some("false-positives".into());
        taken.steal_ms = Some(380);
        let notes = steal_notes(&[quiet, unknown, taken.clone()]);
        assert_eq!(notes.lines().count(), 1, "{notes}");
        assert!(
            notes.contains("380 ms while detect false-positives tmr ran"),
            "{notes}"
        );
        let v: serde_json::Value = serde_json::from_str(&taken.to_json()).unwrap();
        assert_eq!(v["steal_ms"], 380);
        // The steal over a measurement is read where `/proc/stat` is.
        assert!(Steal::start().ms().is_some());
    }

    #[test]
    fn json_row_has_the_required_keys() {
        let r = Row::new("echo", 3, 8, Summary::default());
        let v: serde_json::Value = serde_json::from_str(&r.to_json()).unwrap();
        for k in [
            "bench",
            "replicas",
            "size",
            "count",
            "median_us",
            "p99_us",
            "max_us",
        ] {
            assert!(v.get(k).is_some(), "missing {k}: {v}");
        }
        assert!(v.get("floor_us").is_none());
    }

    #[test]
    fn rows_come_back_from_json() {
        let mut r = Row::new("restart", 3, 1 << 20, Summary::default());
        r.setup = "rr";
        r.floor_us = Some(12.5);
        let v: serde_json::Value = serde_json::from_str(&r.to_json()).unwrap();
        let back = Row::from_json(&v).unwrap();
        assert_eq!(
            (back.bench, back.setup, back.size),
            ("restart", "rr", 1 << 20)
        );
        assert_eq!(back.floor_us, Some(12.5));
        let other = serde_json::json!({"bench": "memory", "setup": "plain"});
        assert!(Row::from_json(&other).is_none());
    }

    #[test]
    fn table_aligns_columns() {
        let t = table(
            &["level", "median"],
            &[
                vec!["tmr".into(), "1.0".into()],
                vec!["none".into(), "10.5".into()],
            ],
        );
        let lines: Vec<&str> = t.lines().collect();
        assert_eq!(lines[0], "level  median");
        assert_eq!(lines[2], "tmr       1.0");
        assert_eq!(lines[3], "none     10.5");
    }

    #[test]
    fn names() {
        assert_eq!(bytes_name(8), "8 B");
        assert_eq!(bytes_name(4096), "4 KiB");
        assert_eq!(bytes_name(64 << 20), "64 MiB");
        assert_eq!(level_name(0), "none");
        assert_eq!(level_name(3), "tmr");
    }
}
