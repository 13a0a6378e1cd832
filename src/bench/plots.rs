//! PNG plots of the benchmark results (plotters, bitmap backend): latency histograms and CDFs, the
//! event-interval trade-off curve. Text needs a TrueType font: the system's DejaVu Sans is read
//! at run time (no font is compiled in); without one, no plots are drawn and the report says so.

use std::path::Path;

use anyhow::Context;
use plotters::prelude::*;

use super::matching::percentile;

const FONT_PATHS: [&str; 3] = [
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/TTF/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu/DejaVuSans.ttf",
];

const SIZE: (u32, u32) = (900, 520);
const COLORS: [RGBColor; 4] = [BLUE, RED, GREEN, MAGENTA];

/// Registers a font for "sans-serif"; false when none is installed.
pub fn load_font() -> bool {
    for path in FONT_PATHS {
        if let Ok(bytes) = std::fs::read(path) {
            // plotters keeps fonts for the whole process: the bytes must live as long.
            let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
            if plotters::style::register_font("sans-serif", FontStyle::Normal, bytes).is_ok() {
                return true;
            }
        }
    }
    false
}

fn to_ms(ns: &[u64]) -> Vec<f64> {
    ns.iter().map(|&v| v as f64 / 1e6).collect()
}

/// Latency histograms of several runs on one axis (counts per bin, bars overlaid). Latencies
/// are sorted nanoseconds; the axis ends at the largest p99.5 so a few outliers do not flatten it.
pub fn histogram(path: &Path, title: &str, series: &[(String, &[u64])]) -> anyhow::Result<()> {
    let top_ns = series
        .iter()
        .filter_map(|(_, v)| percentile(v, 0.995))
        .max()
        .unwrap_or(1)
        .max(1);
    let max_x = top_ns as f64 / 1e6 * 1.05;
    const BINS: usize = 60;
    let width = max_x / BINS as f64;
    let counts: Vec<Vec<u32>> = series
        .iter()
        .map(|(_, values)| {
            let mut bins = vec![0u32; BINS];
            for ms in to_ms(values) {
                let bin = ((ms / width) as usize).min(BINS - 1);
                if let Some(count) = bins.get_mut(bin) {
                    *count += 1;
                }
            }
            bins
        })
        .collect();
    let max_y = counts.iter().flatten().copied().max().unwrap_or(1).max(1);
    let root = BitMapBackend::new(path, SIZE).into_drawing_area();
    root.fill(&WHITE)?;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 22))
        .margin(12)
        .x_label_area_size(45)
        .y_label_area_size(60)
        .build_cartesian_2d(0f64..max_x, 0u32..(max_y + max_y / 10 + 1))?;
    chart
        .configure_mesh()
        .x_desc("change → MQTT arrival, ms")
        .y_desc("changes per bin")
        .label_style(("sans-serif", 14))
        .draw()?;
    for (index, ((name, values), bins)) in series.iter().zip(&counts).enumerate() {
        let color = COLORS[index % COLORS.len()];
        let label = format!(
            "{name}: p50 {:.1} ms, p99 {:.1} ms (n = {})",
            percentile(values, 0.5).unwrap_or(0) as f64 / 1e6,
            percentile(values, 0.99).unwrap_or(0) as f64 / 1e6,
            values.len()
        );
        chart
            .draw_series(bins.iter().enumerate().map(move |(i, &count)| {
                let x0 = i as f64 * width;
                Rectangle::new([(x0, 0), (x0 + width, count)], color.mix(0.45).filled())
            }))?
            .label(label)
            .legend(move |(x, y)| Rectangle::new([(x, y - 5), (x + 12, y + 5)], color.filled()));
    }
    chart
        .configure_series_labels()
        .label_font(("sans-serif", 15))
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()?;
    root.present()
        .with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}

/// Cumulative distributions of several runs, latency on a log axis.
pub fn cdf(path: &Path, title: &str, series: &[(String, &[u64])]) -> anyhow::Result<()> {
    let all: Vec<f64> = series.iter().flat_map(|(_, v)| to_ms(v)).collect();
    let low = all.iter().copied().fold(f64::INFINITY, f64::min).max(0.1);
    let high = all.iter().copied().fold(0.0, f64::max).max(low * 2.0);
    let root = BitMapBackend::new(path, SIZE).into_drawing_area();
    root.fill(&WHITE)?;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 22))
        .margin(12)
        .x_label_area_size(45)
        .y_label_area_size(60)
        .build_cartesian_2d((low * 0.9..high * 1.1).log_scale(), 0f64..1.0)?;
    chart
        .configure_mesh()
        .x_desc("change → MQTT arrival, ms (log)")
        .y_desc("share of changes published")
        .label_style(("sans-serif", 14))
        .draw()?;
    for (index, (name, values)) in series.iter().enumerate() {
        let color = COLORS[index % COLORS.len()];
        let n = values.len().max(1) as f64;
        let points: Vec<(f64, f64)> = to_ms(values)
            .into_iter()
            .enumerate()
            .map(|(i, ms)| (ms.max(low), (i + 1) as f64 / n))
            .collect();
        chart
            .draw_series(LineSeries::new(points, color.stroke_width(2)))?
            .label(name.clone())
            .legend(move |(x, y)| PathElement::new([(x, y), (x + 14, y)], color.stroke_width(2)));
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::LowerRight)
        .label_font(("sans-serif", 15))
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()?;
    root.present()
        .with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}

/// Event interval against event p99 (top) and classic registers/s (bottom).
pub fn tradeoff(path: &Path, points: &[(u64, f64, f64)]) -> anyhow::Result<()> {
    let root = BitMapBackend::new(path, (SIZE.0, SIZE.1 + 200)).into_drawing_area();
    root.fill(&WHITE)?;
    let root = root.titled(
        "Event interval trade-off: 32 devices at 115200 8N2",
        ("sans-serif", 22),
    )?;
    let (upper, lower) = root.split_vertically((SIZE.1 + 160) / 2);
    let max_interval = points.iter().map(|p| p.0).max().unwrap_or(200) as f64 * 1.1;
    let max_p99 = points.iter().map(|p| p.1).fold(1.0, f64::max) * 1.15;
    let max_rate = points.iter().map(|p| p.2).fold(1.0, f64::max) * 1.15;
    let mut top = ChartBuilder::on(&upper)
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(70)
        .build_cartesian_2d(0f64..max_interval, 0f64..max_p99)?;
    top.configure_mesh()
        .x_desc("event_interval_ms")
        .y_desc("event p99, ms")
        .label_style(("sans-serif", 14))
        .draw()?;
    top.draw_series(LineSeries::new(
        points.iter().map(|p| (p.0 as f64, p.1)),
        BLUE.stroke_width(2),
    ))?;
    top.draw_series(
        points
            .iter()
            .map(|p| Circle::new((p.0 as f64, p.1), 4, BLUE.filled())),
    )?;
    let mut bottom = ChartBuilder::on(&lower)
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(70)
        .build_cartesian_2d(0f64..max_interval, 0f64..max_rate)?;
    bottom
        .configure_mesh()
        .x_desc("event_interval_ms")
        .y_desc("classic registers/s")
        .label_style(("sans-serif", 14))
        .draw()?;
    bottom.draw_series(LineSeries::new(
        points.iter().map(|p| (p.0 as f64, p.2)),
        RED.stroke_width(2),
    ))?;
    bottom.draw_series(
        points
            .iter()
            .map(|p| Circle::new((p.0 as f64, p.2), 4, RED.filled())),
    )?;
    root.present()
        .with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}
