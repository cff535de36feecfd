//! The simulated plant: one module for the daemon's simulated fields and
//! the field simulator. A Richards column (MODEL.md §1–2) living in one of
//! the embedded weather scenarios on the clock, read by every sensor of its
//! field, driven by the setpoint in force.

use chrono::{DateTime, TimeDelta, Timelike, Utc};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::service::wire::{
    FieldSpec, Forecast, Measurement, Scenario, SensorSpec, SimulationSpec,
};
use crate::soil::{ColumnState, Field as Plant, FieldSettings, IntegrationError};
use crate::weather::{DRY_SCENARIO, RAIN_SCENARIO, WeatherSeries, WeatherStep};

/// Scenario step [s].
pub const SCENARIO_STEP: f64 = 7200.0;

static DRY: std::sync::LazyLock<WeatherSeries> = std::sync::LazyLock::new(|| {
    WeatherSeries::parse(DRY_SCENARIO, "embedded weather-dry.csv").expect("embedded scenario")
});
static RAIN: std::sync::LazyLock<WeatherSeries> = std::sync::LazyLock::new(|| {
    WeatherSeries::parse(RAIN_SCENARIO, "embedded weather-rain.csv").expect("embedded scenario")
});

fn seconds(d: TimeDelta) -> f64 {
    d.num_milliseconds() as f64 / 1000.0
}

/// The embedded scenario's series.
pub fn scenario_series(s: Scenario) -> &'static WeatherSeries {
    match s {
        Scenario::Dry => &DRY,
        Scenario::Rain => &RAIN,
    }
}

/// The scenario's weather (amounts per 2-h step) at clock time `t`, the
/// scenario's hour 0 being `day_zero` and the scenario repeating.
pub fn scenario_weather(s: Scenario, day_zero: DateTime<Utc>, t: DateTime<Utc>) -> WeatherStep {
    let series = scenario_series(s);
    let k = (seconds(t - day_zero) / SCENARIO_STEP).floor().max(0.0) as usize;
    series.steps()[k % series.len()]
}

/// Midnight (UTC) of the day of `t`.
pub fn midnight(t: DateTime<Utc>) -> DateTime<Utc> {
    t.with_hour(0)
        .and_then(|t| t.with_minute(0))
        .and_then(|t| t.with_second(0))
        .and_then(|t| t.with_nanosecond(0))
        .unwrap_or(t)
}

/// A scenario forecast from `now`: `steps` steps of `period` seconds, each
/// ET0 and P the truth × (1 + U(−error, error)) (MODEL.md §2).
pub fn scenario_forecast(
    s: Scenario,
    day_zero: DateTime<Utc>,
    now: DateTime<Utc>,
    period: f64,
    steps: usize,
    error: f64,
    rng: &mut impl rand::Rng,
) -> Forecast {
    let mut et0 = Vec::with_capacity(steps);
    let mut precip = Vec::with_capacity(steps);
    for k in 0..steps {
        let t = now + TimeDelta::milliseconds((k as f64 * period * 1000.0) as i64);
        let w = scenario_weather(s, day_zero, t);
        let truth = WeatherSeries::new(vec![WeatherStep {
            et0_mm: w.et0_mm * period / SCENARIO_STEP,
            precip_mm: w.precip_mm * period / SCENARIO_STEP,
            ..w
        }]);
        let f = truth.forecast(0, 1, error, rng)[0];
        et0.push(f.et0_mm);
        precip.push(f.precip_mm);
    }
    Forecast {
        issued_at: now,
        start: now,
        step_s: period,
        et0_mm: et0,
        precip_mm: precip,
    }
}

/// The readings of a plant's sensors other than the primary one (which is
/// the plant's own reading): (sensor id, measured θ, true θ), each by
/// [`sensor_reading`] with the sensor's place in `sensors` as its index.
pub fn other_readings(
    plant: &Plant,
    sensors: &[SensorSpec],
    noise: f64,
    seed: u64,
) -> Vec<(String, f64, f64)> {
    let theta = plant.water_contents();
    sensors
        .iter()
        .enumerate()
        .skip(1)
        .map(|(i, s)| {
            let (measured, truth) = reading_of(plant, &theta, s.depth, i, noise, seed);
            (s.id.clone(), measured, truth)
        })
        .collect()
}

/// The reading of sensor `index` of a simulated plant at `depth` m (index 0
/// is the plant's own sensor, which the plant reads itself): θ of the cell
/// holding that depth with relative noise U(−m, m) of level `noise`, drawn
/// from a stream of its own fixed by (seed, index, the plant's step), so a
/// resumed plant reads the same and the daemon, the field simulator and the
/// closed loop read the same plant alike. Returns (measured θ in [0, 1],
/// true θ).
pub fn sensor_reading(
    plant: &Plant,
    depth: f64,
    index: usize,
    noise: f64,
    seed: u64,
) -> (f64, f64) {
    reading_of(plant, &plant.water_contents(), depth, index, noise, seed)
}

fn reading_of(
    plant: &Plant,
    theta: &[f64],
    depth: f64,
    index: usize,
    noise: f64,
    seed: u64,
) -> (f64, f64) {
    let dz = plant.column().cell_thickness();
    let cell = ((depth / dz) as usize).min(theta.len() - 1);
    let mut rng = ChaCha8Rng::seed_from_u64(
        seed ^ (0x9e37_79b9_7f4a_7c15_u64.wrapping_mul(index as u64 + 1))
            ^ (plant.steps() as u64).rotate_left(32),
    );
    let v = noise * (2.0 * rng.random::<f64>() - 1.0);
    ((theta[cell] * (1.0 + v)).clamp(0.0, 1.0), theta[cell])
}

/// The stored state of a simulated plant, and what the API shows of it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PlantState {
    /// Clock time of the state.
    pub time: DateTime<Utc>,
    /// Completed measurement intervals.
    pub steps: usize,
    pub heads: Vec<f64>,
    pub amounts: [f64; 4],
    /// True θ at the primary sensor.
    pub theta: f64,
    /// True θ of every cell, top first (cells of equal thickness).
    #[serde(default)]
    pub theta_profile: Vec<f64>,
    /// Water balance [m]: infiltration, drainage, uptake, runoff.
    pub infiltration_m: f64,
    pub drainage_m: f64,
    pub uptake_m: f64,
    pub runoff_m: f64,
}

/// What one advance produced: the readings of every sensor (the primary
/// one with no sensor id, each with its true θ), and the failure that
/// stopped it early, if any (the readings before it stand).
#[derive(Debug, Default)]
pub struct Advance {
    pub readings: Vec<Measurement>,
    pub failure: Option<IntegrationError>,
    /// Clock time skipped to bound the replay, if any: (from, to).
    pub skipped: Option<(DateTime<Utc>, DateTime<Utc>)>,
}

/// A simulated field: the Richards plant, when it is, and its sensors.
pub struct SimulatedPlant {
    plant: Plant,
    time: DateTime<Utc>,
    /// Midnight (UTC) of the field's first day: the scenario's hour 0.
    day_zero: DateTime<Utc>,
    spec: SimulationSpec,
    sensors: Vec<SensorSpec>,
    /// Whether the reading of the initial state has been taken.
    started: bool,
}

impl SimulatedPlant {
    /// The plant of `field` (its soil, crop, sensors and `sim` section),
    /// starting at `start` from its initial state, or resumed from `saved`.
    pub fn new(
        field: &FieldSpec,
        sim: SimulationSpec,
        start: DateTime<Utc>,
        saved: Option<&PlantState>,
    ) -> Result<SimulatedPlant, String> {
        let settings = FieldSettings {
            soil: sim.soil.as_ref().unwrap_or(&field.soil).parameters()?,
            crop: field.crop(),
            initial_head: sim.initial_head,
            sampling_time: sim.measurement_interval_s,
            process_noise: sim.process_noise,
            measurement_noise: sim.measurement_noise,
            seed: sim.seed,
            ..FieldSettings::default()
        };
        let mut plant = Plant::new(settings)?;
        let mut time = start;
        let mut started = false;
        if let Some(state) = saved {
            plant.restore(
                ColumnState {
                    heads: state.heads.clone(),
                    amounts: state.amounts,
                },
                state.steps as f64 * sim.measurement_interval_s,
                state.steps,
            )?;
            time = state.time;
            started = true;
        }
        Ok(SimulatedPlant {
            plant,
            time,
            day_zero: midnight(start),
            spec: sim,
            sensors: field.effective_sensors(),
            started,
        })
    }

    /// A plant resumed with its day zero and start flag as saved elsewhere
    /// (the field simulator keeps them in its own file).
    pub fn resume_at(mut self, day_zero: DateTime<Utc>, started: bool) -> SimulatedPlant {
        self.day_zero = day_zero;
        self.started = started;
        self
    }

    pub fn time(&self) -> DateTime<Utc> {
        self.time
    }

    pub fn day_zero(&self) -> DateTime<Utc> {
        self.day_zero
    }

    pub fn started(&self) -> bool {
        self.started
    }

    pub fn spec(&self) -> &SimulationSpec {
        &self.spec
    }

    pub fn plant(&self) -> &Plant {
        &self.plant
    }

    pub fn state(&self) -> PlantState {
        let b = self.plant.water_balance();
        PlantState {
            time: self.time,
            steps: self.plant.steps(),
            heads: self.plant.pressure_heads().to_vec(),
            amounts: self.plant.state().amounts,
            theta: self.plant.water_content(),
            theta_profile: self.plant.water_contents(),
            infiltration_m: b.infiltration,
            drainage_m: b.drainage,
            uptake_m: b.uptake,
            runoff_m: b.runoff,
        }
    }

    /// Every sensor's reading now.
    fn read(&mut self, primary: f64, truth: f64, out: &mut Vec<Measurement>) {
        out.push(Measurement {
            time: self.time,
            theta: primary.clamp(0.0, 1.0),
            sensor: None,
            raw: None,
            true_theta: Some(truth),
        });
        let (noise, seed) = (self.spec.measurement_noise, self.spec.seed);
        for (id, theta, truth) in other_readings(&self.plant, &self.sensors, noise, seed) {
            out.push(Measurement {
                time: self.time,
                theta,
                sensor: Some(id),
                raw: None,
                true_theta: Some(truth),
            });
        }
    }

    /// Advances the plant to clock time `now`, one measurement interval at
    /// a time: the sensors read the initial state at the start, then after
    /// each interval. `rate_at(t)` is the irrigation rate [m/s] in force
    /// from `t` and until when; the scenario's weather comes as rates held
    /// over the interval. A plant more than `max_catch_up_s` behind skips
    /// ahead first (its state kept), so the replay is bounded.
    pub fn advance<E>(
        &mut self,
        now: DateTime<Utc>,
        max_catch_up_s: f64,
        mut rate_at: impl FnMut(DateTime<Utc>) -> Result<(f64, DateTime<Utc>), E>,
    ) -> Result<Advance, E> {
        let step = self.spec.measurement_interval_s;
        let interval = TimeDelta::milliseconds((step * 1000.0) as i64);
        let mut out = Advance::default();
        if !self.started && self.time <= now {
            self.started = true;
            let (m, t) = (self.plant.measure(), self.plant.water_content());
            self.read(m, t, &mut out.readings);
        }
        let behind = seconds(now - self.time) / step;
        let most = (max_catch_up_s / step).floor();
        if behind > most + 1.0 {
            let from = self.time;
            self.time += TimeDelta::milliseconds(((behind - most).floor() * step * 1e3) as i64);
            out.skipped = Some((from, self.time));
        }
        let (mut rate, mut rate_until) = (0.0, self.time);
        while self.time + interval <= now {
            if self.time >= rate_until {
                (rate, rate_until) = rate_at(self.time)?;
                if rate_until <= self.time {
                    rate_until = self.time + interval;
                }
            }
            let forcing = scenario_weather(self.spec.scenario, self.day_zero, self.time)
                .forcing(rate, SCENARIO_STEP);
            let report = match self.plant.step(forcing) {
                Ok(report) => report,
                Err(e) => {
                    out.failure = Some(e);
                    break;
                }
            };
            self.time += interval;
            self.read(
                report.measured_water_content,
                report.water_content,
                &mut out.readings,
            );
        }
        Ok(out)
    }
}
