//! The dashboard's chart of a field, drawn server-side as SVG with plotters:
//! measured θ, the true θ of a simulated field, the zone band, the latest
//! predicted θ over the horizon, irrigation and forecast rain as bars.

use chrono::{DateTime, TimeDelta, Utc};
use plotters::prelude::*;

use super::wire::{Forecast, Measurement, Setpoint};

/// What one chart shows.
pub struct ChartData<'a> {
    pub title: &'a str,
    pub now: DateTime<Utc>,
    pub hours: f64,
    pub measurements: &'a [Measurement],
    pub setpoints: &'a [Setpoint],
    pub forecast: Option<&'a Forecast>,
}

fn hours_between(a: DateTime<Utc>, b: DateTime<Utc>) -> f64 {
    (b - a).num_milliseconds() as f64 / 3.6e6
}

/// The SVG text of the chart; x is hours relative to now (the past negative,
/// the horizon positive).
pub fn render(data: &ChartData<'_>) -> Result<String, String> {
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, (900, 520)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| e.to_string())?;
        let (top, bottom) = root.split_vertically(360);
        let latest = data.setpoints.last();
        let ahead = latest.map_or(0.0, |s| {
            hours_between(data.now, s.time)
                + s.plan.len() as f64 * hours_between(s.valid_from, s.valid_until)
        });
        let x0 = -data.hours;
        let x1 = ahead.max(1.0);
        let mut values: Vec<f64> = data
            .measurements
            .iter()
            .flat_map(|m| [Some(m.theta), m.true_theta])
            .flatten()
            .collect();
        if let Some(s) = latest {
            values.extend(s.predicted_theta.iter().copied());
            values.extend(s.predicted_theta_dry.iter().copied());
            values.extend(s.zone.iter().flat_map(|z| [z[0], z[1]]));
        }
        let (lo, hi) = values
            .iter()
            .filter(|v| v.is_finite())
            .fold((0.15f64, 0.25f64), |(a, b), v| (a.min(*v), b.max(*v)));
        let mut chart = ChartBuilder::on(&top)
            .caption(data.title, ("sans-serif", 18))
            .margin(10)
            .x_label_area_size(28)
            .y_label_area_size(56)
            .build_cartesian_2d(x0..x1, (lo - 0.01)..(hi + 0.01))
            .map_err(|e| e.to_string())?;
        chart
            .configure_mesh()
            .max_light_lines(2)
            .y_desc("θ [m³/m³]")
            .draw()
            .map_err(|e| e.to_string())?;
        let green = RGBColor(44, 160, 44);
        // the zone in force: each setpoint's first-step zone until the next
        for (i, s) in data.setpoints.iter().enumerate() {
            let Some(z) = s.zone.first() else { continue };
            let from = hours_between(data.now, s.time).max(x0);
            let to = data
                .setpoints
                .get(i + 1)
                .map_or(x1, |n| hours_between(data.now, n.time));
            if to > from {
                chart
                    .draw_series(std::iter::once(Rectangle::new(
                        [(from, z[0]), (to, z[1])],
                        green.mix(0.15).filled(),
                    )))
                    .map_err(|e| e.to_string())?;
            }
        }
        // the latest plan's zone over the horizon, dashed
        if let Some(s) = latest {
            let step = hours_between(s.valid_from, s.valid_until);
            let start = hours_between(data.now, s.time);
            for side in [0, 1] {
                let pts: Vec<(f64, f64)> = s
                    .zone
                    .iter()
                    .enumerate()
                    .map(|(k, z)| (start + (k + 1) as f64 * step, z[side]))
                    .collect();
                let series = chart
                    .draw_series(DashedLineSeries::new(pts, 5, 4, green.stroke_width(1)))
                    .map_err(|e| e.to_string())?;
                if side == 0 {
                    series
                        .label("zone (shaded: in force; dashed: the plan's)")
                        .legend(move |(x, y)| {
                            Rectangle::new([(x, y - 4), (x + 16, y + 4)], green.mix(0.3).filled())
                        });
                }
            }
            let predicted: Vec<(f64, f64)> = s
                .predicted_theta
                .iter()
                .enumerate()
                .map(|(k, v)| (start + (k + 1) as f64 * step, *v))
                .filter(|p| p.1.is_finite())
                .collect();
            let orange = RGBColor(255, 127, 14);
            chart
                .draw_series(LineSeries::new(predicted, orange.stroke_width(2)))
                .map_err(|e| e.to_string())?
                .label("predicted θ (planned irrigation)")
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], orange));
            let dry: Vec<(f64, f64)> = s
                .predicted_theta_dry
                .iter()
                .enumerate()
                .map(|(k, v)| (start + (k + 1) as f64 * step, *v))
                .filter(|p| p.1.is_finite())
                .collect();
            if !dry.is_empty() {
                let red = RGBColor(214, 39, 40);
                chart
                    .draw_series(DashedLineSeries::new(dry, 6, 4, red.stroke_width(2)))
                    .map_err(|e| e.to_string())?
                    .label("predicted θ without irrigation")
                    .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], red));
            }
        }
        let truth: Vec<(f64, f64)> = data
            .measurements
            .iter()
            .filter_map(|m| Some((hours_between(data.now, m.time), m.true_theta?)))
            .collect();
        if !truth.is_empty() {
            chart
                .draw_series(LineSeries::new(truth, BLACK.stroke_width(2)))
                .map_err(|e| e.to_string())?
                .label("true θ")
                .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], BLACK));
        }
        let blue = RGBColor(31, 119, 180);
        chart
            .draw_series(
                data.measurements.iter().map(|m| {
                    Circle::new((hours_between(data.now, m.time), m.theta), 2, blue.filled())
                }),
            )
            .map_err(|e| e.to_string())?
            .label("measured θ")
            .legend(move |(x, y)| Circle::new((x + 8, y), 3, blue.filled()));
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::UpperLeft)
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .draw()
            .map_err(|e| e.to_string())?;

        // the lower panel, per control period: irrigation given (left half),
        // the rain each cycle planned with for its own period (right half),
        // the latest cycle's rain forecast over its horizon, and ET0
        let periods = water_periods(data, x0, x1);
        let top_mm = periods
            .iter()
            .map(|p| p.irrigation_mm.max(p.rain_mm).max(p.et0_mm))
            .fold(0.5f64, f64::max);
        let mut lower = ChartBuilder::on(&bottom)
            .margin(10)
            .x_label_area_size(30)
            .y_label_area_size(56)
            .build_cartesian_2d(x0..x1, 0.0..top_mm * 1.25)
            .map_err(|e| e.to_string())?;
        lower
            .configure_mesh()
            .max_light_lines(2)
            .x_desc("hours from now")
            .y_desc("mm per period")
            .draw()
            .map_err(|e| e.to_string())?;
        let rain_past = RGBColor(23, 190, 207);
        let rain_ahead = RGBColor(150, 150, 150);
        let brown = RGBColor(140, 86, 75);
        let bar = |a: f64, b: f64, v: f64, c: RGBColor| {
            Rectangle::new([(a.max(x0), 0.0), (b.min(x1), v)], c.filled())
        };
        lower
            .draw_series(periods.iter().filter(|p| p.irrigation_mm > 0.0).map(|p| {
                bar(
                    p.from,
                    p.from + 0.5 * (p.to - p.from),
                    p.irrigation_mm,
                    blue,
                )
            }))
            .map_err(|e| e.to_string())?
            .label("irrigation")
            .legend(move |(x, y)| Rectangle::new([(x, y - 4), (x + 16, y + 4)], blue.filled()));
        for (ahead, colour, label) in [
            (false, rain_past, "rain (as forecast for its period)"),
            (true, rain_ahead, "forecast rain"),
        ] {
            lower
                .draw_series(
                    periods
                        .iter()
                        .filter(|p| p.ahead == ahead && p.rain_mm > 0.0)
                        .map(|p| bar(p.from + 0.5 * (p.to - p.from), p.to, p.rain_mm, colour)),
                )
                .map_err(|e| e.to_string())?
                .label(label)
                .legend(move |(x, y)| {
                    Rectangle::new([(x, y - 4), (x + 16, y + 4)], colour.filled())
                });
        }
        let et0: Vec<(f64, f64)> = periods
            .iter()
            .flat_map(|p| [(p.from, p.et0_mm), (p.to, p.et0_mm)])
            .filter(|q| q.0 >= x0 && q.0 <= x1)
            .collect();
        lower
            .draw_series(LineSeries::new(et0, brown.stroke_width(2)))
            .map_err(|e| e.to_string())?
            .label("ET0 (past and forecast)")
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], brown));
        lower
            .configure_series_labels()
            .position(SeriesLabelPosition::UpperLeft)
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .draw()
            .map_err(|e| e.to_string())?;
        root.present().map_err(|e| e.to_string())?;
    }
    Ok(svg)
}

/// One control period of the lower panel, in hours from now.
#[derive(Debug, Clone, PartialEq)]
struct WaterPeriod {
    from: f64,
    to: f64,
    irrigation_mm: f64,
    rain_mm: f64,
    et0_mm: f64,
    /// A forecast period of the latest cycle (not yet begun when it ran).
    ahead: bool,
}

/// The periods of the lower panel: every setpoint's own period (its
/// irrigation and the weather its cycle planned with), then the latest
/// cycle's forecast for the rest of its horizon; a latest setpoint without
/// recorded weather (stored before setpoints recorded it) falls back to the
/// latest stored forecast.
fn water_periods(data: &ChartData<'_>, x0: f64, x1: f64) -> Vec<WaterPeriod> {
    let mut out = Vec::new();
    for s in data.setpoints {
        let from = hours_between(data.now, s.valid_from);
        let to = hours_between(data.now, s.valid_until);
        if to <= x0 || from >= x1 {
            continue;
        }
        out.push(WaterPeriod {
            from,
            to,
            irrigation_mm: s.amount_mm,
            rain_mm: s.rain_mm.first().copied().unwrap_or(0.0),
            et0_mm: s.et0_mm.first().copied().unwrap_or(0.0),
            ahead: false,
        });
    }
    let latest = data.setpoints.last();
    match latest {
        Some(s) if !s.rain_mm.is_empty() => {
            let step = hours_between(s.valid_from, s.valid_until);
            let start = hours_between(data.now, s.valid_from);
            for k in 1..s.rain_mm.len().min(s.et0_mm.len()) {
                out.push(WaterPeriod {
                    from: start + k as f64 * step,
                    to: start + (k + 1) as f64 * step,
                    irrigation_mm: 0.0,
                    rain_mm: s.rain_mm[k],
                    et0_mm: s.et0_mm[k],
                    ahead: true,
                });
            }
        }
        _ => {
            if let Some(f) = data.forecast {
                let step = f.step_s / 3600.0;
                let start = hours_between(data.now, f.start);
                for (k, (p, e)) in f.precip_mm.iter().zip(&f.et0_mm).enumerate() {
                    let from = start + k as f64 * step;
                    if from >= 0.0 && from <= x1 {
                        out.push(WaterPeriod {
                            from,
                            to: from + step,
                            irrigation_mm: 0.0,
                            rain_mm: *p,
                            et0_mm: *e,
                            ahead: true,
                        });
                    }
                }
            }
        }
    }
    out.retain(|p| p.from.is_finite() && p.to.is_finite());
    out
}

/// What the profile chart shows: the estimate's θ against depth with its
/// ±2 sd band, and a simulated plant's true θ.
pub struct ProfileData<'a> {
    pub title: &'a str,
    /// (depth [m], mean θ, sd) per cell, top first.
    pub estimate: &'a [(f64, f64, f64)],
    /// (depth [m], θ) per cell.
    pub truth: &'a [(f64, f64)],
    /// The sensors' (id, depth).
    pub sensors: &'a [(String, f64)],
    /// The zone in force now (θ), drawn as a band over the rooting depth.
    pub zone: Option<(f64, f64, f64)>,
}

/// The SVG text of the profile chart: θ on x, depth downwards on y.
pub fn render_profile(data: &ProfileData<'_>) -> Result<String, String> {
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, (420, 520)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| e.to_string())?;
        let values = data
            .estimate
            .iter()
            .flat_map(|&(_, m, sd)| [m - 2.0 * sd, m + 2.0 * sd])
            .chain(data.truth.iter().map(|t| t.1))
            .chain(data.zone.iter().flat_map(|z| [z.0, z.1]))
            .filter(|v| v.is_finite());
        let (lo, hi) = values.fold((0.15f64, 0.25f64), |(a, b), v| (a.min(v), b.max(v)));
        let depth = data
            .estimate
            .iter()
            .map(|e| e.0)
            .chain(data.truth.iter().map(|t| t.0))
            .fold(0.5f64, f64::max);
        let mut chart = ChartBuilder::on(&root)
            .caption(data.title, ("sans-serif", 16))
            .margin(10)
            .x_label_area_size(36)
            .y_label_area_size(50)
            .build_cartesian_2d((lo - 0.01)..(hi + 0.01), -depth..0.0)
            .map_err(|e| e.to_string())?;
        chart
            .configure_mesh()
            .max_light_lines(2)
            .x_desc("θ [m³/m³]")
            .y_desc("depth [m]")
            .y_label_formatter(&|y| format!("{:.2}", -y))
            .draw()
            .map_err(|e| e.to_string())?;
        let green = RGBColor(44, 160, 44);
        if let Some((low, up, rooting)) = data.zone {
            chart
                .draw_series(std::iter::once(Rectangle::new(
                    [(low, -rooting), (up, 0.0)],
                    green.mix(0.15).filled(),
                )))
                .map_err(|e| e.to_string())?
                .label("zone (root zone)")
                .legend(move |(x, y)| {
                    Rectangle::new([(x, y - 4), (x + 16, y + 4)], green.mix(0.3).filled())
                });
        }
        let orange = RGBColor(255, 127, 14);
        if !data.estimate.is_empty() {
            let band: Vec<(f64, f64)> = data
                .estimate
                .iter()
                .map(|&(d, m, sd)| (m - 2.0 * sd, -d))
                .chain(
                    data.estimate
                        .iter()
                        .rev()
                        .map(|&(d, m, sd)| (m + 2.0 * sd, -d)),
                )
                .collect();
            chart
                .draw_series(std::iter::once(Polygon::new(
                    band,
                    orange.mix(0.25).filled(),
                )))
                .map_err(|e| e.to_string())?
                .label("estimate ± 2 sd")
                .legend(move |(x, y)| {
                    Rectangle::new([(x, y - 4), (x + 16, y + 4)], orange.mix(0.4).filled())
                });
            chart
                .draw_series(LineSeries::new(
                    data.estimate.iter().map(|&(d, m, _)| (m, -d)),
                    orange.stroke_width(2),
                ))
                .map_err(|e| e.to_string())?
                .label("estimated θ")
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], orange));
        }
        if !data.truth.is_empty() {
            chart
                .draw_series(LineSeries::new(
                    data.truth.iter().map(|&(d, t)| (t, -d)),
                    BLACK.stroke_width(2),
                ))
                .map_err(|e| e.to_string())?
                .label("true θ (simulated)")
                .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], BLACK));
        }
        let blue = RGBColor(31, 119, 180);
        for (id, d) in data.sensors {
            chart
                .draw_series(std::iter::once(Text::new(
                    format!("◂ {id}"),
                    (hi + 0.01 - 0.25 * (hi - lo + 0.02), -d),
                    ("sans-serif", 12).into_font().color(&blue),
                )))
                .map_err(|e| e.to_string())?;
        }
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::LowerLeft)
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .draw()
            .map_err(|e| e.to_string())?;
        root.present().map_err(|e| e.to_string())?;
    }
    Ok(svg)
}

/// The window of a chart: the last `hours` before `now`.
pub fn window(now: DateTime<Utc>, hours: f64) -> DateTime<Utc> {
    now - TimeDelta::milliseconds((hours * 3.6e6) as i64)
}
