//! A setpoint's explanation in words: what it irrigates, what θ the cycle
//! predicted with and without that irrigation, which constraint binds, and
//! the degraded modes. Stored with the setpoint (`Setpoint::explanation`),
//! shown by the dashboard and exported by `history.csv`.

use super::wire::Setpoint;

/// Slack when comparing θ with a zone bound [m³/m³]: the QP's tolerance
/// leaves a bound active within about 1e-4.
const ON_BOUND: f64 = 5e-4;

/// A degraded flag in words (the flag itself when it is unknown).
pub fn flag_words(flag: &str) -> &str {
    match flag {
        "stale-measurement" => "the last reading is old, so the cycle started from its prediction",
        "no-measurement" => "no reading yet",
        "default-forecast" => "no forecast covered the horizon: climatology filled it",
        "stale-forecast" => "the forecast provider's last answer is too old: climatology used",
        "solver-fallback" => "the optimiser fell back",
        "simulation-failed" => "the simulated plant failed",
        "estimator-reset" => "the state estimate was reset",
        "surrogate-refused" => {
            "the field's own network was refused (its file does not match its record)"
        }
        other => other,
    }
}

/// The explanation of `s`, a setpoint of a field whose largest irrigation
/// rate is `u_max` [m/s].
pub fn explain(s: &Setpoint, u_max: f64) -> String {
    let mut parts = Vec::new();
    let mut first = format!("Irrigate {:.2} mm this period", s.amount_mm);
    if let Some(v) = &s.valve {
        first += &format!(" (valve {:.1} min, {:.2} m³", v.valve_minutes, v.volume_m3);
        if v.pulses.len() > 1 {
            first += &format!(
                ", in {} pulses with {:.0} min soaks",
                v.pulses.len(),
                v.soak_minutes
            );
        }
        if let Some(r) = v.predicted_runoff_mm {
            first += &format!(", predicted runoff {r:.2} mm");
        }
        first += ")";
    }
    parts.push(first);
    if let Some(b) = binding(s, u_max) {
        parts.push(b);
    }
    if let (Some(with), Some(dry)) = (s.predicted_theta.first(), s.predicted_theta_dry.first()) {
        parts.push(format!(
            "θ after one period: {with:.3} with this irrigation, {dry:.3} without"
        ));
    }
    let rain: f64 = s.rain_mm.iter().sum();
    if !s.rain_mm.is_empty() {
        let et0: f64 = s.et0_mm.iter().sum();
        parts.push(format!(
            "forecast over the horizon: {rain:.1} mm rain, {et0:.1} mm ET0{}",
            s.forecast
                .as_ref()
                .map(|f| format!(" ({})", f.source))
                .unwrap_or_default()
        ));
    }
    parts.push(format!(
        "optimiser: {} ({} iterations, {:.0} ms)",
        s.status, s.iterations, s.solve_ms
    ));
    for flag in &s.degraded {
        parts.push(flag_words(flag).to_string());
    }
    if let Some(why) = &s.fallback_reason {
        parts.push(format!("reason: {why}"));
    }
    parts.join("; ") + "."
}

/// Which constraint decides the setpoint, from the predictions with and
/// without irrigation against the zone; None without a prediction.
fn binding(s: &Setpoint, u_max: f64) -> Option<String> {
    let with = &s.predicted_theta;
    let n = with.len().min(s.zone.len());
    if n == 0 || !with.iter().all(|v| v.is_finite()) {
        return None;
    }
    // the step where θ with the plan comes closest to the lower bound
    let (k, gap) = (0..n)
        .map(|k| (k, with[k] - s.zone[k][0]))
        .min_by(|a, b| a.1.total_cmp(&b.1))?;
    let dry_below = (s.predicted_theta_dry.len() >= n)
        .then(|| (0..n).find(|&k| s.predicted_theta_dry[k] < s.zone[k][0] - ON_BOUND))
        .flatten();
    let later_mm: f64 = s.plan.iter().skip(1).sum::<f64>() * period_s(s) * 1e3;
    let at_limit = s.rate > 0.0 && s.rate >= u_max * (1.0 - 1e-6);
    let text = if at_limit {
        format!(
            "the irrigation limit binds: the largest rate, {u_max:.2e} m/s, is applied \
             and θ still comes to {:.3} in period {} against the zone's lower bound {:.3}",
            with[k],
            k + 1,
            s.zone[k][0]
        )
    } else if s.rate > 0.0 {
        let without = match dry_below {
            Some(d) => format!(
                "without irrigation θ would fall below the zone in period {} ({:.3} < {:.3}); ",
                d + 1,
                s.predicted_theta_dry[d],
                s.zone[d][0]
            ),
            None => String::new(),
        };
        format!(
            "{without}the zone's lower bound binds in period {} (θ {:.3}, bound {:.3}): \
             this is the least water that keeps θ in the zone",
            k + 1,
            with[k],
            s.zone[k][0]
        )
    } else if gap < -ON_BOUND {
        format!(
            "θ falls below the zone in period {} ({:.3} < {:.3}) even so: the plan irrigates \
             {later_mm:.2} mm later in the horizon, when it does more good",
            k + 1,
            with[k],
            s.zone[k][0]
        )
    } else if let Some(d) = dry_below {
        format!(
            "no irrigation now: θ stays in the zone this period, and the plan irrigates \
             {later_mm:.2} mm later, before it would fall below the zone in period {}",
            d + 1
        )
    } else if with.first().is_some_and(|v| *v > s.zone[0][1] + ON_BOUND) {
        format!(
            "no irrigation: θ ({:.3}) is above the zone's upper bound {:.3}, which \
             irrigation cannot lower",
            with[0], s.zone[0][1]
        )
    } else {
        format!(
            "no irrigation needed: without it θ stays at or above the zone's lower bound \
             over the horizon (lowest {:.3} in period {}, bound {:.3})",
            with[k],
            k + 1,
            s.zone[k][0]
        )
    };
    Some(text)
}

fn period_s(s: &Setpoint) -> f64 {
    (s.valid_until - s.valid_from).num_milliseconds() as f64 / 1e3
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::service::wire::ModelKind;
    use chrono::{DateTime, Utc};

    fn at(s: &str) -> DateTime<Utc> {
        DateTime::parse_from_rfc3339(s).unwrap().to_utc()
    }

    fn setpoint(rate: f64, with: Vec<f64>, dry: Vec<f64>) -> Setpoint {
        let n = with.len();
        Setpoint {
            field_id: 1,
            time: at("2026-06-02T12:00:00Z"),
            valid_from: at("2026-06-02T12:00:00Z"),
            valid_until: at("2026-06-02T14:00:00Z"),
            rate,
            amount_mm: rate * 7200.0 * 1e3,
            plan: vec![rate; n],
            predicted_theta: with,
            zone: vec![[0.18, 0.23]; n],
            model: ModelKind::Richards,
            status: "converged".into(),
            fallback_reason: None,
            iterations: 4,
            solve_ms: 12.0,
            degraded: vec!["default-forecast".into()],
            measured_at: None,
            bias: 0.0,
            predicted_next: None,
            valve: None,
            surrogate: None,
            forecast: None,
            predicted_theta_dry: dry,
            rain_mm: vec![0.0, 1.5, 0.5],
            et0_mm: vec![0.4, 0.6, 0.2],
            explanation: String::new(),
        }
    }

    #[test]
    fn irrigation_that_holds_the_lower_bound_says_the_bound_binds_and_when_it_would_be_left() {
        let s = setpoint(1e-6, vec![0.19, 0.1801, 0.185], vec![0.185, 0.175, 0.17]);
        let text = explain(&s, 1e-5);
        assert!(text.starts_with("Irrigate 7.20 mm this period"), "{text}");
        assert!(
            text.contains(
                "without irrigation θ would fall below the zone in period 2 (0.175 < 0.180)"
            ),
            "{text}"
        );
        assert!(
            text.contains("lower bound binds in period 2 (θ 0.180"),
            "{text}"
        );
        assert!(
            text.contains("0.190 with this irrigation, 0.185 without"),
            "{text}"
        );
        assert!(text.contains("2.0 mm rain, 1.2 mm ET0"), "{text}");
        assert!(text.contains("climatology filled it"), "{text}");
        assert!(
            text.contains("optimiser: converged (4 iterations, 12 ms)"),
            "{text}"
        );
    }

    #[test]
    fn the_limit_the_upper_bound_and_a_wet_field_are_told_apart() {
        let at_max = explain(&setpoint(1e-5, vec![0.17, 0.175], vec![0.16, 0.15]), 1e-5);
        assert!(at_max.contains("the irrigation limit binds"), "{at_max}");
        let wet = explain(&setpoint(0.0, vec![0.26, 0.25], vec![0.26, 0.25]), 1e-5);
        assert!(wet.contains("above the zone's upper bound 0.230"), "{wet}");
        let fine = explain(&setpoint(0.0, vec![0.21, 0.2], vec![0.21, 0.2]), 1e-5);
        assert!(fine.contains("no irrigation needed"), "{fine}");
        assert!(fine.contains("lowest 0.200 in period 2"), "{fine}");
        let mut later = setpoint(0.0, vec![0.2, 0.19, 0.185], vec![0.2, 0.19, 0.17]);
        later.plan = vec![0.0, 1e-6, 0.0];
        let text = explain(&later, 1e-5);
        assert!(
            text.contains(
                "irrigates 7.20 mm later, before it would fall below the zone in period 3"
            ),
            "{text}"
        );
    }

    #[test]
    fn a_setpoint_without_a_prediction_still_explains_its_status() {
        let mut s = setpoint(0.0, vec![], vec![]);
        s.status = "fallback".into();
        s.fallback_reason = Some("no measurement yet: no irrigation".into());
        let text = explain(&s, 1e-5);
        assert!(
            text.starts_with("Irrigate 0.00 mm this period; forecast"),
            "{text}"
        );
        assert!(
            text.ends_with("reason: no measurement yet: no irrigation."),
            "{text}"
        );
    }
}
