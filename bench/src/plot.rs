//! SVG plots (plotters, SVG backend only: text is written as SVG `<text>`, so no font library
//! is needed at build or run time).
//!
//! Every figure has a title, a subtitle saying which setup, how many samples per point and on
//! what machine, and a red warning line when a result contradicts its baseline (a redundancy
//! level faster than no voter, a restart faster than its fork + touch floor): with few samples
//! or on a busy machine that happens, and a reader must not take it for a finding. Log axes put
//! their ticks at the sizes measured (KiB/MiB) and at 1-2-5 times (µs below 1 ms, then ms),
//! leaving out a tick whose label would touch its neighbour's.

use std::path::Path;

use anyhow::{anyhow, Result};
use plotters::coord::combinators::BindKeyPoints as _;
use plotters::element::DashedPathElement;
use plotters::prelude::*;

use crate::report::{self, Row};

const PALETTE: [RGBColor; 6] = [
    RGBColor(0x44, 0x44, 0x44),
    RGBColor(0x1f, 0x77, 0xb4),
    RGBColor(0x2c, 0xa0, 0x2c),
    RGBColor(0xd6, 0x27, 0x28),
    RGBColor(0x94, 0x67, 0xbd),
    RGBColor(0xff, 0x7f, 0x0e),
];

/// Figure size, pixels.
const WIDTH: u32 = 960;
const HEIGHT: u32 = 620;
/// Room for the y tick labels and for the x tick labels, pixels.
const Y_LABELS: u32 = 80;
const X_LABELS: u32 = 48;
const MARGIN: u32 = 16;
/// Approximate width of one character of a 12-pixel tick label, and the least gap between two.
const CHAR_PX: f64 = 7.0;
const LABEL_GAP_PX: f64 = 14.0;
/// Approximate height of a tick label, pixels (the least distance between two y ticks).
const LABEL_HEIGHT_PX: f64 = 18.0;
/// Longest subtitle or warning line, characters (a longer one is wrapped).
const LINE_CHARS: usize = 120;
/// The legend under the chart: columns, height of a row, length of a line sample (pixels).
const LEGEND_COLUMNS: usize = 2;
const LEGEND_ROW_PX: i32 = 18;
const LEGEND_SAMPLE_PX: i32 = 28;

fn err<E: std::fmt::Display>(e: E) -> anyhow::Error {
    anyhow!("plotting: {e}")
}

/// A labelled line with points: `(x, y)` on log-log axes.
struct Series {
    label: String,
    points: Vec<(f64, f64)>,
    /// Index into the palette.
    color: usize,
    /// `(dash, gap)` in pixels; `None` for a solid line.
    dash: Option<(u32, u32)>,
}

/// What one figure shows.
struct Figure<'a> {
    title: &'a str,
    /// Setup, count and machine.
    subtitle: String,
    /// Results that contradict their baseline, one line each.
    warnings: Vec<String>,
    x_desc: &'a str,
    y_desc: &'a str,
    series: Vec<Series>,
}

fn log_log(path: &Path, fig: &Figure) -> Result<()> {
    let all = fig.series.iter().flat_map(|s| s.points.iter());
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for &(x, y) in all {
        x0 = x0.min(x);
        x1 = x1.max(x);
        y0 = y0.min(y);
        y1 = y1.max(y);
    }
    if x0 > x1 {
        return Err(anyhow!("nothing to plot"));
    }
    let (x_lo, x_hi) = (x0 / 1.5, x1 * 1.5);
    let (y_lo, y_hi) = (y0 / 1.5, y1 * 1.5);

    let root = SVGBackend::new(path, (WIDTH, HEIGHT)).into_drawing_area();
    root.fill(&WHITE).map_err(err)?;
    let mut area = root.titled(fig.title, ("sans-serif", 22)).map_err(err)?;
    for line in wrap(&fig.subtitle, LINE_CHARS) {
        let style = ("sans-serif", 14)
            .into_font()
            .color(&RGBColor(0x55, 0x55, 0x55));
        area = area.titled(&line, style).map_err(err)?;
    }
    for w in &fig.warnings {
        for line in wrap(&format!("warning: {w}"), LINE_CHARS) {
            let style = ("sans-serif", 14)
                .into_font()
                .color(&RGBColor(0xc0, 0x00, 0x00));
            area = area.titled(&line, style).map_err(err)?;
        }
    }

    let legend_rows = fig.series.len().div_ceil(LEGEND_COLUMNS) as i32;
    let chart_px = area.dim_in_pixel().1 as i32 - (16 + legend_rows * LEGEND_ROW_PX);
    let (area, legend_area) = area.split_vertically(chart_px.max(100));

    // Tick positions, thinned so that no two labels touch.
    let x_px = f64::from(WIDTH - Y_LABELS - 2 * MARGIN);
    let y_px = f64::from(chart_px.max(100) as u32 - X_LABELS - 2 * MARGIN);
    let mut sizes: Vec<f64> = fig
        .series
        .iter()
        .flat_map(|s| s.points.iter().map(|p| p.0))
        .collect();
    sizes.sort_by(f64::total_cmp);
    sizes.dedup();
    let x_ticks = thin(&sizes, x_lo, x_hi, x_px, |x| {
        bytes_label(*x).chars().count() as f64 * CHAR_PX + LABEL_GAP_PX
    });
    let y_ticks = thin(&one_two_five(y_lo, y_hi), y_lo, y_hi, y_px, |_| {
        LABEL_HEIGHT_PX
    });

    let mut chart = ChartBuilder::on(&area)
        .margin(MARGIN)
        .x_label_area_size(X_LABELS)
        .y_label_area_size(Y_LABELS)
        .build_cartesian_2d(
            (x_lo..x_hi).log_scale().with_key_points(x_ticks),
            (y_lo..y_hi).log_scale().with_key_points(y_ticks),
        )
        .map_err(err)?;
    chart
        .configure_mesh()
        .x_desc(fig.x_desc)
        .y_desc(fig.y_desc)
        .x_label_formatter(&|x| bytes_label(*x))
        .y_label_formatter(&|y| time_label(*y))
        .draw()
        .map_err(err)?;
    for s in &fig.series {
        let color = PALETTE[s.color % PALETTE.len()];
        let style = ShapeStyle {
            color: color.to_rgba(),
            filled: true,
            stroke_width: 2,
        };
        let drawn = match s.dash {
            Some((dash, gap)) => chart
                .draw_series(DashedLineSeries::new(
                    s.points.iter().copied(),
                    dash,
                    gap,
                    style,
                ))
                .map_err(err)?,
            None => chart
                .draw_series(LineSeries::new(s.points.iter().copied(), style))
                .map_err(err)?,
        };
        drawn.label(s.label.clone());
        chart
            .draw_series(
                s.points
                    .iter()
                    .map(|&(x, y)| Circle::new((x, y), 3, color.filled())),
            )
            .map_err(err)?;
    }
    legend(&legend_area, &fig.series)?;
    root.present().map_err(err)?;
    Ok(())
}

/// The legend, below the chart (so it never hides a point): two columns of a line sample drawn
/// as the series is (solid, dashed or dotted) and its label.
fn legend(area: &DrawingArea<SVGBackend, plotters::coord::Shift>, series: &[Series]) -> Result<()> {
    let rows = series.len().div_ceil(LEGEND_COLUMNS);
    let column_px = (WIDTH - 2 * MARGIN) as i32 / LEGEND_COLUMNS as i32;
    for (i, s) in series.iter().enumerate() {
        let (col, row) = ((i / rows) as i32, (i % rows) as i32);
        let x = MARGIN as i32 + Y_LABELS as i32 / 2 + col * column_px;
        let y = 8 + row * LEGEND_ROW_PX + LEGEND_ROW_PX / 2;
        let color = PALETTE[s.color % PALETTE.len()];
        let style = ShapeStyle {
            color: color.to_rgba(),
            filled: true,
            stroke_width: 2,
        };
        // A solid line is one dash as long as the sample.
        let (dash, gap) = s.dash.unwrap_or((LEGEND_SAMPLE_PX as u32, 1));
        area.draw(&DashedPathElement::new(
            vec![(x, y), (x + LEGEND_SAMPLE_PX, y)],
            dash,
            gap,
            style,
        ))
        .map_err(err)?;
        area.draw(&Circle::new(
            (x + LEGEND_SAMPLE_PX / 2, y),
            3,
            color.filled(),
        ))
        .map_err(err)?;
        area.draw(&Text::new(
            s.label.clone(),
            (x + LEGEND_SAMPLE_PX + 8, y - 7),
            ("sans-serif", 13),
        ))
        .map_err(err)?;
    }
    Ok(())
}

/// `values` (ascending) that lie in `lo..hi`, keeping each only if its label, `extent(v)`
/// pixels long, does not reach the previous kept one's on an axis `px` pixels long (log scale).
fn thin(values: &[f64], lo: f64, hi: f64, px: f64, extent: impl Fn(&f64) -> f64) -> Vec<f64> {
    let at = |v: f64| (v.ln() - lo.ln()) / (hi.ln() - lo.ln()) * px;
    let mut kept: Vec<f64> = Vec::new();
    for &v in values.iter().filter(|v| **v >= lo && **v <= hi) {
        let fits = kept
            .last()
            .is_none_or(|&k| at(v) - at(k) >= (extent(&v) + extent(&k)) / 2.0);
        if fits {
            kept.push(v);
        }
    }
    kept
}

/// 1, 2, 5, 10, 20, 50, … within `lo..=hi`.
fn one_two_five(lo: f64, hi: f64) -> Vec<f64> {
    let mut out = Vec::new();
    let mut decade = 10f64.powf(lo.log10().floor());
    while decade <= hi {
        for m in [1.0, 2.0, 5.0] {
            let v = decade * m;
            if v >= lo && v <= hi {
                out.push(v);
            }
        }
        decade *= 10.0;
    }
    out
}

/// A byte count as measured: `256 KiB`, `8 MiB`, `64 B`.
fn bytes_label(x: f64) -> String {
    report::bytes_name(x.round() as u64)
}

/// A time in microseconds: `2 µs`, `500 µs`, `1 ms`, `20 ms`, `1.5 s`.
fn time_label(us: f64) -> String {
    let num = |v: f64| {
        if (v - v.round()).abs() < 1e-9 {
            format!("{}", v.round())
        } else {
            format!("{v:.1}")
        }
    };
    if us >= 1e6 {
        format!("{} s", num(us / 1e6))
    } else if us >= 1e3 {
        format!("{} ms", num(us / 1e3))
    } else {
        format!("{} µs", num(us))
    }
}

/// Splits `text` at spaces into lines of at most `max` characters (a longer word stays whole).
fn wrap(text: &str, max: usize) -> Vec<String> {
    let mut lines = vec![String::new()];
    for word in text.split(' ') {
        let last = lines.last_mut().expect("lines is never empty");
        if !last.is_empty() && last.chars().count() + 1 + word.chars().count() > max {
            lines.push(word.to_owned());
        } else {
            if !last.is_empty() {
                last.push(' ');
            }
            last.push_str(word);
        }
    }
    lines
}

/// `setup plain, rr · 20000 round trips per point · <machine>`.
fn subtitle(rows: &[Row], what: &str) -> String {
    let mut setups: Vec<&str> = rows.iter().map(|r| r.setup).collect();
    setups.sort();
    setups.dedup();
    let lo = rows.iter().map(|r| r.count).min().unwrap_or(0);
    let hi = rows.iter().map(|r| r.count).max().unwrap_or(0);
    let count = if lo == hi {
        format!("{lo}")
    } else {
        format!("{lo}–{hi}")
    };
    let machine = rows
        .iter()
        .find_map(|r| r.machine.clone())
        .unwrap_or_else(|| "machine not recorded".to_owned());
    format!(
        "setup {} · {count} {what} per point · {machine}",
        setups.join(", ")
    )
}

/// Sizes (and setups) at which a redundancy level's median round trip is below the no-voter
/// median of the same size and setup.
pub fn faster_than_baseline(rows: &[Row]) -> Vec<String> {
    let mut found = Vec::new();
    for r in rows.iter().filter(|r| r.replicas > 0) {
        let base = rows
            .iter()
            .find(|b| b.replicas == 0 && b.size == r.size && b.setup == r.setup);
        if let Some(b) = base.filter(|b| r.median_us < b.median_us) {
            found.push(format!(
                "{} ({}) at {} measured faster than no voter ({} vs {}): too few samples or a \
                 busy machine; do not read it as a result",
                report::level_name(r.replicas),
                r.setup,
                report::bytes_name(r.size),
                time_label(r.median_us),
                time_label(b.median_us)
            ));
        }
    }
    found
}

/// Figure 3: median round trip by frame size, one line per replication level (and setup).
pub fn round_trip(rows: &[Row], path: &Path) -> Result<()> {
    let mut keys: Vec<(&str, usize)> = rows.iter().map(|r| (r.setup, r.replicas)).collect();
    keys.sort();
    keys.dedup();
    let several_setups = keys.iter().any(|k| k.0 != keys[0].0);
    let series: Vec<Series> = keys
        .iter()
        .map(|&(setup, n)| Series {
            label: if several_setups {
                format!("{} ({setup})", report::level_name(n))
            } else {
                report::level_name(n)
            },
            points: rows
                .iter()
                .filter(|r| r.setup == setup && r.replicas == n)
                .map(|r| (r.size as f64, r.median_us))
                .collect(),
            color: n,
            dash: match setup {
                "plain" => None,
                "rr" => Some((8, 4)),
                _ => Some((2, 4)),
            },
        })
        .collect();
    let warnings = faster_than_baseline(rows);
    for w in &warnings {
        tracing::warn!("{w}");
    }
    log_log(
        path,
        &Figure {
            title: "s3res round trip by replication level (median)",
            subtitle: subtitle(rows, "round trips"),
            warnings,
            x_desc: "frame payload",
            y_desc: "round trip",
            series,
        },
    )
}

/// Sizes (and setups) at which the median restart is below its fork + touch floor.
pub fn faster_than_floor(rows: &[Row]) -> Vec<String> {
    rows.iter()
        .filter_map(|r| {
            let floor = r.floor_us.filter(|&f| r.median_us < f)?;
            Some(format!(
                "restart ({}) at {} measured faster than its floor ({} vs {}): too few samples \
                 or a busy machine",
                r.setup,
                report::bytes_name(r.size),
                time_label(r.median_us),
                time_label(floor)
            ))
        })
        .collect()
}

/// Figure 4: restart (detection → ready) and the fork+touch floor by state size, per setup.
pub fn restart(rows: &[Row], path: &Path) -> Result<()> {
    let mut setups: Vec<&str> = rows.iter().map(|r| r.setup).collect();
    setups.sort();
    setups.dedup();
    let mut series = Vec::new();
    for (k, &setup) in setups.iter().enumerate() {
        let of = |r: &&Row| r.setup == setup;
        series.push(Series {
            label: format!("restart by fork, detection → ready, median ({setup})"),
            points: rows
                .iter()
                .filter(of)
                .map(|r| (r.size as f64, r.median_us))
                .collect(),
            color: 3 + k,
            dash: None,
        });
        series.push(Series {
            label: format!("floor: fork + touch every page, median ({setup})"),
            points: rows
                .iter()
                .filter(of)
                .filter_map(|r| r.floor_us.map(|f| (r.size as f64, f)))
                .collect(),
            color: 3 + k,
            dash: Some((8, 4)),
        });
    }
    let warnings = faster_than_floor(rows);
    for w in &warnings {
        tracing::warn!("{w}");
    }
    log_log(
        path,
        &Figure {
            title: "s3res TMR replica restart by component state",
            subtitle: subtitle(rows, "restarts"),
            warnings,
            x_desc: "resident state",
            y_desc: "time",
            series,
        },
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::report::Summary;

    #[test]
    fn ticks_do_not_overlap_and_cover_the_range() {
        let sizes = [8.0, 64.0, 1024.0, 8192.0, 65536.0, 262144.0, 1048576.0];
        let kept = thin(&sizes, 5.0, 2e6, 800.0, |x| {
            bytes_label(*x).len() as f64 * CHAR_PX + LABEL_GAP_PX
        });
        assert_eq!(kept.first(), Some(&8.0));
        assert!(kept.contains(&262144.0), "{kept:?}");
        // 8, 9 and 10 MiB cannot all be labelled on one 800-pixel axis from 200 KiB up.
        let close = [262144.0, 8388608.0, 9437184.0, 10485760.0];
        let kept = thin(&close, 2e5, 1.6e7, 800.0, |x| {
            bytes_label(*x).len() as f64 * CHAR_PX + LABEL_GAP_PX
        });
        assert_eq!(kept, vec![262144.0, 8388608.0]);
    }

    #[test]
    fn labels_in_binary_sizes_and_readable_times() {
        assert_eq!(bytes_label(262144.0), "256 KiB");
        assert_eq!(bytes_label(8388608.0), "8 MiB");
        assert_eq!(time_label(200.0), "200 µs");
        assert_eq!(time_label(2000.0), "2 ms");
        assert_eq!(time_label(1500.0), "1.5 ms");
        assert_eq!(one_two_five(3.0, 120.0), vec![5.0, 10.0, 20.0, 50.0, 100.0]);
        assert_eq!(wrap("a bb ccc", 4), vec!["a bb", "ccc"]);
    }

    #[test]
    fn a_level_faster_than_no_voter_is_called_out() {
        let row = |n: usize, median: f64| {
            Row::new(
                "echo",
                n,
                8,
                Summary {
                    count: 10,
                    median_us: median,
                    ..Summary::default()
                },
            )
        };
        let rows = [row(0, 10.0), row(1, 8.0), row(3, 40.0)];
        let w = faster_than_baseline(&rows);
        assert_eq!(w.len(), 1, "{w:?}");
        assert!(w[0].starts_with("smr (plain) at 8 B"), "{w:?}");
    }
}
