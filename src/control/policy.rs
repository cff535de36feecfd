//! What every controller does around a zone-MPC solve, written once for
//! the in-process controllers ([`super::Controller`],
//! [`super::EstimatedRichards`]) and the daemon's cycle
//! (`service::cycle::decide`): the rate applied from a plan, the plan
//! stored, the bias of the surrogates and the no-irrigation fallback.

use std::time::Duration;

use super::mpc::{MpcSettings, Solution, SolveStatus};

/// The rate applied from a plan's first move: clamped to [0, u_max], and 0
/// when it is not finite (a failed solve never irrigates by accident).
pub fn applied_rate(plan: &[f64], u_max: f64) -> f64 {
    match plan.first() {
        Some(u) if u.is_finite() => u.clamp(0.0, u_max),
        _ => 0.0,
    }
}

/// The plan as published: every move clamped as [`applied_rate`] does.
pub fn published_plan(plan: &[f64], u_max: f64) -> Vec<f64> {
    plan.iter()
        .map(|u| applied_rate(std::slice::from_ref(u), u_max))
        .collect()
}

/// The surrogates' bias correction (MODEL.md §3, closed loop): the mean of
/// the one-step residuals y_meas(t) − ŷ(t | t − 1) given, 0 without any.
pub fn bias(residuals: &[f64]) -> f64 {
    let finite: Vec<f64> = residuals
        .iter()
        .copied()
        .filter(|r| r.is_finite())
        .collect();
    if finite.is_empty() {
        0.0
    } else {
        finite.iter().sum::<f64>() / finite.len() as f64
    }
}

/// A sound start for the surrogates (issue 17): while fewer than `window`
/// samples have been measured, their prediction rests on a padded or
/// synthesised past, and they mispredict fields outside the range they were
/// trained on. Then a field whose measured θ lies above its zone's upper
/// bound `zone_up` now is not irrigated this period: it is re-decided at
/// the next one, and u_max refills a zone far faster than a crop empties it
/// (72 mm per 2-h period at the default u_max).
pub fn start_up_hold(
    measured_samples: usize,
    window: usize,
    measured: Option<f64>,
    zone_up: f64,
) -> bool {
    measured_samples < window && measured.is_some_and(|theta| theta > zone_up)
}

/// The fallback when there is nothing to solve with: no irrigation over the
/// horizon, the zone in force, and the reason.
pub fn no_irrigation(settings: &MpcSettings, reason: impl Into<String>) -> Solution {
    let n = settings.horizon;
    Solution {
        plan: vec![0.0; n],
        predicted: Vec::new(),
        zone: (1..=n).map(|k| settings.zone.bounds(k, n)).collect(),
        status: SolveStatus::Fallback(reason.into()),
        iterations: 0,
        objective: f64::NAN,
        solve_time: Duration::ZERO,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_applied_rate_is_clamped_and_never_irrigates_on_a_bad_plan() {
        assert_eq!(applied_rate(&[5e-6, 1.0], 1e-5), 5e-6);
        assert_eq!(applied_rate(&[2e-5], 1e-5), 1e-5);
        assert_eq!(applied_rate(&[-1e-7], 1e-5), 0.0);
        assert_eq!(applied_rate(&[f64::NAN], 1e-5), 0.0);
        assert_eq!(applied_rate(&[f64::INFINITY], 1e-5), 0.0);
        assert_eq!(applied_rate(&[], 1e-5), 0.0);
        assert_eq!(
            published_plan(&[1.0, -1.0, f64::NAN, 3e-6], 1e-5),
            vec![1e-5, 0.0, 0.0, 3e-6]
        );
    }

    #[test]
    fn the_bias_is_the_mean_of_the_finite_residuals() {
        assert_eq!(bias(&[]), 0.0);
        assert!((bias(&[0.01, -0.03]) - (-0.01)).abs() < 1e-15);
        assert!((bias(&[0.02, f64::NAN]) - 0.02).abs() < 1e-15);
    }

    #[test]
    fn a_field_above_its_zone_is_held_only_while_the_window_is_incomplete() {
        assert!(start_up_hold(1, 20, Some(0.26), 0.23));
        assert!(start_up_hold(19, 20, Some(0.231), 0.23));
        assert!(!start_up_hold(20, 20, Some(0.26), 0.23));
        assert!(!start_up_hold(1, 20, Some(0.23), 0.23));
        assert!(!start_up_hold(1, 20, Some(0.17), 0.23));
        assert!(!start_up_hold(1, 20, None, 0.23));
    }

    #[test]
    fn the_fallback_irrigates_nothing_and_keeps_the_zone() {
        let settings = MpcSettings::default();
        let s = no_irrigation(&settings, "no model");
        assert_eq!(s.plan, vec![0.0; settings.horizon]);
        assert_eq!(s.zone.len(), settings.horizon);
        assert_eq!(s.zone[0], settings.zone.bounds(1, settings.horizon));
        assert_eq!(s.status, SolveStatus::Fallback("no model".into()));
    }
}
