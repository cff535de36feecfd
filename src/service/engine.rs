//! The daemon's work, synchronous (it runs on the blocking pool): a field's
//! control cycle, rebuilt from storage every time, and the simulated plants.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use chrono::{DateTime, TimeDelta, Utc};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use crate::sim::{PlantState, SimulatedPlant, scenario_forecast};
use crate::surrogate::ModelFile;
use crate::surrogate::evaluate::WINDOW;
use crate::weather::WeatherStep;

use super::cycle::{BIAS_PERIOD, CycleInputs, climatology, decide};
use super::store::{Sensors, Store, StoreError};
use super::wire::{Actuator, Field, Forecast, Setpoint};

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

    /// The climatological forecast a cycle at `now` falls back on: the
    /// horizon of control periods from the last period boundary.
    pub fn climatology_forecast(&self, field: &Field, now: DateTime<Utc>) -> Forecast {
        let period = field.spec.control_period_s;
        let start = super::clock::boundary_at_or_before(now, period);
        let n = field.spec.mpc_settings().horizon;
        let steps: Vec<WeatherStep> = (0..n)
            .map(|k| {
                climatology(
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

    /// One control cycle of `field` at clock time `now`: the window from the
    /// stored history, the forecast, the zone MPC, the stored setpoint.
    /// Reads what one cycle of `field` at `now` needs, in one go.
    pub fn load(&self, field: &Field, now: DateTime<Utc>) -> Result<CycleInputs, EngineError> {
        let period = field.spec.control_period_s;
        let span = TimeDelta::milliseconds(((WINDOW + 2) as f64 * period * 1000.0) as i64);
        let mut measurements = self.store.measurements(
            field.id,
            Some(now - span),
            Some(now),
            100_000,
            Sensors::Primary,
        )?;
        if measurements.is_empty()
            && let Some(latest) = self.store.measurement_before(field.id, now)?
        {
            measurements.push(latest);
        }
        let scenario = match (&field.spec.actuator, field.spec.simulation) {
            (Actuator::Simulated, Some(sim)) => self.plant(field)?.map(|p| {
                (
                    sim.scenario,
                    p.lock().unwrap_or_else(|e| e.into_inner()).day_zero(),
                )
            }),
            _ => None,
        };
        Ok(CycleInputs {
            field: field.clone(),
            now,
            recent: self
                .store
                .recent_setpoints(field.id, WINDOW + BIAS_PERIOD)?,
            measurements,
            forecast: self.store.latest_forecast(field.id)?,
            scenario,
            degraded: Vec::new(),
        })
    }

    /// One control cycle: a simulated field's plant and weather service
    /// first, then load → decide → store.
    pub fn control_cycle(
        &self,
        field: &Field,
        now: DateTime<Utc>,
    ) -> Result<Setpoint, EngineError> {
        let mut flags = Vec::new();
        if self.plant(field)?.is_some() {
            if let Err(e) = self.advance_plant(field, now) {
                // the cycle still decides, on the latest stored measurement
                tracing::warn!(field = field.id, at = %now, error = %e,
                    "simulation before the cycle failed");
                flags.push("simulation-failed".to_string());
            }
            let n = field.spec.mpc_settings().horizon;
            self.simulated_forecast(field, now, n)?;
        }
        let mut inputs = self.load(field, now)?;
        inputs.degraded = flags;
        let setpoint = decide(&inputs, &self.models, &self.cancel);
        self.store.add_setpoint(&setpoint)?;
        Ok(setpoint)
    }
}
