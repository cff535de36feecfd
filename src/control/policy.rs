//! What every controller does around a zone-MPC solve, written once for
//! the in-process controllers ([`super::Controller`],
//! [`super::EstimatedRichards`]) and the daemon's cycle
//! (`service::cycle::decide`): the rate applied from a plan, the plan
//! stored, the bias of the surrogates and the no-irrigation fallback.

use std::time::Duration;

use super::model::PredictionModel;
use super::mpc::{MpcSettings, Solution, SolveStatus, ZoneMpc};
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

/// A sound start (issue 17): a model that is not yet settled mispredicts
/// fields outside the range it knows, so while it is not, a field whose θ
/// lies above its zone's upper bound now is not irrigated this period: it
/// is re-decided at the next one, and u_max refills a zone far faster than
/// a crop empties it (72 mm per 2-h period at the default u_max).
///
/// A surrogate is settled once a full window has been measured (before, its
/// prediction rests on a padded or synthesised past; [`StartUp::window`]).
/// The estimated Richards model is settled once the "unknown" prior's
/// texture selection has ended (before, it plans on the mean of the
/// textures still in the running, which is no soil: on a silt read at
/// 0.4645, above its zone, that mean's θs lay below the zone and the first
/// cycle irrigated 6.9 mm).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StartUp {
    pub settled: bool,
    /// The θ the field is at now (measured, or estimated), if known.
    pub measured: Option<f64>,
}

impl StartUp {
    /// A surrogate's start: settled once `measured_samples` (this step's
    /// included) fill its `window`.
    pub fn window(measured_samples: usize, window: usize, measured: Option<f64>) -> StartUp {
        StartUp {
            settled: measured_samples >= window,
            measured,
        }
    }

    /// Whether the field is held at zero irrigation under a zone whose
    /// upper bound is `zone_up` now.
    pub fn holds(&self, zone_up: f64) -> bool {
        !self.settled && self.measured.is_some_and(|theta| theta > zone_up)
    }
}

/// One control step's decision.
#[derive(Debug, Clone, PartialEq)]
pub struct Step {
    /// The rate applied over the next step [m/s], in [0, u_max].
    pub rate: f64,
    /// The plan as published: every move clamped, the first one the rate.
    pub plan: Vec<f64>,
    pub solution: Solution,
    /// Whether the sound start held the field (rate 0 whatever the plan).
    pub held: bool,
}

/// One control step, the same for every controller (the in-process
/// [`super::Controller`] and [`super::EstimatedRichards`], and the
/// daemon's `service::cycle::decide`): the zone MPC solved on `model`, or
/// the no-irrigation fallback with the reason when there is no model; the
/// applied rate and the published plan clamped to [0, u_max] (0 for a move
/// that is not finite); and while the model is not settled (`start_up`
/// given) the sound start's hold.
pub fn step(
    mpc: &mut ZoneMpc,
    model: Result<&mut dyn PredictionModel, String>,
    start_up: Option<StartUp>,
) -> Step {
    let solution = match model {
        Ok(model) => mpc.solve(model),
        Err(reason) => no_irrigation(&mpc.settings, reason),
    };
    let settings = &mpc.settings;
    let mut rate = applied_rate(&solution.plan, settings.u_max);
    let mut plan = published_plan(&solution.plan, settings.u_max);
    let held = start_up.is_some_and(|s| s.holds(settings.zone.bounds(1, settings.horizon).1));
    if held {
        rate = 0.0;
        if let Some(first) = plan.first_mut() {
            *first = 0.0;
        }
    }
    Step {
        rate,
        plan,
        solution,
        held,
    }
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
    use crate::control::model::LinearModel;

    /// θ_k = θ0 − 0.002·k + 1e3·Σ_{j≤k} u_j (k = 1..N): 1e-5 m/s over one
    /// step raises θ by 0.01, the crop takes 0.002.
    fn field(theta0: f64) -> LinearModel {
        LinearModel {
            a: (1..=20).map(|k| theta0 - 0.002 * k as f64).collect(),
            b: 1e3,
            rho: 1.0,
        }
    }

    #[test]
    fn a_step_irrigates_a_drying_field_within_its_bounds_and_publishes_what_it_applies() {
        let mut mpc = ZoneMpc::new(MpcSettings::default());
        let s = step(&mut mpc, Ok(&mut field(0.17)), None);
        let u_max = mpc.settings.u_max;
        assert!(s.rate > 0.0 && s.rate <= u_max, "rate {}", s.rate);
        assert_eq!(s.plan[0], s.rate);
        assert!(s.plan.iter().all(|u| (0.0..=u_max).contains(u)));
        assert!(!s.held);
        // the plan holds the field near its zone's lower bound 0.18 (it
        // would end at 0.17 − 20·0.002 = 0.13 without water, and no plan
        // overshoots the top), and its prediction is the model's own
        let last = *s.solution.predicted.last().unwrap();
        assert!((0.165..=0.23).contains(&last), "θ_N {last}");
        let total: f64 = s.solution.plan.iter().sum();
        assert!((last - (0.17 - 0.04 + 1e3 * total)).abs() < 1e-9);
    }

    #[test]
    fn a_step_without_a_model_or_with_a_failing_one_never_irrigates() {
        let mut mpc = ZoneMpc::new(MpcSettings::default());
        let s = step(&mut mpc, Err("no model here".into()), None);
        assert_eq!((s.rate, s.held), (0.0, false));
        assert_eq!(s.plan, vec![0.0; mpc.settings.horizon]);
        assert_eq!(
            s.solution.status,
            SolveStatus::Fallback("no model here".into())
        );
        // a model whose predictions are not finite
        let mut broken = field(0.17);
        broken.a[3] = f64::NAN;
        let s = step(&mut mpc, Ok(&mut broken), None);
        assert_eq!(s.rate, 0.0);
        assert!(matches!(s.solution.status, SolveStatus::Fallback(_)));
    }

    #[test]
    fn the_sound_start_holds_a_wet_field_only_while_its_window_is_short() {
        // measured above the zone, but the model (say a padded window)
        // predicts it dry: the plan irrigates, the hold overrides it
        let mut mpc = ZoneMpc::new(MpcSettings::default());
        let short = StartUp::window(3, 20, Some(0.25));
        let s = step(&mut mpc, Ok(&mut field(0.17)), Some(short));
        assert!(s.held);
        assert_eq!((s.rate, s.plan[0]), (0.0, 0.0));
        assert!(s.solution.plan[0] > 0.0);
        let full = StartUp::window(20, 20, Some(0.25));
        let mut mpc = ZoneMpc::new(MpcSettings::default());
        let s = step(&mut mpc, Ok(&mut field(0.17)), Some(full));
        assert!(!s.held && s.rate > 0.0);
    }

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
        let held = |samples, theta| StartUp::window(samples, 20, theta).holds(0.23);
        assert!(held(1, Some(0.26)));
        assert!(held(19, Some(0.231)));
        assert!(!held(20, Some(0.26)));
        assert!(!held(1, Some(0.23)));
        assert!(!held(1, Some(0.17)));
        assert!(!held(1, None));
        let settled = StartUp {
            settled: true,
            measured: Some(0.26),
        };
        assert!(!settled.holds(0.23));
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
