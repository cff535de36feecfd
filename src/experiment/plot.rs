//! SVG figures of the experiments, drawn with plotters.

use std::path::Path;

use plotters::prelude::*;

/// One line of a figure.
pub struct Line<'a> {
    pub label: &'a str,
    pub values: &'a [f64],
    pub color: RGBColor,
}

/// Colours for successive lines.
pub const PALETTE: [RGBColor; 5] = [
    RGBColor(0, 0, 0),
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
];

/// A figure could not be written.
#[derive(Debug, thiserror::Error)]
#[error("cannot draw {path}: {message}")]
pub struct PlotError {
    pub path: String,
    pub message: String,
}

/// Draws `lines` against the step index (hours on the x axis, `step_hours` per
/// step) into an SVG file.
pub fn line_chart(
    path: &Path,
    title: &str,
    y_label: &str,
    step_hours: f64,
    lines: &[Line<'_>],
) -> Result<(), PlotError> {
    let fail = |e: &dyn std::fmt::Display| PlotError {
        path: path.display().to_string(),
        message: e.to_string(),
    };
    let len = lines.iter().map(|l| l.values.len()).max().unwrap_or(0);
    let (lo, hi) = lines
        .iter()
        .flat_map(|l| l.values.iter().copied())
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
            (a.min(v), b.max(v))
        });
    if len == 0 || !lo.is_finite() {
        return Err(fail(&"nothing to draw"));
    }
    let pad = 0.05 * (hi - lo).max(1e-6);
    let root = SVGBackend::new(path, (900, 420)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| fail(&e))?;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 20))
        .margin(12)
        .x_label_area_size(36)
        .y_label_area_size(56)
        .build_cartesian_2d(0f64..len as f64 * step_hours, (lo - pad)..(hi + pad))
        .map_err(|e| fail(&e))?;
    chart
        .configure_mesh()
        .x_desc("time [h]")
        .y_desc(y_label)
        .draw()
        .map_err(|e| fail(&e))?;
    for line in lines {
        let color = line.color;
        chart
            .draw_series(LineSeries::new(
                line.values
                    .iter()
                    .enumerate()
                    .filter(|(_, v)| v.is_finite())
                    .map(|(k, &v)| (k as f64 * step_hours, v)),
                color.stroke_width(2),
            ))
            .map_err(|e| fail(&e))?
            .label(line.label)
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], color));
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()
        .map_err(|e| fail(&e))?;
    root.present().map_err(|e| fail(&e))?;
    Ok(())
}
