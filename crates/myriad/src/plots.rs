//! Plots of benchmark results, as PNG and SVG: the stage breakdown of each scenario and
//! the time per tick against object count on log–log axes (the scale sweep).
//!
//! Text needs a font and a server may have none installed, so DejaVu Sans (Bitstream
//! Vera licence, `assets/DejaVuSans-LICENSE.txt`) is compiled into the binary.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, anyhow};
use plotters::coord::Shift;
use plotters::prelude::*;

use crate::bench::Row;

static FONT: &[u8] = include_bytes!("../assets/DejaVuSans.ttf");

/// Stage colours, in the order of `Row::stages`.
const STAGE_COLOURS: [RGBColor; 9] = [
    RGBColor(120, 120, 120),
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(23, 190, 207),
];

fn register_font() -> Result<()> {
    plotters::style::register_font("sans-serif", FontStyle::Normal, FONT)
        .map_err(|_| anyhow!("the bundled font could not be parsed"))
}

/// One chart to draw.
enum Chart<'a> {
    /// The stage breakdown of one scenario.
    Stages(&'a str, Vec<&'a Row>),
    /// The scale sweep.
    Sweep(Vec<&'a Row>),
}

/// Draws every plot the rows allow into `dir`; returns the files written.
pub fn draw_all(rows: &[Row], dir: &Path) -> Result<Vec<PathBuf>> {
    register_font()?;
    let mut charts = Vec::new();
    let mut scenarios: Vec<&str> = Vec::new();
    for r in rows.iter().filter(|r| r.skipped.is_none() && !r.is_sweep()) {
        if !scenarios.contains(&r.scenario.as_str()) {
            scenarios.push(&r.scenario);
        }
    }
    for s in scenarios {
        let of: Vec<&Row> = rows.iter().filter(|r| r.scenario == s && r.skipped.is_none()).collect();
        charts.push((format!("stages-{s}"), Chart::Stages(s, of)));
    }
    let sweep: Vec<&Row> = rows.iter().filter(|r| r.is_sweep() && r.skipped.is_none()).collect();
    if !sweep.is_empty() {
        charts.push(("sweep".to_string(), Chart::Sweep(sweep)));
    }
    let mut written = Vec::new();
    for (name, chart) in &charts {
        for ext in ["png", "svg"] {
            let path = dir.join(format!("{name}.{ext}"));
            draw(&path, chart).with_context(|| format!("drawing {}", path.display()))?;
            written.push(path);
        }
    }
    Ok(written)
}

/// Renders with the backend the file extension asks for.
fn draw(path: &Path, chart: &Chart) -> Result<()> {
    let size = (1000, 600);
    if path.extension().is_some_and(|e| e == "svg") {
        let area = SVGBackend::new(path, size).into_drawing_area();
        area.fill(&WHITE)?;
        draw_on(&area, chart)?;
        area.present()?;
    } else {
        let area = BitMapBackend::new(path, size).into_drawing_area();
        area.fill(&WHITE)?;
        draw_on(&area, chart)?;
        area.present()?;
    }
    Ok(())
}

fn draw_on<DB: DrawingBackend>(area: &DrawingArea<DB, Shift>, chart: &Chart) -> Result<()>
where
    DB::ErrorType: 'static,
{
    match chart {
        Chart::Stages(scenario, rows) => stage_chart(area, scenario, rows),
        Chart::Sweep(rows) => sweep_chart(area, rows),
    }
}

/// Stacked bars: one bar per backend, one segment per stage.
fn stage_chart<DB: DrawingBackend>(area: &DrawingArea<DB, Shift>, scenario: &str, rows: &[&Row]) -> Result<()>
where
    DB::ErrorType: 'static,
{
    let top = rows.iter().map(|r| r.stages().iter().sum::<f64>()).fold(0.0, f64::max).max(1e-3) * 1.15;
    let names: Vec<String> = rows.iter().map(|r| r.label()).collect();
    let mut chart = ChartBuilder::on(area)
        .caption(format!("Scenario {scenario}: time per stage (ms, median per tick)"), ("sans-serif", 24))
        .margin(16)
        .x_label_area_size(40)
        .y_label_area_size(70)
        .build_cartesian_2d(-0.5f64..(rows.len() as f64 - 0.5), 0f64..top)?;
    chart
        .configure_mesh()
        .disable_x_mesh()
        .x_labels(rows.len())
        .x_label_formatter(&|x| {
            let i = x.round();
            if (x - i).abs() < 1e-6 && i >= 0.0 {
                names.get(i as usize).cloned().unwrap_or_default()
            } else {
                String::new()
            }
        })
        .y_desc("ms")
        .label_style(("sans-serif", 16))
        .draw()?;
    for (s, name) in crate::reference::STAGES.iter().enumerate() {
        let colour = STAGE_COLOURS[s];
        let bars = rows.iter().enumerate().map(|(i, r)| {
            let below: f64 = r.stages()[..s].iter().sum();
            let x = i as f64;
            Rectangle::new([(x - 0.3, below), (x + 0.3, below + r.stages()[s])], colour.filled())
        });
        chart
            .draw_series(bars)?
            .label(*name)
            .legend(move |(x, y)| Rectangle::new([(x, y - 5), (x + 10, y + 5)], colour.filled()));
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .label_font(("sans-serif", 14))
        .draw()?;
    Ok(())
}

/// Log–log lines: time per tick against dynamic objects, one line per backend.
fn sweep_chart<DB: DrawingBackend>(area: &DrawingArea<DB, Shift>, rows: &[&Row]) -> Result<()>
where
    DB::ErrorType: 'static,
{
    let xs = rows.iter().map(|r| r.dynamic as f64);
    let (x_lo, x_hi) = xs.clone().fold((f64::MAX, f64::MIN), |(lo, hi), x| (lo.min(x), hi.max(x)));
    let ys = rows.iter().map(|r| r.total_ms.max(1e-4));
    let (y_lo, y_hi) = ys.fold((f64::MAX, f64::MIN), |(lo, hi), y| (lo.min(y), hi.max(y)));
    let mut chart = ChartBuilder::on(area)
        .caption("Physics time per tick against dynamic objects (statics = half)", ("sans-serif", 24))
        .margin(16)
        .x_label_area_size(50)
        .y_label_area_size(70)
        .build_cartesian_2d((x_lo * 0.8..x_hi * 1.25).log_scale(), (y_lo * 0.5..y_hi * 2.0).log_scale())?;
    chart
        .configure_mesh()
        .x_desc("dynamic objects")
        .y_desc("ms per tick (median)")
        .label_style(("sans-serif", 16))
        .draw()?;
    let mut backends: Vec<&str> = Vec::new();
    for r in rows {
        if !backends.contains(&r.backend.as_str()) {
            backends.push(&r.backend);
        }
    }
    for (i, b) in backends.iter().enumerate() {
        let colour = Palette99::pick(i).to_rgba();
        let mut pts: Vec<(f64, f64)> =
            rows.iter().filter(|r| r.backend == *b).map(|r| (r.dynamic as f64, r.total_ms.max(1e-4))).collect();
        pts.sort_by(|a, b| a.0.total_cmp(&b.0));
        chart
            .draw_series(LineSeries::new(pts.clone(), colour.stroke_width(2)))?
            .label(*b)
            .legend(move |(x, y)| PathElement::new([(x, y), (x + 20, y)], colour.stroke_width(2)));
        chart.draw_series(pts.into_iter().map(|p| Circle::new(p, 4, colour.filled())))?;
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .label_font(("sans-serif", 16))
        .draw()?;
    Ok(())
}
