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

use super::cycle::{
    BIAS_PERIOD, CycleInputs, EstimateView, assimilate, climatology, decide, observed_weather,
    window_is_measured,
};
use super::store::{CycleOutputs, CycleQuery, CycleRead, CycleRun, Store, StoreError};
use super::wire::{Actuator, Field, Forecast, Measurement, Setpoint};
use crate::estimate::{
    Estimator, EstimatorSettings, EstimatorSnapshot, InitialGuess, Prior, Sensor as EstimatedSensor,
};

/// The surrogates, loaded once.
pub struct Models {
    pub two_layer: ModelFile,
    pub lstm: ModelFile,
}

/// A field's stored state estimate: the estimator's snapshot, the clock
/// time it has reached, how often it was reset, and the settled estimate
/// the next cycle starts from.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct StoredEstimate {
    pub time: DateTime<Utc>,
    pub snapshot: EstimatorSnapshot,
    #[serde(default)]
    pub resets: u64,
    /// The estimate after the last reading older than the late window.
    #[serde(default)]
    pub settled: Option<Box<Checkpoint>>,
    /// The readings assimilated after the settled estimate, up to `time`.
    /// When the next cycle finds exactly these there and `time` has left
    /// the late window, it goes on from this estimate instead of replaying
    /// them from the settled one (the same result: no reading came late).
    #[serde(default)]
    pub seen: Option<Seen>,
}

/// A summary of the readings of a span: how many, and an order-free digest
/// of their times, sensors and values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct Seen {
    pub count: u64,
    pub digest: u64,
}

impl Seen {
    /// The readings of `readings` in (`after`, `until`].
    pub fn of(readings: &[Measurement], after: DateTime<Utc>, until: DateTime<Utc>) -> Seen {
        use std::hash::{Hash, Hasher};
        let mut seen = Seen {
            count: 0,
            digest: 0,
        };
        for m in readings
            .iter()
            .filter(|m| m.time > after && m.time <= until)
        {
            // a fixed-key hasher: the digest is stored and compared later
            let mut h = std::hash::DefaultHasher::new();
            m.time.timestamp_micros().hash(&mut h);
            m.sensor.hash(&mut h);
            m.theta.to_bits().hash(&mut h);
            seen.count += 1;
            seen.digest = seen.digest.wrapping_add(h.finish());
        }
        seen
    }
}

/// An estimate at a time.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct Checkpoint {
    pub time: DateTime<Utc>,
    pub snapshot: EstimatorSnapshot,
    pub resets: u64,
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
    /// How late [s of clock time] a reading may arrive and still be
    /// assimilated.
    late_window_s: f64,
    /// The fields' own surrogates (`service::training`).
    pub own_models: super::training::OwnModels,
    /// The polled forecast sources' staleness and rounding.
    forecasts: crate::adapters::forecast::ForecastSettings,
    /// Whether a scheduled surrogate cycle may leave its state estimate to
    /// [`Engine::update_estimate`] (see [`Engine::control_cycle`]).
    defer_estimates: bool,
}

/// A failure of the work (not of the input).
#[derive(Debug, thiserror::Error)]
pub enum EngineError {
    #[error(transparent)]
    Store(#[from] StoreError),
    #[error("simulated field {0}: {1}")]
    Plant(i64, String),
}

/// What [`Engine::estimate`] gives a cycle: the estimate it plans on, the
/// estimator's flags and the record to store with the setpoint (JSON).
pub type Estimated = (Option<EstimateView>, Vec<String>, Option<String>);

impl Engine {
    pub fn new(store: Arc<Store>, models: Models) -> Engine {
        Engine {
            store,
            models,
            plants: Mutex::new(HashMap::new()),
            cancel: Arc::default(),
            max_catch_up_s: super::settings::default_catch_up(),
            late_window_s: super::settings::default_late_window(),
            defer_estimates: false,
            own_models: super::training::OwnModels::disabled(),
            forecasts: Default::default(),
        }
    }

    /// Lets scheduled surrogate cycles defer their state estimate (the
    /// daemon does, with threads that run [`Engine::update_estimate`]).
    pub fn defer_estimates(mut self, defer: bool) -> Engine {
        self.defer_estimates = defer;
        self
    }

    /// Where the fields' own surrogates are stored.
    pub fn own_models(mut self, own: super::training::OwnModels) -> Engine {
        self.own_models = own;
        self
    }

    /// The settings of the polled forecast sources.
    pub fn forecast_settings(
        mut self,
        settings: crate::adapters::forecast::ForecastSettings,
    ) -> Engine {
        self.forecasts = settings;
        self
    }

    /// The forecast a cycle of `field` at `now` uses, a flag when it falls
    /// back, and the record of it: a field with a `forecast_source` uses
    /// that source's last good forecast while it is fresh, else (stale, or
    /// never fetched) the climatology, flagged `stale-forecast`; a field
    /// without one the latest stored forecast.
    pub fn cycle_forecast(
        &self,
        field: &Field,
        now: DateTime<Utc>,
        stored: Option<Forecast>,
        source_state: Option<&str>,
    ) -> Result<(Option<Forecast>, Option<String>, super::wire::ForecastUsed), EngineError> {
        use crate::adapters::forecast::{SourceState, for_cycle};
        let period = field.spec.control_period_s;
        if let Some(src) = &field.spec.forecast_source {
            let state: Option<SourceState> =
                source_state.and_then(|b| serde_json::from_str(b).ok());
            let (f, flag, used) = for_cycle(
                src.provider,
                state.as_ref(),
                period,
                now,
                self.forecasts.stale_after_s,
            );
            return Ok((f, flag.map(str::to_string), used));
        }
        let fresh = stored
            .as_ref()
            .filter(|f| (now - f.issued_at).num_milliseconds() as f64 <= 2e3 * period);
        let used = super::wire::ForecastUsed {
            source: match (fresh, &field.spec.actuator) {
                (None, _) => "climatology",
                (Some(_), Actuator::Simulated) => "simulated",
                (Some(_), _) => "posted",
            }
            .into(),
            issued_at: fresh.map(|f| f.issued_at),
            fetched_at: None,
        };
        Ok((stored, None, used))
    }

    /// How late [s of clock time] a reading may arrive and still enter the
    /// state estimate.
    pub fn late_window(mut self, seconds: f64) -> Engine {
        self.late_window_s = seconds;
        self
    }

    /// The longest span [s] a simulated plant replays to catch up with the
    /// clock; what lies before is skipped (the plant keeps its state).
    pub fn catch_up_limit(mut self, seconds: f64) -> Engine {
        self.max_catch_up_s = seconds;
        self
    }

    /// The simulated plant of `field`, created or resumed from storage.
    pub fn plant(&self, field: &Field) -> Result<Option<Arc<Mutex<SimulatedPlant>>>, EngineError> {
        let (Actuator::Simulated, Some(spec)) =
            (&field.spec.actuator, field.spec.simulation.clone())
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
            spec.clone(),
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
            (p.spec().clone(), p.day_zero())
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
    /// A simulated field's weather scenario and day zero (its weather is
    /// known); None for a real field.
    fn scenario(
        &self,
        field: &Field,
    ) -> Result<Option<(super::wire::Scenario, DateTime<Utc>)>, EngineError> {
        let (Actuator::Simulated, Some(sim)) =
            (&field.spec.actuator, field.spec.simulation.clone())
        else {
            return Ok(None);
        };
        Ok(self.plant(field)?.map(|p| {
            (
                sim.scenario,
                p.lock().unwrap_or_else(|e| e.into_inner()).day_zero(),
            )
        }))
    }

    /// What one cycle of `field` at `now` reads ([`Store::cycle_read`]):
    /// every reading of the longer of the surrogate window (plus two
    /// periods) and the estimator's catch-up span; the setpoints and stored
    /// forecasts from two days before that (the weather and irrigation the
    /// estimate replays); the latest setpoints for the warm start and bias.
    fn cycle_query(&self, field: &Field, now: DateTime<Utc>, scenario: bool) -> CycleQuery {
        let period = field.spec.control_period_s;
        let window = (WINDOW + 2) as f64 * period;
        let span = self.max_catch_up_s.max(period);
        let from = super::clock::add_seconds(now, -window.max(span));
        let before = from - TimeDelta::days(2);
        CycleQuery {
            field: field.id,
            now,
            readings_from: from,
            readings_limit: 100_000,
            setpoints_from: before,
            recent: WINDOW + BIAS_PERIOD,
            forecasts_from: (!scenario).then_some(before),
            forecast_source: field
                .spec
                .forecast_source
                .as_ref()
                .map(|src| src.key(self.forecasts.location_decimals).id()),
        }
    }

    /// The controller's inputs from the cycle's read: the primary sensor's
    /// readings over the window (or, with none there, its latest one).
    fn load(
        &self,
        field: &Field,
        now: DateTime<Utc>,
        read: &mut CycleRead,
        scenario: Option<(super::wire::Scenario, DateTime<Utc>)>,
    ) -> CycleInputs {
        let period = field.spec.control_period_s;
        let window_from = super::clock::add_seconds(now, -((WINDOW + 2) as f64 * period));
        let mut measurements: Vec<_> = read
            .readings
            .iter()
            .filter(|m| m.sensor.is_none() && m.time >= window_from)
            .cloned()
            .collect();
        if measurements.is_empty()
            && let Some(latest) = read.latest_primary.clone()
        {
            measurements.push(latest);
        }
        CycleInputs {
            field: field.clone(),
            now,
            recent: std::mem::take(&mut read.recent),
            measurements,
            forecast: read.latest_forecast.take(),
            scenario,
            estimate: None,
            degraded: Vec::new(),
        }
    }

    /// The estimator of a new field: the prior of its declared soil (a
    /// texture, or given parameters), its sensors, members started from its
    /// first reading.
    fn new_estimator(&self, field: &Field, first: f64) -> Result<Estimator, String> {
        let prior = match &field.spec.soil {
            soil if soil.is_unknown() => Prior::Unknown,
            super::wire::SoilSpec::Preset(name) => Prior::Texture(
                name.parse::<crate::soil::Texture>()
                    .map_err(|e| e.to_string())?,
            ),
            soil => Prior::Soil(soil.parameters()?),
        };
        let sensors = field
            .spec
            .effective_sensors()
            .into_iter()
            .map(|s| EstimatedSensor {
                id: s.id,
                depth: s.depth,
                // the filter needs a positive observation error
                noise: s.noise.max(0.005),
            })
            .collect();
        Estimator::new(
            prior,
            field.spec.crop(),
            sensors,
            InitialGuess::Reading(first),
            EstimatorSettings {
                seed: (field.id as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15),
                ..EstimatorSettings::default()
            },
        )
    }

    /// Brings the field's state estimate up to `now`: restored from its
    /// settled state (the estimate after the last reading older than the
    /// late window) or started from the first reading, then [`assimilate`]
    /// over every reading since, so readings that arrive late or out of
    /// order within the window count. The weather between readings is the
    /// scenario's for a simulated field, else the forecast nearest the
    /// time, else the climatology. A diverged estimator is reset to its
    /// prior and flagged `estimator-reset`. Stores the current and the
    /// settled estimate (JSON, for the cycle to store with its setpoint) and
    /// returns what the cycle uses.
    pub fn estimate(
        &self,
        field: &Field,
        now: DateTime<Utc>,
        read: &CycleRead,
        scenario: Option<(super::wire::Scenario, DateTime<Utc>)>,
    ) -> Result<Estimated, EngineError> {
        let period = field.spec.control_period_s;
        let stored: Option<StoredEstimate> = read
            .estimate
            .as_deref()
            .and_then(|body| serde_json::from_str(body).ok());
        let settle_before = now - TimeDelta::milliseconds((self.late_window_s * 1e3) as i64);
        let restored = stored.and_then(|s| {
            // from the settled state, or from the estimate itself when it
            // has left the late window and no reading came in late since
            // (see `StoredEstimate::seen`); an estimate stored without
            // either starts from itself. However old it is, the soil it has
            // learnt is kept: a long gap is forecast over its last catch-up
            // span only.
            let (time, snapshot, resets) = match s.settled {
                Some(c)
                    if !(s.time <= settle_before
                        && s.seen == Some(Seen::of(&read.readings, c.time, s.time))) =>
                {
                    (c.time, c.snapshot, c.resets)
                }
                _ => (s.time, s.snapshot, s.resets),
            };
            Some((Estimator::restore(snapshot).ok()?, time, resets))
        });
        let (mut est, clock, resets) = match restored {
            Some(found) => found,
            None => {
                // start from the first primary reading within the catch-up span
                let from = now - TimeDelta::milliseconds((self.max_catch_up_s * 1e3) as i64);
                let first = read
                    .readings
                    .iter()
                    .find(|m| m.sensor.is_none() && m.time >= from);
                let Some(first) = first else {
                    return Ok((None, Vec::new(), None));
                };
                let est = self
                    .new_estimator(field, first.theta)
                    .map_err(|e| EngineError::Plant(field.id, e))?;
                (est, first.time - TimeDelta::milliseconds(1), 0)
            }
        };
        // the readings since, within the catch-up span (older ones would be
        // forecast over nothing and updated on stale weather)
        let span = TimeDelta::milliseconds((self.max_catch_up_s.max(period) * 1e3) as i64);
        // (both are oldest first: the ones wanted are a tail of each)
        let since = (clock + TimeDelta::milliseconds(1)).max(now - span);
        let readings = &read.readings[read.readings.partition_point(|m| m.time < since)..];
        let back = clock - TimeDelta::days(2);
        let setpoints = &read.setpoints[read.setpoints.partition_point(|s| s.time < back)..];
        let forecasts: Vec<_> = read
            .forecasts
            .iter()
            .filter(|f| f.issued_at >= back)
            .cloned()
            .collect();
        let weather_at = |t: DateTime<Utc>| match scenario {
            Some((sc, d0)) => crate::sim::scenario_weather(sc, d0, t),
            None => observed_weather(&forecasts, t),
        };
        let primary = field.spec.effective_sensors()[0].id.clone();
        let done = assimilate(
            &mut est,
            clock,
            resets,
            readings,
            setpoints,
            &weather_at,
            period,
            self.max_catch_up_s,
            settle_before,
            &primary,
        );
        for reason in &done.reset_reasons {
            tracing::warn!(field = field.id, reason = %reason, "state estimate reset to its prior");
        }
        let (settled_time, settled_snapshot, settled_resets) = done.settled;
        let body = serde_json::to_string(&StoredEstimate {
            time: done.clock,
            snapshot: est.snapshot(),
            resets: done.resets,
            seen: Some(Seen::of(&read.readings, settled_time, done.clock)),
            settled: Some(Box::new(Checkpoint {
                time: settled_time,
                snapshot: settled_snapshot,
                resets: settled_resets,
            })),
        })
        .map_err(StoreError::from)?;
        Ok((Some(EstimateView::of(&est)), done.flags, Some(body)))
    }

    /// The field's current state estimate as its latest cycle left it (the
    /// stored record and the restored filter); None before the first.
    pub fn current_estimate(
        &self,
        field: &Field,
    ) -> Result<Option<(StoredEstimate, Estimator)>, EngineError> {
        let Some(stored) = self
            .store
            .estimate(field.id)?
            .and_then(|body| serde_json::from_str::<StoredEstimate>(&body).ok())
        else {
            return Ok(None);
        };
        let est = Estimator::restore(stored.snapshot.clone())
            .map_err(|e| EngineError::Plant(field.id, format!("stored estimate: {e}")))?;
        Ok(Some((stored, est)))
    }

    /// One control cycle: a simulated field's plant and weather service
    /// first, then load → decide → store (the setpoint, the state estimate
    /// and, for a scheduled cycle, the run of its boundary, in one
    /// transaction). Returns None when the store refused a scheduled cycle:
    /// its boundary has run already, or this replica's lease of the field
    /// ended; nothing of it is stored or published.
    pub fn control_cycle(
        &self,
        field: &Field,
        now: DateTime<Utc>,
        run: Option<CycleRun<'_>>,
    ) -> Result<Option<CycleDone>, EngineError> {
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
        // the one read of the cycle's inputs
        let scenario = self.scenario(field)?;
        let mut read = self
            .store
            .cycle_read(&self.cycle_query(field, now, scenario.is_some()))?;
        let mut inputs = self.load(field, now, &mut read, scenario);
        let (forecast, forecast_flag, used) = self.cycle_forecast(
            field,
            now,
            inputs.forecast.take(),
            read.forecast_source.as_deref(),
        )?;
        inputs.forecast = forecast;
        flags.extend(forecast_flag);
        // a scheduled surrogate cycle whose window is all measured plans on
        // no estimate brought up to now (only a valve schedule reads the
        // stored one): it leaves that to `update_estimate`, after its
        // setpoint, unless the stored estimate is more than a period behind
        let stored_view = match run {
            Some(_) => self.deferrable(field, now, &inputs, &read, scenario.is_some()),
            None => None,
        };
        let deferred = stored_view.is_some();
        let (estimate, estimate_flags, estimate_body) = if let Some(view) = stored_view {
            (Some(view), Vec::new(), None)
        } else {
            self.estimate(field, now, &read, scenario)?
        };
        flags.extend(estimate_flags);
        inputs.estimate = estimate;
        inputs.degraded = flags;
        // a two-layer field with its own surrogate plans on it; one that
        // does not match its metadata is refused (logged) and flagged
        let own = match field.spec.model {
            super::wire::ModelKind::TwoLayer => self.own_models.current(field.id),
            _ => None,
        };
        let mut own_id = None;
        let mut setpoint = match own {
            Some((id, Ok(file))) => {
                own_id = Some(id);
                let models = Models {
                    two_layer: (*file).clone(),
                    lstm: self.models.lstm.clone(),
                };
                decide(&inputs, &models, &self.cancel)
            }
            Some((_, Err(_))) => {
                inputs.degraded.push("surrogate-refused".into());
                decide(&inputs, &self.models, &self.cancel)
            }
            None => decide(&inputs, &self.models, &self.cancel),
        };
        setpoint.surrogate = own_id;
        setpoint.forecast = Some(used);
        setpoint.explanation = super::explain::explain(&setpoint, field.spec.irrigation_max);
        let stored = self.store.commit_cycle(&CycleOutputs {
            setpoint: &setpoint,
            estimate: estimate_body.as_deref(),
            run,
        })?;
        Ok(stored.then(|| CycleDone {
            setpoint,
            previous: inputs.recent.first().cloned(),
            theta: read.latest_primary.map(|m| m.theta),
            estimate_deferred: deferred,
        }))
    }

    /// The stored estimate's view when this cycle may defer bringing the
    /// estimate up to `now`: deferring is on, the cycle is scheduled, the
    /// field is a surrogate one whose window is all measured, it is not
    /// simulated (its plant stays with the cycles), and the stored
    /// estimate reached a time at most one period and a half before `now`
    /// (so an estimate lags by at most a cycle, however starved the
    /// deferred work is).
    fn deferrable(
        &self,
        field: &Field,
        now: DateTime<Utc>,
        inputs: &CycleInputs,
        read: &CycleRead,
        simulated: bool,
    ) -> Option<EstimateView> {
        let surrogate = matches!(
            field.spec.model,
            super::wire::ModelKind::TwoLayer | super::wire::ModelKind::Lstm
        );
        if !self.defer_estimates || simulated || !surrogate || !window_is_measured(inputs) {
            return None;
        }
        let stored: StoredEstimate = serde_json::from_str(read.estimate.as_deref()?).ok()?;
        let lag = (now - stored.time).as_seconds_f64();
        if !(0.0..=1.5 * field.spec.control_period_s).contains(&lag) {
            return None;
        }
        let est = Estimator::restore(stored.snapshot).ok()?;
        Some(EstimateView::of(&est))
    }

    /// Brings a field's state estimate up to `now` after a cycle at `now`
    /// that deferred it: the cycle's read again (readings at or before
    /// `now` only, so the result is what the cycle would have stored,
    /// counting any reading that came in late meanwhile), then
    /// [`Engine::estimate`], stored only if the stored estimate is still
    /// the one it started from and, on PostgreSQL, `replica` still holds
    /// the field. Returns whether it was stored (false: the stored
    /// estimate has reached `now` already, a later cycle or update came
    /// first, or the lease moved; that one's estimate stands).
    pub fn update_estimate(
        &self,
        field: &Field,
        now: DateTime<Utc>,
        replica: &str,
    ) -> Result<bool, EngineError> {
        let scenario = self.scenario(field)?;
        let read = self
            .store
            .cycle_read(&self.cycle_query(field, now, scenario.is_some()))?;
        let reached = read
            .estimate
            .as_deref()
            .and_then(|b| serde_json::from_str::<StoredEstimate>(b).ok())
            .map(|s| s.time);
        if reached.is_some_and(|t| t >= now) {
            // a later cycle brought it this far already
            return Ok(false);
        }
        let (_, _, body) = self.estimate(field, now, &read, scenario)?;
        let Some(body) = body else {
            return Ok(false);
        };
        Ok(self
            .store
            .replace_estimate(field.id, read.estimate.as_deref(), &body, replica)?)
    }
}

/// A committed cycle: its setpoint, and what the daemon's metrics need
/// from the cycle's one read (so that publishing it reads nothing more).
#[derive(Debug, Clone)]
pub struct CycleDone {
    pub setpoint: Setpoint,
    /// The setpoint this one replaces: the latest before the cycle.
    pub previous: Option<Setpoint>,
    /// The primary sensor's latest θ at or before the cycle.
    pub theta: Option<f64>,
    /// The cycle left its state estimate to [`Engine::update_estimate`].
    pub estimate_deferred: bool,
}
