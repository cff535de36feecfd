//! What every controller does around a zone-MPC solve, written once for
//! the in-process controllers ([`super::Controller`],
//! [`super::EstimatedRichards`]) and the daemon's cycle
//! (`service::cycle::decide`): the rate applied from a plan, the plan
//! stored, the bias of the surrogates and the no-irrigation fallback.

use std::time::Duration;

use super::mpc::{MpcSettings, Solution, SolveStatus};
use super::zone::ZoneSettings;

/// How many standard deviations of the estimated θ at the model's output
/// cell the lower zone bound is raised by for a controller that plans on a
/// state estimate ([`backed_off`]).
pub const BACK_OFF_SDS: f64 = 0.5;

/// The largest back-off, as a share of the terminal zone's width: the zone
/// keeps at least half of its width.
pub const BACK_OFF_SHARE: f64 = 0.5;

/// The zone a controller planning on a *state estimate* aims at: the lower
/// bound raised by [`BACK_OFF_SDS`] × `sd`, the standard deviation of the
/// estimated θ at the model's output cell, at most [`BACK_OFF_SHARE`] of the
/// terminal zone's width (a constraint back-off, as in stochastic MPC: a
/// plan that just touches the lower bound of the estimate dries the true
/// root zone about half of the time). The upper bound is kept: the wet side
/// only wastes water, the dry side harms the crop (MODEL.md §4). A `sd`
/// that is not finite or not positive leaves the zone as it is.
pub fn backed_off(zone: ZoneSettings, sd: f64) -> ZoneSettings {
    if !(sd.is_finite() && sd > 0.0) {
        return zone;
    }
    let width = (zone.y_up - zone.y_low).max(0.0);
    let lift = (BACK_OFF_SDS * sd).min(BACK_OFF_SHARE * width);
    ZoneSettings {
        low0: zone.low0 + lift,
        y_low: zone.y_low + lift,
        ..zone
    }
}

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
    fn the_back_off_raises_the_lower_bound_by_the_sd_within_half_the_width() {
        let zone = ZoneSettings::band(0.18, 0.23);
        let z = backed_off(zone, 0.004 / BACK_OFF_SDS);
        assert!((z.y_low - 0.184).abs() < 1e-15 && (z.low0 - 0.184).abs() < 1e-15);
        assert_eq!((z.y_up, z.up0, z.mu), (0.23, 0.23, 0.0));
        // capped at half the width
        let z = backed_off(zone, 0.1 / BACK_OFF_SDS);
        assert!((z.y_low - 0.205).abs() < 1e-15);
        assert!(z.problem().is_none());
        // a shrinking zone keeps its order
        let shrinking = ZoneSettings {
            low0: 0.18,
            up0: 0.23,
            y_low: 0.20,
            y_up: 0.21,
            mu: 1.0,
        };
        let z = backed_off(shrinking, 0.003 / BACK_OFF_SDS);
        assert!((z.low0 - 0.183).abs() < 1e-15 && (z.y_low - 0.203).abs() < 1e-15);
        assert!(z.problem().is_none());
        // nothing to back off by
        for sd in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            assert_eq!(backed_off(zone, sd), zone);
        }
    }

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
