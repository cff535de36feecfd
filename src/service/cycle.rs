//! One control cycle as a pure step: [`decide`] maps what the cycle needs
//! ([`CycleInputs`], read in one go by `Engine::load`) to the setpoint, with
//! no storage, clock or I/O, so the bias, clamp and fallback logic is
//! unit-tested on plain data. The engine then writes the setpoint once.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use chrono::{DateTime, TimeDelta, Timelike, Utc};

pub use crate::control::EstimateView;
use crate::control::{
    PredictionModel, RichardsModel, SolveStatus, SurrogateModel, ZoneMpc, policy, step_on_estimate,
};
use crate::sim::{SCENARIO_STEP, scenario_series, scenario_weather};
use crate::soil::{Field as Plant, FieldSettings, Forcing, VanGenuchten};
use crate::surrogate::evaluate::WINDOW;
use crate::weather::{WeatherStep, mm_to_rate, rate_to_mm};

use super::engine::Models;
use super::valve;
use super::wire::{Field, Forecast, Measurement, ModelKind, Scenario, Setpoint};
use crate::estimate::{EstimateError, Estimator, EstimatorSnapshot};

/// How many past setpoints enter the bias (MODEL.md: f = 2).
pub const BIAS_PERIOD: usize = 2;

/// Everything one cycle reads.
#[derive(Debug, Clone)]
pub struct CycleInputs {
    pub field: Field,
    /// The cycle's time.
    pub now: DateTime<Utc>,
    /// The field's latest setpoints, newest first (at most WINDOW + BIAS_PERIOD).
    pub recent: Vec<Setpoint>,
    /// The primary sensor's measurements, oldest first: those of the
    /// window's span and the latest at or before `now`.
    pub measurements: Vec<Measurement>,
    /// The latest stored forecast.
    pub forecast: Option<Forecast>,
    /// A simulated field's scenario and day zero (its past rain is known).
    pub scenario: Option<(Scenario, DateTime<Utc>)>,
    /// The field's state estimate, when it has one.
    pub estimate: Option<EstimateView>,
    /// Degraded flags raised while loading (e.g. simulation-failed).
    pub degraded: Vec<String>,
}

impl CycleInputs {
    /// The latest measurement at or before `t`.
    pub fn before(&self, t: DateTime<Utc>) -> Option<&Measurement> {
        self.measurements.iter().rev().find(|m| m.time <= t)
    }
}

fn seconds(d: TimeDelta) -> f64 {
    d.num_milliseconds() as f64 / 1000.0
}

/// The climatological forecast: the dry scenario's daily ET0 cycle by
/// hour of day, no rain; amounts per step of `period` seconds.
pub fn climatology(t: DateTime<Utc>, period: f64) -> WeatherStep {
    let hour = t.hour() as f64 + t.minute() as f64 / 60.0;
    let k = ((hour * 3600.0) / SCENARIO_STEP).floor() as usize % 12;
    let step = scenario_series(Scenario::Dry).steps()[k];
    WeatherStep {
        start_hour: hour,
        et0_mm: step.et0_mm * period / SCENARIO_STEP,
        precip_mm: 0.0,
    }
}

/// The horizon's weather (amounts per control period) from the latest
/// forecast, or the climatology where it is missing or stale (more than two
/// periods old); and whether the climatology was used.
fn horizon_weather(
    forecast: Option<&Forecast>,
    period: f64,
    now: DateTime<Utc>,
    n: usize,
) -> (Vec<WeatherStep>, bool) {
    let forecast = forecast.filter(|f| seconds(now - f.issued_at) <= 2.0 * period);
    let mut defaulted = forecast.is_none();
    let mut out = Vec::with_capacity(n);
    for k in 0..n {
        let t0 = now + TimeDelta::milliseconds((k as f64 * period * 1000.0) as i64);
        let covered = forecast.as_ref().and_then(|f| {
            // amounts of the forecast steps overlapping [t0, t0 + period)
            let a = seconds(t0 - f.start);
            let b = a + period;
            let end = f.step_s * f.et0_mm.len() as f64;
            if a < 0.0 || b > end + 1e-6 {
                return None;
            }
            let (mut et0, mut precip) = (0.0, 0.0);
            let first = (a / f.step_s).floor() as usize;
            let last = ((b / f.step_s).ceil() as usize).min(f.et0_mm.len());
            for i in first..last {
                let lo = (i as f64 * f.step_s).max(a);
                let hi = ((i + 1) as f64 * f.step_s).min(b);
                let share = ((hi - lo) / f.step_s).max(0.0);
                et0 += f.et0_mm[i] * share;
                precip += f.precip_mm[i] * share;
            }
            Some(WeatherStep {
                start_hour: 0.0,
                et0_mm: et0,
                precip_mm: precip,
            })
        });
        match covered {
            Some(w) => out.push(w),
            None => {
                defaulted = true;
                out.push(climatology(t0, period));
            }
        }
    }
    (out, defaulted)
}

pub fn decide(inputs: &CycleInputs, models: &Models, cancel: &Arc<AtomicBool>) -> Setpoint {
    let (field, now, recent) = (&inputs.field, inputs.now, &inputs.recent);
    let spec = &field.spec;
    let period = spec.control_period_s;
    let period_d = TimeDelta::milliseconds((period * 1000.0) as i64);
    // the Richards model plans on the estimated soil; the surrogates know
    // the soil they were trained on
    let richards_estimate = inputs
        .estimate
        .as_ref()
        .filter(|_| spec.model == ModelKind::Richards);
    let mut settings = spec.mpc_settings_with(richards_estimate.map(|e| &e.soil));
    let asked_zone = settings.zone;
    // planning on an estimate: the lower bound backed off by its uncertainty
    // (step_on_estimate backs off again from `asked_zone`; this is the zone
    // a cycle with no measurement publishes)
    if let Some(e) = richards_estimate {
        settings.zone = policy::backed_off(settings.zone, e.output_sd);
    }
    let n = settings.horizon;
    let mut degraded = inputs.degraded.clone();
    let (weather, defaulted) = horizon_weather(inputs.forecast.as_ref(), period, now, n);
    if defaulted {
        degraded.push("default-forecast".to_string());
    }
    let latest = inputs.before(now);
    let fresh = latest
        .as_ref()
        .filter(|m| seconds(now - m.time) <= 2.0 * period);
    // the current θ: measured, or predicted by the last cycle when stale
    let measured_at = fresh.map(|m| m.time);
    let mut current = fresh.map(|m| m.theta);
    if current.is_none() {
        if latest.is_some() {
            degraded.push("stale-measurement".into());
        } else {
            degraded.push("no-measurement".into());
        }
        current = recent.first().and_then(|s| {
            let k = (seconds(now - s.time) / period).round() as usize;
            s.predicted_theta.get(k.saturating_sub(1)).copied()
        });
        if current.is_none() {
            current = latest.as_ref().map(|m| m.theta);
        }
    }
    let rain_rate: Vec<f64> = weather
        .iter()
        .map(|w| mm_to_rate(w.precip_mm, period))
        .collect();
    let mut mpc = ZoneMpc::new(settings);
    mpc.set_cancel(Some(cancel.clone()));
    if let Some(prev) = recent.first()
        && seconds(now - prev.time) <= 1.5 * period
        && prev.model == spec.model
    {
        mpc.remember(prev.plan.clone());
    }
    let mut bias = 0.0;
    let mut one_step: Option<SurrogateModel> = None;
    let measured_samples = measured_samples(inputs);
    // the cycle's prediction model, if it has one
    let mut richards: Option<RichardsModel> = None;
    match (current, spec.model) {
        (None, _) => {}
        // on an estimate: step_on_estimate below builds the model
        (Some(_), ModelKind::Richards) if richards_estimate.is_some() => {}
        (Some(theta), ModelKind::Richards) => {
            // the controller sees what a real field gives: with no estimate
            // yet it starts from the column in equilibrium with the measured
            // θ in the declared soil; never from a simulated plant's true
            // state
            let soil = spec.soil.nominal().unwrap_or(VanGenuchten::SANDY_LOAM);
            let head = equilibrium_head(&soil, theta);
            let model = Plant::new(FieldSettings {
                soil,
                crop: spec.crop(),
                initial_head: head,
                sampling_time: period,
                ..FieldSettings::default()
            })
            .map(|plant| RichardsModel::new(&plant, &weather));
            match model {
                Ok(model) => richards = Some(model),
                Err(e) => tracing::warn!(field = field.id, error = %e, "no Richards model"),
            }
        }
        (Some(theta), kind) => {
            let file = if kind == ModelKind::Lstm {
                &models.lstm
            } else {
                &models.two_layer
            };
            let (past_u, past_y, past_e) = window(inputs, theta);
            let mut model = SurrogateModel::new(file.predictor(), past_u, past_y, past_e);
            // bias: mean over the last f cycles of y(t) − ŷ(t | t − 1)
            let mut residuals = Vec::new();
            for s in recent
                .iter()
                .filter(|s| s.valid_until <= now)
                .take(BIAS_PERIOD)
            {
                if let Some(m) = inputs.before(s.valid_until)
                    && seconds(s.valid_until - m.time) <= period / 2.0
                    && let Some(predicted) = s.predicted_next
                {
                    residuals.push(m.theta - predicted);
                }
            }
            bias = policy::bias(&residuals);
            model.bias = bias;
            model.rain = rain_rate.clone();
            model.et0 = weather
                .iter()
                .map(|w| mm_to_rate(w.et0_mm, period))
                .collect();
            one_step = Some(model);
        }
    }
    let policy::Step {
        rate,
        plan,
        solution,
        ..
    } = match (current, richards_estimate) {
        // the Richards model on the estimate, as the in-process controller
        // plans (the sound start while the texture is being selected)
        (Some(_), Some(e)) => {
            let (step, model) = step_on_estimate(
                &mut mpc,
                asked_zone,
                e,
                spec.crop(),
                &weather,
                period,
                fresh.map(|m| m.theta),
            );
            richards = model;
            step
        }
        _ => {
            let model = cycle_model(&mut richards, &mut one_step).ok_or_else(|| {
                if current.is_none() {
                    "no measurement yet: no irrigation".to_string()
                } else {
                    "no prediction model: no irrigation".to_string()
                }
            });
            // the sound start of a surrogate: until its window is full
            let start_up = (spec.model != ModelKind::Richards)
                .then(|| policy::StartUp::window(measured_samples, WINDOW, fresh.map(|m| m.theta)));
            policy::step(&mut mpc, model, start_up)
        }
    };
    // θ with no irrigation at all, for the explanation
    let dry = cycle_model(&mut richards, &mut one_step)
        .map_or_else(Vec::new, |model| without_irrigation(model, n, cancel));
    let (status, reason) = match &solution.status {
        SolveStatus::Converged => ("converged", None),
        SolveStatus::IterationCap => ("iteration-cap", None),
        SolveStatus::WorkBudget => ("work-budget", None),
        SolveStatus::TimeBudget => ("time-budget", None),
        SolveStatus::Fallback(why) => ("fallback", Some(why.clone())),
    };
    if reason.is_some() {
        degraded.push("solver-fallback".into());
    }
    let predicted_next = match one_step.as_mut() {
        Some(model) => model
            .one_step(
                rate + rain_rate.first().copied().unwrap_or(0.0),
                weather
                    .first()
                    .map_or(0.0, |w| mm_to_rate(w.et0_mm, period)),
            )
            .ok(),
        None => solution.predicted.first().copied(),
    }
    .filter(|p| p.is_finite());
    let valve = spec.irrigation_system.as_ref().map(|system| {
        let start = valve_start(inputs, current);
        let w = weather
            .first()
            .map_or(Forcing::default(), |w| w.forcing(0.0, period));
        valve::schedule(system, rate_to_mm(rate, period), period, start.as_ref(), w)
    });
    Setpoint {
        field_id: field.id,
        time: now,
        valid_from: now,
        valid_until: now + period_d,
        rate,
        amount_mm: rate_to_mm(rate, period),
        plan,
        predicted_theta: solution.predicted.clone(),
        zone: solution.zone.iter().map(|&(l, u)| [l, u]).collect(),
        model: spec.model,
        status: status.into(),
        fallback_reason: reason,
        iterations: solution.iterations,
        solve_ms: solution.solve_time.as_secs_f64() * 1e3,
        degraded,
        measured_at,
        bias,
        predicted_next,
        valve,
        surrogate: None,
        forecast: None,
        predicted_theta_dry: dry,
        rain_mm: weather.iter().map(|w| w.precip_mm).collect(),
        et0_mm: weather.iter().map(|w| w.et0_mm).collect(),
        explanation: String::new(),
    }
}

/// The model a cycle plans on: its Richards model, else its surrogate.
fn cycle_model<'a>(
    richards: &'a mut Option<RichardsModel>,
    surrogate: &'a mut Option<SurrogateModel>,
) -> Option<&'a mut dyn PredictionModel> {
    match (richards, surrogate) {
        (Some(m), _) => Some(m),
        (None, Some(m)) => Some(m),
        (None, None) => None,
    }
}

/// θ over the horizon of `n` steps with no irrigation at all, for the
/// explanation; empty when the model fails or the cycle is being cancelled.
fn without_irrigation(model: &mut dyn PredictionModel, n: usize, cancel: &AtomicBool) -> Vec<f64> {
    if cancel.load(Ordering::Relaxed) {
        return Vec::new();
    }
    let mut out = vec![0.0; n];
    match model.predict(&vec![0.0; n], &mut out) {
        Ok(()) if out.iter().all(|v| v.is_finite()) => out,
        _ => Vec::new(),
    }
}

/// The uniform head of a column in equilibrium with a measured θ (kept
/// strictly inside (θr, θs), where the head is finite).
fn equilibrium_head(soil: &VanGenuchten, theta: f64) -> f64 {
    soil.pressure_head_at(theta.clamp(
        soil.residual_water_content + 1e-6,
        soil.saturated_water_content - 1e-6,
    ))
}

/// The column a valve schedule is predicted on: the state estimate, or the
/// declared soil in equilibrium with the current θ (as the Richards
/// controller starts without an estimate); None without either.
fn valve_start(inputs: &CycleInputs, current: Option<f64>) -> Option<valve::ColumnStart> {
    let spec = &inputs.field.spec;
    if let Some(e) = &inputs.estimate {
        return Some(valve::ColumnStart {
            soil: e.soil,
            crop: spec.crop(),
            depth: e.depth,
            heads: e.heads.clone(),
        });
    }
    let theta = current?;
    let soil = spec.soil.nominal().ok()?;
    let defaults = FieldSettings::default();
    let head = equilibrium_head(&soil, theta);
    Some(valve::ColumnStart {
        soil,
        crop: spec.crop(),
        depth: defaults.depth,
        heads: vec![head; defaults.cells],
    })
}

/// The weather of a field without a plant over the SCENARIO_STEP starting
/// at `t`, as amounts per SCENARIO_STEP: the newest of `forecasts` whose
/// span holds `t` (the forecast nearest the event), else the climatology.
pub fn observed_weather(forecasts: &[Forecast], t: DateTime<Utc>) -> WeatherStep {
    for f in forecasts.iter().rev() {
        let a = seconds(t - f.start);
        if a < 0.0 || f.step_s <= 0.0 {
            continue;
        }
        let i = (a / f.step_s).floor() as usize;
        if let (Some(et0), Some(precip)) = (f.et0_mm.get(i), f.precip_mm.get(i)) {
            return WeatherStep {
                start_hour: 0.0,
                et0_mm: et0 * SCENARIO_STEP / f.step_s,
                precip_mm: precip * SCENARIO_STEP / f.step_s,
            };
        }
    }
    climatology(t, SCENARIO_STEP)
}

/// Where an assimilation ended.
#[derive(Debug, Clone)]
pub struct Assimilated {
    /// The time the estimate has reached (its last reading).
    pub clock: DateTime<Utc>,
    /// The estimate after the last reading at or before `settle_before`
    /// (time, snapshot, resets), from which the next run starts.
    pub settled: (DateTime<Utc>, EstimatorSnapshot, u64),
    /// Resets to the prior, counting those passed on by the start.
    pub resets: u64,
    pub flags: Vec<String>,
    /// Why each reset of this run happened (time: error).
    pub reset_reasons: Vec<String>,
}

/// Brings `est` from `clock` through `readings` (every sensor, oldest
/// first; those at or before `clock` are skipped): between reading times a
/// forecast per interval of at most `period` s with the irrigation in force
/// (`setpoints`) and the weather of `weather_at`, at each time an update
/// with that time's readings. A gap between readings longer than
/// `max_gap_s` (a sensor or the daemon down for days) is forecast over its
/// last `max_gap_s` only, so the work stays bounded and the identified soil
/// is kept. A reading naming no sensor is `primary`'s; readings of unknown
/// sensors are skipped. A diverged estimator is reset to its prior and
/// flagged `estimator-reset`. A pure function: the daemon and its tests run
/// it on plain data.
#[allow(clippy::too_many_arguments)]
pub fn assimilate(
    est: &mut Estimator,
    mut clock: DateTime<Utc>,
    mut resets: u64,
    readings: &[Measurement],
    setpoints: &[Setpoint],
    weather_at: &dyn Fn(DateTime<Utc>) -> WeatherStep,
    period: f64,
    max_gap_s: f64,
    settle_before: DateTime<Utc>,
    primary: &str,
) -> Assimilated {
    let mut flags = Vec::new();
    let mut flags_detail = Vec::new();
    let mut settled = None;
    let mut i = readings.partition_point(|m| m.time <= clock);
    while i < readings.len() {
        let t = readings[i].time;
        if settled.is_none() && t > settle_before {
            settled = Some((clock, est.snapshot(), resets));
        }
        let group = &readings[i..][..readings[i..].iter().take_while(|m| m.time == t).count()];
        i += group.len();
        let mut outcome: Result<(), EstimateError> = Ok(());
        let max_gap = TimeDelta::milliseconds((max_gap_s.max(period) * 1e3) as i64);
        if t - clock > max_gap {
            clock = t - max_gap;
        }
        while clock < t && outcome.is_ok() {
            let dt = seconds(t - clock).min(period);
            let rate = setpoints
                .iter()
                .rev()
                .find(|s| s.valid_from <= clock && clock < s.valid_until)
                .map_or(0.0, |s| s.rate);
            outcome = est.predict(weather_at(clock).forcing(rate, SCENARIO_STEP), dt);
            clock += TimeDelta::milliseconds((dt * 1e3) as i64);
        }
        clock = t;
        let values: Vec<(usize, f64)> = group
            .iter()
            .filter_map(|m| {
                let id = m.sensor.as_deref().unwrap_or(primary);
                est.sensor_index(id).map(|k| (k, m.theta))
            })
            .collect();
        if outcome.is_ok() && !values.is_empty() {
            outcome = est.update(&values).map(|_| ());
        }
        if let Err(e) = outcome {
            flags_detail.push(format!("{t}: {e}"));
            est.reset_to_prior(&values);
            resets += 1;
            if !flags.iter().any(|f| f == "estimator-reset") {
                flags.push("estimator-reset".into());
            }
        }
    }
    Assimilated {
        clock,
        settled: settled.unwrap_or_else(|| (clock, est.snapshot(), resets)),
        resets,
        flags,
        reset_reasons: flags_detail,
    }
}

/// How many of the window's samples have a measurement at their end (the
/// last one: the current θ).
fn measured_samples(inputs: &CycleInputs) -> usize {
    let period = inputs.field.spec.control_period_s;
    let period_d = TimeDelta::milliseconds((period * 1000.0) as i64);
    (0..WINDOW)
        .filter(|&k| {
            let end = inputs.now - period_d * (WINDOW - 1 - k) as i32;
            inputs
                .before(end)
                .is_some_and(|m| seconds(end - m.time) <= period)
        })
        .count()
}

/// Whether the surrogate window at `now` starts with a measurement, so that
/// [`window`] synthesises none of it from the state estimate: a surrogate
/// cycle's setpoint then does not depend on the estimate being brought up
/// to `now` (the engine may defer that).
pub fn window_is_measured(inputs: &CycleInputs) -> bool {
    let period = inputs.field.spec.control_period_s;
    let period_d = TimeDelta::milliseconds((period * 1000.0) as i64);
    let end = inputs.now - period_d * (WINDOW - 1) as i32;
    inputs
        .before(end)
        .is_some_and(|m| seconds(end - m.time) <= period)
}

/// The surrogate window at `now`: for each of the last 20 periods, the
/// supply (the setpoint in force, plus the rain of a simulated field) and
/// θ measured at its end. Before the first measurement the window is
/// synthesised from the state estimate ([`synthesised_history`]); without
/// an estimate it is padded with the first θ and no supply.
fn window(inputs: &CycleInputs, current: f64) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    let (now, recent) = (inputs.now, &inputs.recent);
    let period = inputs.field.spec.control_period_s;
    let period_d = TimeDelta::milliseconds((period * 1000.0) as i64);
    let mut past_u = vec![0.0; WINDOW];
    let mut past_y: Vec<Option<f64>> = vec![None; WINDOW];
    // ET0 over each sample: a simulated field's scenario, else the stored
    // forecast nearest it (the climatology when none covers it)
    let mut past_e: Vec<f64> = (0..WINDOW)
        .map(|k| {
            let mid = now - period_d * (WINDOW - 1 - k) as i32 - period_d / 2;
            let w = match inputs.scenario {
                Some((sc, d0)) => scenario_weather(sc, d0, mid),
                None => observed_weather(inputs.forecast.as_slice(), mid),
            };
            mm_to_rate(w.et0_mm, SCENARIO_STEP)
        })
        .collect();
    for k in 0..WINDOW {
        // sample k ends at now − (WINDOW − 1 − k) periods
        let end = now - period_d * (WINDOW - 1 - k) as i32;
        let mid = end - period_d / 2;
        past_y[k] = if k + 1 == WINDOW {
            Some(current)
        } else {
            inputs
                .before(end)
                .filter(|m| seconds(end - m.time) <= period)
                .map(|m| m.theta)
        };
        let applied = recent
            .iter()
            .find(|s| s.valid_from <= mid && mid < s.valid_until)
            .map_or(0.0, |s| s.rate);
        let rain = match inputs.scenario {
            Some((sc, d0)) => {
                let w = scenario_weather(sc, d0, mid);
                mm_to_rate(w.precip_mm, SCENARIO_STEP)
            }
            _ => 0.0,
        };
        past_u[k] = applied + rain;
    }
    // before the first measurement: padded with it and no supply; gaps
    // carry the previous value forward
    let first = past_y
        .iter()
        .position(Option::is_some)
        .unwrap_or(WINDOW - 1);
    let first_y = past_y[first].unwrap_or(current);
    if first > 0
        && let Some(history) = inputs.estimate.as_ref().and_then(|e| {
            let rates: Vec<f64> = (0..=first)
                .map(|k| {
                    let mid = now - period_d * (WINDOW - 1 - k) as i32 - period_d / 2;
                    recent
                        .iter()
                        .find(|s| s.valid_from <= mid && mid < s.valid_until)
                        .map_or(0.0, |s| s.rate)
                })
                .collect();
            let weather: Vec<WeatherStep> = (0..=first)
                .map(|k| {
                    let start = now - period_d * (WINDOW - k) as i32;
                    let w = match inputs.scenario {
                        Some((sc, d0)) => scenario_weather(sc, d0, start),
                        None => climatology(start, SCENARIO_STEP),
                    };
                    WeatherStep {
                        start_hour: w.start_hour,
                        et0_mm: w.et0_mm * period / SCENARIO_STEP,
                        precip_mm: w.precip_mm * period / SCENARIO_STEP,
                    }
                })
                .collect();
            synthesised_history(
                e,
                inputs.field.spec.crop(),
                &rates,
                &weather,
                period,
                first_y,
            )
        })
    {
        let mut y = history;
        let mut last = first_y;
        for v in &past_y[first..] {
            last = v.unwrap_or(last);
            y.push(last);
        }
        return (past_u, y, past_e);
    }
    let mut y = Vec::with_capacity(WINDOW);
    let mut last = first_y;
    for (k, v) in past_y.iter().enumerate() {
        if k < first {
            // the padding: no supply, no uptake, a flat θ (MODEL.md §4)
            past_u[k] = 0.0;
            past_e[k] = 0.0;
            y.push(first_y);
        } else {
            last = v.unwrap_or(last);
            y.push(last);
        }
    }
    (past_u, y, past_e)
}

/// A past consistent with the estimate, for the samples before the first
/// measurement: the estimated column (soil and profile) is run forward
/// over the steps of `rates` (irrigation [m/s]) and `weather` (amounts per
/// step of `period` s), and its fall over k steps is taken as the rise k
/// steps back from `target`, the first measured θ. A field with no history
/// is thus taken to have come to its θ at the pace its own soil dries at
/// that θ, not to have stood still (which the surrogates read as a field
/// that does not dry). Returns θ at the end of each of the steps before
/// the last, oldest first; None when the column cannot be run.
pub fn synthesised_history(
    estimate: &EstimateView,
    crop: crate::soil::Crop,
    rates: &[f64],
    weather: &[WeatherStep],
    period: f64,
    target: f64,
) -> Option<Vec<f64>> {
    let mut model = RichardsModel::from_state(
        estimate.soil,
        crop,
        estimate.depth,
        estimate.heads.clone(),
        weather,
        period,
    )
    .ok()?;
    let mut ahead = vec![0.0; rates.len()];
    model.predict(rates, &mut ahead).ok()?;
    if !ahead.iter().all(|v| v.is_finite()) {
        return None;
    }
    // θ now at the sensor (the cell the model reads), on the estimate
    let cell = crate::soil::Column::new(estimate.soil, crop, estimate.depth, estimate.heads.len())
        .ok()?
        .sensor_cell();
    let now = estimate.soil.water_content(*estimate.heads.get(cell)?);
    let n = rates.len();
    let top = estimate.soil.saturated_water_content;
    Some(
        (0..n.saturating_sub(1))
            .map(|k| {
                // sample k lies n − 1 − k steps before the target
                let back = n - 1 - k;
                (target + (now - ahead[back - 1])).min(top)
            })
            .collect(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::service::wire::{Actuator, FieldSpec};
    use crate::surrogate::ModelFile;

    fn models() -> Models {
        let load = |text: &str, name: &str| {
            ModelFile::from_json(text, std::path::Path::new(name)).unwrap()
        };
        Models {
            two_layer: load(include_str!("../../models/two-layer.json"), "two-layer"),
            lstm: load(include_str!("../../models/single-lstm.json"), "single-lstm"),
        }
    }

    fn at(s: &str) -> DateTime<Utc> {
        DateTime::parse_from_rfc3339(s).unwrap().to_utc()
    }

    fn inputs(model: ModelKind) -> CycleInputs {
        CycleInputs {
            field: Field {
                id: 7,
                created_at: at("2026-06-01T00:00:00Z"),
                spec: FieldSpec {
                    model,
                    actuator: Actuator::None,
                    simulation: None,
                    ..FieldSpec::demo()
                },
            },
            now: at("2026-06-02T12:00:00Z"),
            recent: Vec::new(),
            measurements: Vec::new(),
            forecast: None,
            scenario: None,
            estimate: None,
            degraded: Vec::new(),
        }
    }

    fn reading(t: &str, theta: f64) -> Measurement {
        Measurement {
            time: at(t),
            theta,
            sensor: None,
            raw: None,
            true_theta: None,
        }
    }

    fn cancel() -> Arc<AtomicBool> {
        Arc::default()
    }

    #[test]
    fn without_a_measurement_the_cycle_falls_back_to_no_irrigation() {
        let sp = decide(&inputs(ModelKind::TwoLayer), &models(), &cancel());
        assert_eq!((sp.rate, sp.amount_mm), (0.0, 0.0));
        assert_eq!(sp.status, "fallback");
        for flag in ["no-measurement", "default-forecast", "solver-fallback"] {
            assert!(sp.degraded.contains(&flag.to_string()), "{:?}", sp.degraded);
        }
        assert_eq!(sp.valid_until - sp.valid_from, TimeDelta::hours(2));
        assert_eq!(sp.zone.len(), 20);
    }

    #[test]
    fn a_dry_field_is_irrigated_within_the_limit_and_a_wet_one_is_not() {
        let m = models();
        let forecast = |i: &CycleInputs| Forecast {
            issued_at: i.now,
            start: i.now,
            step_s: 7200.0,
            et0_mm: vec![0.4; 24],
            precip_mm: vec![0.0; 24],
        };
        for model in [ModelKind::Richards, ModelKind::TwoLayer] {
            let mut dry = inputs(model);
            dry.measurements = vec![reading("2026-06-02T11:55:00Z", 0.15)];
            dry.forecast = Some(forecast(&dry));
            let sp = decide(&dry, &m, &cancel());
            assert!(sp.rate > 0.0 && sp.rate <= 1e-5, "{model:?}: {sp:?}");
            assert!(sp.plan.iter().all(|u| (0.0..=1e-5).contains(u)));
            assert_eq!(sp.measured_at, Some(at("2026-06-02T11:55:00Z")));
            assert!(sp.degraded.is_empty(), "{:?}", sp.degraded);
            let mut wet = dry.clone();
            wet.measurements = vec![reading("2026-06-02T11:55:00Z", 0.26)];
            let sp = decide(&wet, &m, &cancel());
            // zero to the QP's tolerance: less than a micrometre of water.
            // (A surrogate, trained on θ in the zone's range, still
            // mispredicts a field this wet and irrigates it a little, even
            // with a window synthesised from the estimate: issue 17.)
            if model == ModelKind::Richards {
                assert!(sp.amount_mm < 1e-6, "{model:?}: {sp:?}");
            }
        }
    }

    #[test]
    fn the_bias_is_the_mean_one_step_residual_of_the_last_two_cycles() {
        let m = models();
        let mut i = inputs(ModelKind::TwoLayer);
        let past = |t: &str, until: &str, predicted: f64| Setpoint {
            field_id: 7,
            time: at(t),
            valid_from: at(t),
            valid_until: at(until),
            rate: 0.0,
            amount_mm: 0.0,
            plan: vec![0.0; 20],
            predicted_theta: vec![predicted; 20],
            zone: vec![[0.18, 0.23]; 20],
            model: ModelKind::TwoLayer,
            status: "converged".into(),
            fallback_reason: None,
            iterations: 1,
            solve_ms: 1.0,
            degraded: Vec::new(),
            measured_at: None,
            bias: 0.0,
            predicted_next: Some(predicted),
            valve: None,
            surrogate: None,
            forecast: None,
            predicted_theta_dry: Vec::new(),
            rain_mm: Vec::new(),
            et0_mm: Vec::new(),
            explanation: String::new(),
        };
        // newest first; a third, older one does not count
        i.recent = vec![
            past("2026-06-02T10:00:00Z", "2026-06-02T12:00:00Z", 0.200),
            past("2026-06-02T08:00:00Z", "2026-06-02T10:00:00Z", 0.210),
            past("2026-06-02T06:00:00Z", "2026-06-02T08:00:00Z", 0.300),
        ];
        i.measurements = vec![
            reading("2026-06-02T08:00:00Z", 0.250),
            reading("2026-06-02T10:00:00Z", 0.205),
            reading("2026-06-02T12:00:00Z", 0.195),
        ];
        let sp = decide(&i, &m, &cancel());
        // (0.205 − 0.210 + 0.195 − 0.200) / 2
        assert!((sp.bias - (-0.005)).abs() < 1e-12, "{}", sp.bias);
    }

    fn estimator() -> Estimator {
        Estimator::new(
            crate::estimate::Prior::Texture(crate::soil::Texture::SandyLoam),
            crate::soil::Crop::default(),
            vec![
                crate::estimate::Sensor {
                    id: "top".into(),
                    depth: 0.05,
                    noise: 0.01,
                },
                crate::estimate::Sensor {
                    id: "root".into(),
                    depth: 0.125,
                    noise: 0.01,
                },
            ],
            crate::estimate::InitialGuess::Reading(0.2),
            crate::estimate::EstimatorSettings::default(),
        )
        .unwrap()
    }

    fn sensor_reading(t: &str, sensor: &str, theta: f64) -> Measurement {
        Measurement {
            sensor: Some(sensor.into()),
            ..reading(t, theta)
        }
    }

    #[test]
    fn a_reading_late_within_the_window_counts_as_if_it_had_come_in_time() {
        let start = at("2026-06-02T00:00:00Z");
        let all = vec![
            sensor_reading("2026-06-02T01:00:00Z", "root", 0.21),
            sensor_reading("2026-06-02T02:00:00Z", "root", 0.20),
            sensor_reading("2026-06-02T02:00:00Z", "top", 0.17),
            sensor_reading("2026-06-02T03:00:00Z", "root", 0.19),
            sensor_reading("2026-06-02T04:00:00Z", "root", 0.185),
        ];
        let weather = |t| climatology(t, SCENARIO_STEP);
        let run = |est: &mut Estimator, clock, readings: &[Measurement], settle: &str| {
            assimilate(
                est,
                clock,
                0,
                readings,
                &[],
                &weather,
                7200.0,
                86_400.0,
                at(settle),
                "root",
            )
        };
        // in time: everything at once
        let mut on_time = estimator();
        let done = run(&mut on_time, start, &all, "2026-06-02T04:00:00Z");
        assert_eq!(done.clock, at("2026-06-02T04:00:00Z"));
        // late: the 02:00 readings and the 03:00 one are missing at the
        // first cycle, whose window settles the estimate after 01:00
        let mut late = estimator();
        let first: Vec<Measurement> = vec![all[0].clone(), all[4].clone()];
        let done = run(&mut late, start, &first, "2026-06-02T01:30:00Z");
        let (settled_at, snapshot, _) = done.settled;
        assert_eq!(settled_at, at("2026-06-02T01:00:00Z"));
        assert_ne!(late.mean_heads(), on_time.mean_heads());
        // the next cycle starts from the settled state with every reading
        let mut resumed = Estimator::restore(snapshot).unwrap();
        let done = run(&mut resumed, settled_at, &all, "2026-06-02T04:00:00Z");
        assert_eq!(done.clock, at("2026-06-02T04:00:00Z"));
        assert_eq!(resumed.mean_heads(), on_time.mean_heads());
        assert_eq!(resumed.soil(), on_time.soil());
        // a reading older than the settled state is not assimilated
        let mut again = Estimator::restore(late_snapshot(&all)).unwrap();
        let mut with_old = vec![sensor_reading("2026-06-02T00:30:00Z", "root", 0.30)];
        with_old.extend(all.iter().cloned());
        run(
            &mut again,
            at("2026-06-02T01:00:00Z"),
            &with_old,
            "2026-06-02T04:00:00Z",
        );
        assert_eq!(again.mean_heads(), on_time.mean_heads());
    }

    #[test]
    fn a_long_gap_is_forecast_over_its_last_span_only() {
        let weather = |t| climatology(t, SCENARIO_STEP);
        let run = |first: &str| {
            let mut est = estimator();
            let readings = [
                sensor_reading(first, "root", 0.22),
                sensor_reading("2026-06-12T00:00:00Z", "root", 0.19),
            ];
            let done = assimilate(
                &mut est,
                at(first) - TimeDelta::milliseconds(1),
                0,
                &readings,
                &[],
                &weather,
                7200.0,
                86_400.0,
                at("2026-06-12T00:00:00Z"),
                "root",
            );
            assert_eq!(done.clock, at("2026-06-12T00:00:00Z"));
            est
        };
        // ten days without a reading cost what one day does, and end alike
        let long = run("2026-06-02T00:00:00Z");
        let short = run("2026-06-11T00:00:00Z");
        assert_eq!(long.mean_heads(), short.mean_heads());
        assert_eq!(long.soil(), short.soil());
    }

    #[test]
    fn a_reading_the_estimate_cannot_explain_resets_it_and_says_so() {
        let weather = |t| climatology(t, SCENARIO_STEP);
        let mut est = estimator();
        // θ 0.21 in the root zone, then within the hour a saturated reading:
        // an innovation far beyond the filter's bound
        let readings = [
            sensor_reading("2026-06-02T01:00:00Z", "root", 0.21),
            sensor_reading("2026-06-02T02:00:00Z", "root", 0.21),
            sensor_reading("2026-06-02T02:15:00Z", "root", 0.41),
        ];
        let done = assimilate(
            &mut est,
            at("2026-06-02T00:59:00Z"),
            4,
            &readings,
            &[],
            &weather,
            7200.0,
            86_400.0,
            at("2026-06-02T03:00:00Z"),
            "root",
        );
        assert_eq!(done.flags, vec!["estimator-reset".to_string()]);
        assert_eq!(done.resets, 5, "the earlier resets are passed on");
        assert_eq!(done.reset_reasons.len(), 1);
        assert!(
            done.reset_reasons[0].contains("02:15"),
            "{:?}",
            done.reset_reasons
        );
        // the estimate is the prior again, finite
        assert!(est.mean_heads().iter().all(|h| h.is_finite()));
    }

    /// The estimate after the first reading of `all` alone.
    fn late_snapshot(all: &[Measurement]) -> EstimatorSnapshot {
        let mut est = estimator();
        let weather = |t| climatology(t, SCENARIO_STEP);
        let done = assimilate(
            &mut est,
            at("2026-06-02T00:00:00Z"),
            0,
            &all[..1],
            &[],
            &weather,
            7200.0,
            86_400.0,
            at("2026-06-02T01:00:00Z"),
            "root",
        );
        done.settled.1
    }

    #[test]
    fn the_weather_between_readings_is_the_newest_forecast_holding_the_time() {
        let old = Forecast {
            issued_at: at("2026-06-02T00:00:00Z"),
            start: at("2026-06-02T00:00:00Z"),
            step_s: 3600.0,
            et0_mm: vec![0.1; 12],
            precip_mm: vec![0.0; 12],
        };
        let new = Forecast {
            issued_at: at("2026-06-02T06:00:00Z"),
            start: at("2026-06-02T06:00:00Z"),
            step_s: 3600.0,
            et0_mm: vec![0.3; 12],
            precip_mm: vec![2.0; 12],
        };
        let both = [old, new];
        // 03:00 only the old one holds: 0.1 mm/h = 0.2 mm per 2-h step
        let w = observed_weather(&both, at("2026-06-02T03:00:00Z"));
        assert!(
            (w.et0_mm - 0.2).abs() < 1e-12 && w.precip_mm == 0.0,
            "{w:?}"
        );
        // 07:00 both do: the newer wins
        let w = observed_weather(&both, at("2026-06-02T07:00:00Z"));
        assert!((w.et0_mm - 0.6).abs() < 1e-12 && (w.precip_mm - 4.0).abs() < 1e-12);
        // after both: the climatology
        let t = at("2026-06-03T03:00:00Z");
        assert_eq!(
            observed_weather(&both, t).et0_mm,
            climatology(t, SCENARIO_STEP).et0_mm
        );
    }

    fn view_at(theta: f64) -> EstimateView {
        let soil = VanGenuchten::SANDY_LOAM;
        EstimateView {
            heads: vec![soil.pressure_head_at(theta); 26],
            soil,
            depth: 0.5,
            output_sd: 0.0,
            selecting: false,
        }
    }

    #[test]
    fn a_richards_field_planning_on_its_estimate_backs_the_lower_bound_off() {
        let m = models();
        for (model, sd, low) in [
            (ModelKind::Richards, 0.0, 0.18),
            (ModelKind::Richards, 0.004, 0.182),
            // at most half the zone's width
            (ModelKind::Richards, 1.0, 0.205),
            // the surrogates do not plan on the estimate
            (ModelKind::TwoLayer, 0.004, 0.18),
        ] {
            let mut i = inputs(model);
            i.measurements = vec![reading("2026-06-02T11:55:00Z", 0.2)];
            i.estimate = Some(EstimateView {
                output_sd: sd,
                ..view_at(0.2)
            });
            let sp = decide(&i, &m, &cancel());
            assert_eq!(sp.zone.len(), 20);
            for z in &sp.zone {
                assert!((z[0] - low).abs() < 1e-12, "{model:?} sd {sd}: {z:?}");
                assert_eq!(z[1], 0.23, "{model:?} sd {sd}");
            }
        }
    }

    /// The daemon's cycle and the in-process estimated controller (E8's and
    /// `rootzone closed-loop`'s) plan by one function, `step_on_estimate`:
    /// on the same estimate, reading and forecast they publish the same
    /// rate, plan, prediction and zone, bit for bit.
    #[test]
    fn the_daemon_and_the_in_process_controller_plan_alike_on_one_estimate() {
        use crate::control::EstimatedRichards;
        use crate::estimate::{Estimator, EstimatorSettings, InitialGuess, Prior, Sensor};
        use crate::soil::{Crop, Texture};
        let m = models();
        for (prior, theta) in [
            (Prior::Texture(Texture::SandyLoam), 0.165),
            (Prior::Texture(Texture::Loam), 0.2),
            // still selecting the texture: the sound start holds a wet field
            (Prior::Unknown, 0.25),
        ] {
            let estimator = Estimator::new(
                prior,
                Crop::default(),
                vec![Sensor {
                    id: "default".into(),
                    depth: 0.125,
                    noise: 0.004,
                }],
                InitialGuess::Reading(theta),
                EstimatorSettings::default(),
            )
            .unwrap();
            let mut i = inputs(ModelKind::Richards);
            i.measurements = vec![reading("2026-06-02T11:55:00Z", theta)];
            let forecast = Forecast {
                issued_at: i.now,
                start: i.now,
                step_s: 7200.0,
                et0_mm: (0..24).map(|k| 0.2 + 0.05 * (k % 6) as f64).collect(),
                precip_mm: (0..24).map(|k| if k == 9 { 4.0 } else { 0.0 }).collect(),
            };
            i.forecast = Some(forecast.clone());
            let view = EstimateView::of(&estimator);
            i.estimate = Some(view.clone());
            let daemon = decide(&i, &m, &cancel());

            let settings = i.field.spec.mpc_settings_with(Some(&view.soil));
            let mut in_process =
                EstimatedRichards::new(settings, estimator, i.field.spec.crop(), 7200.0)
                    .with_reading(theta);
            let (weather, defaulted) = horizon_weather(Some(&forecast), 7200.0, i.now, 20);
            assert!(!defaulted);
            let own = in_process.decide(&weather);
            let what = format!("{} at θ {theta}", prior.describe());
            assert_eq!(daemon.rate, own.setpoint, "{what}");
            assert_eq!(daemon.status, "converged", "{what}");
            assert_eq!(daemon.predicted_theta, own.solution.predicted, "{what}");
            let zone: Vec<[f64; 2]> = own.solution.zone.iter().map(|&(l, u)| [l, u]).collect();
            assert_eq!(daemon.zone, zone, "{what}");
            if prior == Prior::Unknown {
                assert_eq!(daemon.rate, 0.0, "{what}: held while selecting");
            } else if theta < 0.18 {
                assert!(daemon.rate > 0.0, "{what}: below the zone, irrigated");
            }
        }
    }

    #[test]
    fn a_richards_field_whose_texture_is_still_being_selected_is_not_irrigated_above_its_zone() {
        // the estimate says dry, the sensor says wet
        let m = models();
        let mut rates = Vec::new();
        for selecting in [true, false] {
            let mut i = inputs(ModelKind::Richards);
            i.measurements = vec![reading("2026-06-02T11:55:00Z", 0.25)];
            i.estimate = Some(EstimateView {
                selecting,
                ..view_at(0.14)
            });
            let sp = decide(&i, &m, &cancel());
            rates.push(sp.rate);
            // a held field publishes the zero it applies
            assert_eq!(
                sp.plan.first().copied(),
                Some(sp.rate),
                "selecting {selecting}"
            );
        }
        assert_eq!(rates[0], 0.0, "held while selecting");
        assert!(rates[1] > 0.0, "the settled estimate irrigates: {rates:?}");
        // below its zone a selecting field is irrigated
        let mut i = inputs(ModelKind::Richards);
        i.measurements = vec![reading("2026-06-02T11:55:00Z", 0.15)];
        i.estimate = Some(EstimateView {
            selecting: true,
            ..view_at(0.14)
        });
        assert!(decide(&i, &m, &cancel()).rate > 0.0);
    }

    #[test]
    fn a_synthesised_history_dries_down_to_the_first_measured_theta() {
        let period = 7200.0;
        let t0 = at("2026-06-01T00:00:00Z");
        let weather: Vec<WeatherStep> = (0..20)
            .map(|k| climatology(t0 + TimeDelta::hours(2 * k), period))
            .collect();
        let y = synthesised_history(
            &view_at(0.2),
            crate::soil::Crop::default(),
            &[0.0; 20],
            &weather,
            period,
            0.2,
        )
        .unwrap();
        // the 19 samples before the first measured one
        assert_eq!(y.len(), 19);
        // no supply, only uptake and drainage: the past was wetter, and the
        // nearer the measurement the nearer its θ
        assert!(y.windows(2).all(|w| w[1] <= w[0] + 1e-12), "{y:?}");
        assert!(y[0] > 0.2 + 1e-3 && y[18] >= 0.2, "{y:?}");
        // the rise one step back is the column's own fall over one step
        let soil = VanGenuchten::SANDY_LOAM;
        let mut model = RichardsModel::from_state(
            soil,
            crate::soil::Crop::default(),
            0.5,
            view_at(0.2).heads,
            &weather,
            period,
        )
        .unwrap();
        let mut ahead = [0.0; 1];
        model.predict(&[0.0], &mut ahead).unwrap();
        assert!(
            (y[18] - (0.2 + (0.2 - ahead[0]))).abs() < 1e-9,
            "{y:?} {ahead:?}"
        );
    }

    #[test]
    fn without_history_the_surrogate_window_comes_from_the_estimate() {
        let mut i = inputs(ModelKind::TwoLayer);
        i.measurements = vec![reading("2026-06-02T12:00:00Z", 0.2)];
        // no estimate: the documented padding, flat and without supply
        let (u, y, e) = window(&i, 0.2);
        assert!(u.iter().all(|v| *v == 0.0) && y.iter().all(|v| *v == 0.2));
        // the padded samples have no ET0 either; the last, measured one has
        // the climatology's at its middle (no forecast stored)
        assert!(e[..WINDOW - 1].iter().all(|v| *v == 0.0), "{e:?}");
        let mid = i.now - TimeDelta::hours(1);
        let want = mm_to_rate(climatology(mid, SCENARIO_STEP).et0_mm, SCENARIO_STEP);
        assert_eq!(e[WINDOW - 1], want);
        // with one: the estimated column's own dry-down, ending at the reading
        i.estimate = Some(view_at(0.2));
        let (u, y, e) = window(&i, 0.2);
        assert_eq!((u.len(), y.len()), (WINDOW, WINDOW));
        // a synthesised past has its weather's ET0 at every sample
        for (k, e) in e.iter().enumerate() {
            let mid = i.now - TimeDelta::hours(2 * (WINDOW - 1 - k) as i64) - TimeDelta::hours(1);
            let want = mm_to_rate(climatology(mid, SCENARIO_STEP).et0_mm, SCENARIO_STEP);
            assert_eq!(*e, want, "sample {k}");
        }
        assert_eq!(y[WINDOW - 1], 0.2);
        let weather: Vec<WeatherStep> = (0..WINDOW)
            .map(|k| climatology(i.now - TimeDelta::hours(2 * (WINDOW - k) as i64), 7200.0))
            .collect();
        let expected = synthesised_history(
            &view_at(0.2),
            i.field.spec.crop(),
            &[0.0; WINDOW],
            &weather,
            7200.0,
            0.2,
        )
        .unwrap();
        assert_eq!(&y[..WINDOW - 1], &expected[..], "{y:?}");
        assert!(y[0] > y[WINDOW - 2], "{y:?}");
    }

    #[test]
    fn a_surrogate_without_history_does_not_irrigate_a_field_above_its_zone() {
        let m = models();
        // the cases: θ 0.2605 under dry weather, 0.256 under rain
        for (theta, rain_mm) in [(0.2605, 0.0), (0.256, 1.5)] {
            for with_estimate in [false, true] {
                let mut wet = inputs(ModelKind::TwoLayer);
                wet.measurements = vec![reading("2026-06-02T11:55:00Z", theta)];
                wet.forecast = Some(Forecast {
                    issued_at: wet.now,
                    start: wet.now,
                    step_s: 7200.0,
                    et0_mm: vec![0.33; 24],
                    precip_mm: vec![rain_mm; 24],
                });
                wet.estimate = with_estimate.then(|| view_at(theta));
                let sp = decide(&wet, &m, &cancel());
                assert_eq!(sp.rate, 0.0, "θ {theta}: {sp:?}");
                assert_eq!(sp.plan[0], 0.0);
                // a dry field in the same state of history is irrigated
                let mut dry = wet.clone();
                dry.measurements = vec![reading("2026-06-02T11:55:00Z", 0.15)];
                dry.estimate = with_estimate.then(|| view_at(0.15));
                dry.forecast.as_mut().unwrap().precip_mm = vec![0.0; 24];
                assert!(decide(&dry, &m, &cancel()).rate > 0.0);
            }
        }
    }

    #[test]
    fn a_stale_measurement_is_flagged_and_the_last_prediction_used() {
        let m = models();
        let mut i = inputs(ModelKind::TwoLayer);
        i.measurements = vec![reading("2026-06-02T04:00:00Z", 0.2)];
        let sp = decide(&i, &m, &cancel());
        assert!(sp.degraded.contains(&"stale-measurement".to_string()));
        assert_eq!(sp.measured_at, None);
    }
}
