//! SVG plots (plotters, SVG backend only: text is written as SVG `<text>`, so no font library
//! is needed at build or run time).

use std::path::Path;

use anyhow::{anyhow, Result};
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

fn log_log(
    path: &Path,
    title: &str,
    x_desc: &str,
    y_desc: &str,
    x_label: impl Fn(&f64) -> String,
    series: &[Series],
) -> Result<()> {
    let all = series.iter().flat_map(|s| s.points.iter());
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
    let root = SVGBackend::new(path, (900, 560)).into_drawing_area();
    root.fill(&WHITE).map_err(err)?;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 22))
        .margin(16)
        .x_label_area_size(48)
        .y_label_area_size(64)
        .build_cartesian_2d(
            (x0 / 1.5..x1 * 1.5).log_scale(),
            (y0 / 1.5..y1 * 1.5).log_scale(),
        )
        .map_err(err)?;
    chart
        .configure_mesh()
        .x_desc(x_desc)
        .y_desc(y_desc)
        .x_label_formatter(&x_label)
        .y_label_formatter(&|y| format!("{y}"))
        .draw()
        .map_err(err)?;
    for s in series {
        let color = PALETTE[s.color % PALETTE.len()];
        let style = ShapeStyle {
            color: color.to_rgba(),
            filled: true,
            stroke_width: 2,
        };
        if let Some((dash, gap)) = s.dash {
            chart
                .draw_series(DashedLineSeries::new(
                    s.points.iter().copied(),
                    dash,
                    gap,
                    style,
                ))
                .map_err(err)?
                .label(s.label.clone())
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], color));
        } else {
            chart
                .draw_series(LineSeries::new(s.points.iter().copied(), style))
                .map_err(err)?
                .label(s.label.clone())
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], color));
        }
        chart
            .draw_series(
                s.points
                    .iter()
                    .map(|&(x, y)| Circle::new((x, y), 3, color.filled())),
            )
            .map_err(err)?;
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperLeft)
        .background_style(WHITE.mix(0.9))
        .border_style(BLACK)
        .draw()
        .map_err(err)?;
    root.present().map_err(err)?;
    Ok(())
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
    log_log(
        path,
        "s3res round trip by replication level (median)",
        "frame payload",
        "round trip, µs",
        axis_bytes,
        &series,
    )
}

/// Axis label for a byte count: the log axis puts its marks at powers of ten.
fn axis_bytes(x: &f64) -> String {
    let n = x.round() as u64;
    match n {
        n if n >= 1_000_000_000 => format!("{} GB", n / 1_000_000_000),
        n if n >= 1_000_000 => format!("{} MB", n / 1_000_000),
        n if n >= 1_000 => format!("{} kB", n / 1_000),
        n => format!("{n} B"),
    }
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
    log_log(
        path,
        "s3res TMR replica restart by component state",
        "resident state",
        "µs",
        axis_bytes,
        &series,
    )
}
