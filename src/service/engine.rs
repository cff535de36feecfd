//! The daemon's work, synchronous (it runs on the blocking pool): a field's
//! control cycle, rebuilt from storage every time, and the simulated plants.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use chrono::{DateTime, TimeDelta, Timelike, Utc};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use crate::control::{PredictionModel, RichardsModel, SolveStatus, SurrogateModel, ZoneMpc};
use crate::sim::{
    PlantState, SCENARIO_STEP, SimulatedPlant, scenario_forecast, scenario_series, scenario_weather,
};
use crate::soil::{Field as Plant, FieldSettings};
use crate::surrogate::ModelFile;
use crate::surrogate::evaluate::WINDOW;
use crate::weather::{WeatherStep, mm_to_rate, rate_to_mm};

use super::store::{Store, StoreError};
use super::wire::{Actuator, Field, Forecast, ModelKind, Scenario, Setpoint};

/// How many past setpoints enter the bias (MODEL.md: f = 2).
const BIAS_PERIOD: usize = 2;
/// The surrogates, loaded once.
pub struct Models {
    pub two_layer: ModelFile,
    pub lstm: ModelFile,
}

/// Shared state of the work: storage, models, the simulated plants.
pub struct Engine {
    pub store: Arc<Store>,
    pub models: Models,
    plants: Mutex<HashMap<i64, Arc<Mutex<SimulatedPlant>>>>,
    /// Set at shutdown: running solves stop as at their time budget.
    pub cancel: Arc<std::sync::atomic::AtomicBool>,
    /// Longest span a simulated plant replays [s of clock time].
    max_catch_up_s: f64,
}

/// A failure of the work (not of the input).
#[derive(Debug, thiserror::Error)]
pub enum EngineError {
    #[error(transparent)]
    Store(#[from] StoreError),
    #[error("simulated field {0}: {1}")]
    Plant(i64, String),
}

fn seconds(d: TimeDelta) -> f64 {
    d.num_milliseconds() as f64 / 1000.0
}

impl Engine {
    pub fn new(store: Arc<Store>, models: Models) -> Engine {
        Engine {
            store,
            models,
            plants: Mutex::new(HashMap::new()),
            cancel: Arc::default(),
            max_catch_up_s: 2.0 * 86_400.0,
        }
    }

    /// The longest span [s] a simulated plant replays to catch up with the
    /// clock; what lies before is skipped (the plant keeps its state).
    pub fn catch_up_limit(mut self, seconds: f64) -> Engine {
        self.max_catch_up_s = seconds;
        self
    }

    /// The climatological forecast: the dry scenario's daily ET0 cycle by
    /// hour of day, no rain; amounts per step of `period` seconds.
    fn climatology(&self, t: DateTime<Utc>, period: f64) -> WeatherStep {
        let hour = t.hour() as f64 + t.minute() as f64 / 60.0;
        let k = ((hour * 3600.0) / SCENARIO_STEP).floor() as usize % 12;
        let step = scenario_series(Scenario::Dry).steps()[k];
        WeatherStep {
            start_hour: hour,
            et0_mm: step.et0_mm * period / SCENARIO_STEP,
            precip_mm: 0.0,
        }
    }

    /// The simulated plant of `field`, created or resumed from storage.
    pub fn plant(&self, field: &Field) -> Result<Option<Arc<Mutex<SimulatedPlant>>>, EngineError> {
        let (Actuator::Simulated, Some(spec)) = (&field.spec.actuator, field.spec.simulation)
        else {
            return Ok(None);
        };
        let mut plants = self.plants.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(p) = plants.get(&field.id) {
            return Ok(Some(p.clone()));
        }
        let saved: Option<PlantState> = match self.store.simulation(field.id)? {
            Some(body) => Some(serde_json::from_str(&body).map_err(StoreError::from)?),
            None => None,
        };
        let plant = SimulatedPlant::new(
            &field.spec,
            spec,
            spec.start.unwrap_or(field.created_at),
            saved.as_ref(),
        )
        .map_err(|e| EngineError::Plant(field.id, e))?;
        let p = Arc::new(Mutex::new(plant));
        plants.insert(field.id, p.clone());
        Ok(Some(p))
    }

    /// Forgets a deleted field's plant.
    pub fn forget(&self, field: i64) {
        self.plants
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .remove(&field);
    }

    /// Advances a simulated field's plant to clock time `now`, one
    /// measurement interval at a time, applying the setpoint in force at
    /// each interval and storing each noisy measurement. Returns how many
    /// measurements were stored.
    pub fn advance_plant(&self, field: &Field, now: DateTime<Utc>) -> Result<usize, EngineError> {
        let Some(plant) = self.plant(field)? else {
            return Ok(0);
        };
        let mut p = plant.lock().unwrap_or_else(|e| e.into_inner());
        let store = &self.store;
        let advance = p.advance(now, self.max_catch_up_s, |t| {
            // the latest setpoint issued at or before t
            let recent = store.recent_setpoints(field.id, 8)?;
            Ok::<_, EngineError>(match recent.iter().find(|s| s.time <= t) {
                Some(s) if s.valid_until > t => (s.rate, s.valid_until),
                _ => (0.0, t),
            })
        })?;
        if let Some((from, to)) = advance.skipped {
            tracing::warn!(
                field = field.id, from = %from, to = %to,
                "simulation behind the clock: skipped to replay at most {} s (limits.max_catch_up_s)",
                self.max_catch_up_s
            );
        }
        let batch = advance.readings;
        let failure = advance
            .failure
            .map(|e| EngineError::Plant(field.id, e.to_string()));
        if !batch.is_empty() {
            self.store.add_measurements(field.id, &batch)?;
            let state = serde_json::to_string(&p.state()).map_err(StoreError::from)?;
            self.store.put_simulation(field.id, &state)?;
        }
        match failure {
            Some(e) => Err(e),
            None => Ok(batch.len()),
        }
    }

    /// The true state of a simulated field.
    pub fn simulation_state(&self, field: &Field) -> Result<Option<PlantState>, EngineError> {
        Ok(self
            .plant(field)?
            .map(|p| p.lock().unwrap_or_else(|e| e.into_inner()).state()))
    }

    /// A simulated field's weather service: the scenario from `now` with
    /// forecast error, stored as the field's latest forecast.
    fn simulated_forecast(
        &self,
        field: &Field,
        now: DateTime<Utc>,
        steps: usize,
    ) -> Result<(), EngineError> {
        let Some(plant) = self.plant(field)? else {
            return Ok(());
        };
        let (spec, day_zero) = {
            let p = plant.lock().unwrap_or_else(|e| e.into_inner());
            (*p.spec(), p.day_zero())
        };
        let period = field.spec.control_period_s;
        let mut rng = ChaCha8Rng::seed_from_u64(
            spec.seed.wrapping_add(1000) ^ (now.timestamp() as u64).rotate_left(20),
        );
        let forecast = scenario_forecast(
            spec.scenario,
            day_zero,
            now,
            period,
            steps,
            spec.forecast_error,
            &mut rng,
        );
        self.store.put_forecast(field.id, &forecast)?;
        Ok(())
    }

    /// The horizon's weather (amounts per control period) from the latest
    /// forecast, or the climatology where it is missing or stale.
    /// The climatological forecast a cycle at `now` falls back on: the
    /// horizon of control periods from the last period boundary.
    pub fn climatology_forecast(&self, field: &Field, now: DateTime<Utc>) -> Forecast {
        let period = field.spec.control_period_s;
        let start = super::clock::boundary_at_or_before(now, period);
        let n = field.spec.mpc_settings().horizon;
        let steps: Vec<WeatherStep> = (0..n)
            .map(|k| {
                self.climatology(
                    start + TimeDelta::milliseconds((k as f64 * period * 1000.0) as i64),
                    period,
                )
            })
            .collect();
        Forecast {
            issued_at: start,
            start,
            step_s: period,
            et0_mm: steps.iter().map(|w| w.et0_mm).collect(),
            precip_mm: steps.iter().map(|w| w.precip_mm).collect(),
        }
    }

    fn horizon_weather(
        &self,
        field: &Field,
        now: DateTime<Utc>,
        n: usize,
    ) -> Result<(Vec<WeatherStep>, bool), EngineError> {
        let period = field.spec.control_period_s;
        let forecast = self
            .store
            .latest_forecast(field.id)?
            .filter(|f| seconds(now - f.issued_at) <= 2.0 * period);
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
                    out.push(self.climatology(t0, period));
                }
            }
        }
        Ok((out, defaulted))
    }

    /// One control cycle of `field` at clock time `now`: the window from the
    /// stored history, the forecast, the zone MPC, the stored setpoint.
    pub fn control_cycle(
        &self,
        field: &Field,
        now: DateTime<Utc>,
    ) -> Result<Setpoint, EngineError> {
        let spec = &field.spec;
        let period = spec.control_period_s;
        let period_d = TimeDelta::milliseconds((period * 1000.0) as i64);
        let settings = spec.mpc_settings();
        let n = settings.horizon;
        let simulated = self.plant(field)?.is_some();
        let mut degraded = Vec::new();
        if simulated {
            if let Err(e) = self.advance_plant(field, now) {
                // the cycle still decides, on the latest stored measurement
                tracing::warn!(field = field.id, at = %now, error = %e,
                    "simulation before the cycle failed");
                degraded.push("simulation-failed".to_string());
            }
            self.simulated_forecast(field, now, n)?;
        }
        let (weather, defaulted) = self.horizon_weather(field, now, n)?;
        if defaulted {
            degraded.push("default-forecast".to_string());
        }
        let recent = self
            .store
            .recent_setpoints(field.id, WINDOW + BIAS_PERIOD)?;
        let latest = self.store.measurement_before(field.id, now)?;
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
        mpc.set_cancel(Some(self.cancel.clone()));
        if let Some(prev) = recent.first()
            && seconds(now - prev.time) <= 1.5 * period
            && prev.model == spec.model
        {
            mpc.remember(prev.plan.clone());
        }
        let mut bias = 0.0;
        let mut one_step: Option<SurrogateModel> = None;
        let solution = match (current, spec.model) {
            (None, _) => None,
            (Some(theta), ModelKind::Richards) => {
                // the controller sees what a real field gives: measurements,
                // never a simulated plant's true state (the column starts in
                // equilibrium with the measured θ)
                let soil = spec
                    .soil
                    .parameters()
                    .map_err(|e| EngineError::Plant(field.id, e))?;
                let head = soil.pressure_head_at(theta.clamp(
                    soil.residual_water_content + 1e-6,
                    soil.saturated_water_content - 1e-6,
                ));
                let plant = Plant::new(FieldSettings {
                    soil,
                    crop: spec.crop(),
                    initial_head: head,
                    sampling_time: period,
                    ..FieldSettings::default()
                })
                .map_err(|e| EngineError::Plant(field.id, e))?;
                let mut model = RichardsModel::new(&plant, &weather);
                Some(mpc.solve(&mut model as &mut dyn PredictionModel))
            }
            (Some(theta), kind) => {
                let file = if kind == ModelKind::Lstm {
                    &self.models.lstm
                } else {
                    &self.models.two_layer
                };
                let (past_u, past_y) = self.window(field, now, theta, &recent)?;
                let mut model = SurrogateModel::new(file.predictor(), past_u, past_y);
                // bias: mean over the last f cycles of y(t) − ŷ(t | t − 1)
                let mut residuals = Vec::new();
                for s in recent
                    .iter()
                    .filter(|s| s.valid_until <= now)
                    .take(BIAS_PERIOD)
                {
                    if let Some(m) = self.store.measurement_before(field.id, s.valid_until)?
                        && seconds(s.valid_until - m.time) <= period / 2.0
                        && let Some(predicted) = s.predicted_next
                    {
                        residuals.push(m.theta - predicted);
                    }
                }
                if !residuals.is_empty() {
                    bias = residuals.iter().sum::<f64>() / residuals.len() as f64;
                }
                model.bias = bias;
                model.rain = rain_rate.clone();
                let sol = mpc.solve(&mut model);
                one_step = Some(model);
                Some(sol)
            }
        };
        let Some(solution) = solution else {
            degraded.push("solver-fallback".into());
            let setpoint = Setpoint {
                field_id: field.id,
                time: now,
                valid_from: now,
                valid_until: now + period_d,
                rate: 0.0,
                amount_mm: 0.0,
                plan: vec![0.0; n],
                predicted_theta: Vec::new(),
                zone: (1..=n)
                    .map(|k| {
                        let (l, u) = settings.zone.bounds(k, n);
                        [l, u]
                    })
                    .collect(),
                model: spec.model,
                status: "fallback".into(),
                fallback_reason: Some("no measurement yet: no irrigation".into()),
                iterations: 0,
                solve_ms: 0.0,
                degraded,
                measured_at: None,
                bias: 0.0,
                predicted_next: None,
            };
            self.store.add_setpoint(&setpoint)?;
            return Ok(setpoint);
        };
        let first = solution.plan.first().copied().unwrap_or(0.0);
        let rate = if first.is_finite() {
            first.clamp(0.0, settings.u_max)
        } else {
            0.0
        };
        let (status, reason) = match &solution.status {
            SolveStatus::Converged => ("converged", None),
            SolveStatus::IterationCap => ("iteration-cap", None),
            SolveStatus::TimeBudget => ("time-budget", None),
            SolveStatus::Fallback(why) => ("fallback", Some(why.clone())),
        };
        if reason.is_some() {
            degraded.push("solver-fallback".into());
        }
        let predicted_next = match one_step.as_mut() {
            Some(model) => model
                .one_step(rate + rain_rate.first().copied().unwrap_or(0.0))
                .ok(),
            None => solution.predicted.first().copied(),
        }
        .filter(|p| p.is_finite());
        let setpoint = Setpoint {
            field_id: field.id,
            time: now,
            valid_from: now,
            valid_until: now + period_d,
            rate,
            amount_mm: rate_to_mm(rate, period),
            plan: solution
                .plan
                .iter()
                .map(|u| {
                    if u.is_finite() {
                        u.clamp(0.0, settings.u_max)
                    } else {
                        0.0
                    }
                })
                .collect(),
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
        };
        self.store.add_setpoint(&setpoint)?;
        Ok(setpoint)
    }

    /// The surrogate window at `now`: for each of the last 20 periods, the
    /// supply (the setpoint in force, plus the rain of a simulated field) and
    /// θ measured at its end; before the first measurement, (0, first θ).
    fn window(
        &self,
        field: &Field,
        now: DateTime<Utc>,
        current: f64,
        recent: &[Setpoint],
    ) -> Result<(Vec<f64>, Vec<f64>), EngineError> {
        let period = field.spec.control_period_s;
        let period_d = TimeDelta::milliseconds((period * 1000.0) as i64);
        let scenario = match (&field.spec.actuator, field.spec.simulation) {
            (Actuator::Simulated, Some(sim)) => Some(sim.scenario),
            _ => None,
        };
        let day_zero = self
            .plant(field)?
            .map(|p| p.lock().unwrap_or_else(|e| e.into_inner()).day_zero());
        let mut past_u = vec![0.0; WINDOW];
        let mut past_y: Vec<Option<f64>> = vec![None; WINDOW];
        for k in 0..WINDOW {
            // sample k ends at now − (WINDOW − 1 − k) periods
            let end = now - period_d * (WINDOW - 1 - k) as i32;
            let mid = end - period_d / 2;
            past_y[k] = if k + 1 == WINDOW {
                Some(current)
            } else {
                self.store
                    .measurement_before(field.id, end)?
                    .filter(|m| seconds(end - m.time) <= period)
                    .map(|m| m.theta)
            };
            let applied = recent
                .iter()
                .find(|s| s.valid_from <= mid && mid < s.valid_until)
                .map_or(0.0, |s| s.rate);
            let rain = match (scenario, day_zero) {
                (Some(sc), Some(d0)) => {
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
        let mut y = Vec::with_capacity(WINDOW);
        let mut last = first_y;
        for (k, v) in past_y.iter().enumerate() {
            if k < first {
                past_u[k] = 0.0;
                y.push(first_y);
            } else {
                last = v.unwrap_or(last);
                y.push(last);
            }
        }
        Ok((past_u, y))
    }
}
