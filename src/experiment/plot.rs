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

/// One closed-loop run as a figure: the top panel shows the noise-free and
/// the measured θ with the scoring zone (light band) and the zone of every
/// step's first prediction (dashed); the bottom panel the irrigation and the
/// rain of every step as bars.
pub struct ClosedLoopFigure<'a> {
    pub title: &'a str,
    pub step_hours: f64,
    pub initial_theta: f64,
    pub true_theta: &'a [f64],
    pub measured_theta: &'a [f64],
    /// (low, up) in force at each step.
    pub zone: &'a [(f64, f64)],
    pub scoring_zone: (f64, f64),
    pub irrigation_mm: &'a [f64],
    pub rain_mm: &'a [f64],
}

/// Draws a [`ClosedLoopFigure`] into an SVG file.
pub fn closed_loop_chart(path: &Path, figure: &ClosedLoopFigure<'_>) -> Result<(), PlotError> {
    let fail = |e: &dyn std::fmt::Display| PlotError {
        path: path.display().to_string(),
        message: e.to_string(),
    };
    let steps = figure.true_theta.len();
    if steps == 0 {
        return Err(fail(&"nothing to draw"));
    }
    let hours = steps as f64 * figure.step_hours;
    let at = |k: usize| (k + 1) as f64 * figure.step_hours;
    let thetas = figure
        .true_theta
        .iter()
        .chain(figure.measured_theta)
        .chain([
            &figure.initial_theta,
            &figure.scoring_zone.0,
            &figure.scoring_zone.1,
        ])
        .copied()
        .filter(|v| v.is_finite());
    let (lo, hi) = thetas.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
        (a.min(v), b.max(v))
    });
    let pad = 0.05 * (hi - lo).max(1e-3);
    let root = SVGBackend::new(path, (900, 640)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| fail(&e))?;
    let (top, bottom) = root.split_vertically(400);
    let mut chart = ChartBuilder::on(&top)
        .caption(figure.title, ("sans-serif", 20))
        .margin(12)
        .x_label_area_size(30)
        .y_label_area_size(60)
        .build_cartesian_2d(0f64..hours, (lo - pad)..(hi + pad))
        .map_err(|e| fail(&e))?;
    chart
        .configure_mesh()
        .y_desc("θ [m³/m³]")
        .draw()
        .map_err(|e| fail(&e))?;
    let (low, up) = figure.scoring_zone;
    let band = RGBColor(44, 160, 44);
    chart
        .draw_series(std::iter::once(Rectangle::new(
            [(0.0, low), (hours, up)],
            band.mix(0.12).filled(),
        )))
        .map_err(|e| fail(&e))?
        .label("scoring zone")
        .legend(move |(x, y)| {
            Rectangle::new([(x, y - 5), (x + 18, y + 5)], band.mix(0.3).filled())
        });
    for side in [0, 1] {
        let points: Vec<(f64, f64)> = figure
            .zone
            .iter()
            .enumerate()
            .map(|(k, z)| (at(k), if side == 0 { z.0 } else { z.1 }))
            .filter(|p| p.1.is_finite())
            .collect();
        let series = chart
            .draw_series(DashedLineSeries::new(points, 6, 4, band.stroke_width(1)))
            .map_err(|e| fail(&e))?;
        if side == 0 {
            series
                .label("zone of the first prediction step")
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], band));
        }
    }
    let truth = PALETTE[0];
    chart
        .draw_series(LineSeries::new(
            std::iter::once((0.0, figure.initial_theta)).chain(
                figure
                    .true_theta
                    .iter()
                    .enumerate()
                    .map(|(k, &v)| (at(k), v)),
            ),
            truth.stroke_width(2),
        ))
        .map_err(|e| fail(&e))?
        .label("θ (noise-free)")
        .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], truth));
    let measured = PALETTE[3];
    chart
        .draw_series(
            figure
                .measured_theta
                .iter()
                .enumerate()
                .map(|(k, &v)| Circle::new((at(k), v), 2, measured.filled())),
        )
        .map_err(|e| fail(&e))?
        .label("θ measured")
        .legend(move |(x, y)| Circle::new((x + 9, y), 3, measured.filled()));
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperRight)
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()
        .map_err(|e| fail(&e))?;

    let top_mm = figure
        .irrigation_mm
        .iter()
        .chain(figure.rain_mm)
        .copied()
        .filter(|v| v.is_finite())
        .fold(0.1f64, f64::max);
    let mut bars = ChartBuilder::on(&bottom)
        .margin(12)
        .x_label_area_size(36)
        .y_label_area_size(60)
        .build_cartesian_2d(0f64..hours, 0f64..top_mm * 1.1)
        .map_err(|e| fail(&e))?;
    bars.configure_mesh()
        .x_desc("time [h]")
        .y_desc("mm per step")
        .draw()
        .map_err(|e| fail(&e))?;
    let width = figure.step_hours;
    for (values, color, label, offset) in [
        (figure.irrigation_mm, PALETTE[1], "irrigation", 0.0),
        (figure.rain_mm, RGBColor(128, 128, 128), "rain", 0.5),
    ] {
        bars.draw_series(
            values
                .iter()
                .enumerate()
                .filter(|(_, v)| **v > 0.0)
                .map(|(k, &v)| {
                    let x0 = k as f64 * width + offset * width;
                    Rectangle::new([(x0, 0.0), (x0 + 0.5 * width, v)], color.filled())
                }),
        )
        .map_err(|e| fail(&e))?
        .label(label)
        .legend(move |(x, y)| Rectangle::new([(x, y - 5), (x + 18, y + 5)], color.filled()));
    }
    bars.configure_series_labels()
        .position(SeriesLabelPosition::UpperRight)
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()
        .map_err(|e| fail(&e))?;
    root.present().map_err(|e| fail(&e))?;
    Ok(())
}
