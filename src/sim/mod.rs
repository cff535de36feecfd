//! The simulated plant: one module for the daemon's simulated fields and
//! the field simulator. A Richards column (MODEL.md §1–2) living in one of
//! the embedded weather scenarios on the clock, read by every sensor of its
//! field, driven by the setpoint in force.

use chrono::{DateTime, TimeDelta, Timelike, Utc};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::estimate::cell_of;
use crate::service::wire::{FieldSpec, Forecast, Measurement, Scenario, SimulationSpec};
use crate::soil::{ColumnState, Field as Plant, FieldSettings, Forcing, IntegrationError};
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

/// The reading of sensor `index` of a simulated plant at `depth` m, `theta`
/// being the plant's θ profile: θ of the cell holding that depth
/// ([`cell_of`]) with relative noise U(−m, m) of level `noise`, drawn from a
/// stream of its own fixed by (seed, index, the plant's step), so a resumed
/// plant reads the same and the daemon, the field simulator and the closed
/// loop read the same plant alike. (The plant's own sensor,
/// [`SensedPlant`]'s `own`, reads the plant's own measurement stream
/// instead.) Returns (measured θ in [0, 1], true θ).
fn reading_of(
    plant: &Plant,
    theta: &[f64],
    depth: f64,
    index: usize,
    noise: f64,
    seed: u64,
) -> (f64, f64) {
    let cell = cell_of(depth, plant.column().depth(), theta.len());
    let mut rng = ChaCha8Rng::seed_from_u64(
        seed ^ (0x9e37_79b9_7f4a_7c15_u64.wrapping_mul(index as u64 + 1))
            ^ (plant.steps() as u64).rotate_left(32),
    );
    let v = noise * (2.0 * rng.random::<f64>() - 1.0);
    ((theta[cell] * (1.0 + v)).clamp(0.0, 1.0), theta[cell])
}

/// A Richards plant and the sensors that read it: the one simulated plant
/// of the daemon's simulated fields, the field simulator (both through
/// [`SimulatedPlant`], which adds the clock and the scenario) and the
/// in-process closed loop (which drives it under its own weather series).
///
/// The first sensor in the plant's own sensor cell (the rooting depth's)
/// reads the plant's own measurement stream ([`Plant::measure`]); every
/// other sensor reads its cell with a stream of its own (`reading_of`),
/// its place in the list being its index.
pub struct SensedPlant {
    plant: Plant,
    depths: Vec<f64>,
    own: Option<usize>,
}

/// One step of a [`SensedPlant`]: every sensor's (measured, true) θ, in
/// the sensors' order.
#[derive(Debug, Clone, PartialEq)]
pub struct SensedStep {
    pub readings: Vec<(f64, f64)>,
}

impl SensedPlant {
    /// The plant of `settings` read by sensors at `depths` [m], each in
    /// [0, the column's depth].
    pub fn new(settings: FieldSettings, depths: Vec<f64>) -> Result<SensedPlant, String> {
        let plant = Plant::new(settings)?;
        let column = plant.column();
        if depths.is_empty() {
            return Err("at least one sensor is needed".into());
        }
        if let Some(d) = depths
            .iter()
            .find(|d| !(d.is_finite() && (0.0..=column.depth()).contains(*d)))
        {
            return Err(format!(
                "sensor depth {d} m is outside the column (0 … {} m)",
                column.depth()
            ));
        }
        let (depth, cells, own_cell) = (column.depth(), column.cells(), column.sensor_cell());
        let own = depths
            .iter()
            .position(|&d| cell_of(d, depth, cells) == own_cell);
        Ok(SensedPlant { plant, depths, own })
    }

    pub fn plant(&self) -> &Plant {
        &self.plant
    }

    /// The index of the sensor that reads the plant's own measurement.
    pub fn own(&self) -> Option<usize> {
        self.own
    }

    /// Every sensor's (measured, true) θ now, the own sensor reading
    /// `own_measured` (a draw the plant has just made).
    fn read(&self, own_measured: f64) -> Vec<(f64, f64)> {
        let s = self.plant.settings();
        let theta = self.plant.water_contents();
        self.depths
            .iter()
            .enumerate()
            .map(|(k, &depth)| {
                if Some(k) == self.own {
                    (own_measured.clamp(0.0, 1.0), self.plant.water_content())
                } else {
                    reading_of(&self.plant, &theta, depth, k, s.measurement_noise, s.seed)
                }
            })
            .collect()
    }

    /// The readings of the initial state (a draw from the own stream).
    pub fn read_now(&mut self) -> SensedStep {
        let own = self.plant.measure();
        SensedStep {
            readings: self.read(own),
        }
    }

    /// One sampling step of the plant under `forcing`, then every
    /// sensor's reading.
    pub fn step(&mut self, forcing: Forcing) -> Result<SensedStep, IntegrationError> {
        let report = self.plant.step(forcing)?;
        Ok(SensedStep {
            readings: self.read(report.measured_water_content),
        })
    }
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
    /// True θ at the rooting depth (the cell holding it).
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

/// A simulated field: its [`SensedPlant`] on the clock, in the weather of
/// its scenario, driven by the setpoint in force.
pub struct SimulatedPlant {
    sensed: SensedPlant,
    time: DateTime<Utc>,
    /// Midnight (UTC) of the field's first day: the scenario's hour 0.
    day_zero: DateTime<Utc>,
    spec: SimulationSpec,
    /// The sensors' ids, the primary (first) one's none.
    ids: Vec<Option<String>>,
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
        let sensors = field.effective_sensors();
        let ids = sensors
            .iter()
            .enumerate()
            .map(|(k, s)| (k > 0).then(|| s.id.clone()))
            .collect();
        let mut sensed = SensedPlant::new(settings, sensors.iter().map(|s| s.depth).collect())?;
        let mut time = start;
        let mut started = false;
        if let Some(state) = saved {
            sensed.plant.restore(
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
            sensed,
            time,
            day_zero: midnight(start),
            spec: sim,
            ids,
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
        self.sensed.plant()
    }

    pub fn state(&self) -> PlantState {
        let plant = self.sensed.plant();
        let b = plant.water_balance();
        PlantState {
            time: self.time,
            steps: plant.steps(),
            heads: plant.pressure_heads().to_vec(),
            amounts: plant.state().amounts,
            theta: plant.water_content(),
            theta_profile: plant.water_contents(),
            infiltration_m: b.infiltration,
            drainage_m: b.drainage,
            uptake_m: b.uptake,
            runoff_m: b.runoff,
        }
    }

    /// The step's readings as measurements at the plant's time.
    fn record(&self, step: SensedStep, out: &mut Vec<Measurement>) {
        for (id, (theta, truth)) in self.ids.iter().zip(step.readings) {
            out.push(Measurement {
                time: self.time,
                theta,
                sensor: id.clone(),
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
            let first = self.sensed.read_now();
            self.record(first, &mut out.readings);
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
            let step = match self.sensed.step(forcing) {
                Ok(step) => step,
                Err(e) => {
                    out.failure = Some(e);
                    break;
                }
            };
            self.time += interval;
            self.record(step, &mut out.readings);
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn settings() -> FieldSettings {
        FieldSettings {
            initial_head: -0.3,
            measurement_noise: 0.05,
            seed: 4,
            ..FieldSettings::default()
        }
    }

    /// Whatever the sensors' order, the one in the rooting depth's cell
    /// reads the plant's own stream and the others their own cells: a
    /// field whose first sensor sits at 0.3 m gets θ of 0.3 m from it, not
    /// the plant's reading at 0.125 m.
    #[test]
    fn each_sensor_reads_its_own_cell_whatever_the_order() {
        let mut drained = settings();
        // a profile that differs with depth: drained for a day
        drained.initial_head = -1.0;
        let depths = vec![0.3, 0.125, 0.45];
        let mut sensed = SensedPlant::new(drained, depths.clone()).unwrap();
        assert_eq!(sensed.own(), Some(1));
        let mut twin = Plant::new(drained).unwrap();
        let forcing = Forcing {
            irrigation: 3e-6,
            ..Forcing::default()
        };
        for _ in 0..3 {
            let step = sensed.step(forcing).unwrap();
            let report = twin.step(forcing).unwrap();
            let theta = twin.water_contents();
            let dz = twin.column().cell_thickness();
            for (k, &d) in depths.iter().enumerate() {
                let (measured, truth) = step.readings[k];
                assert_eq!(truth, theta[(d / dz) as usize], "sensor {k} at {d} m");
                assert!((measured / truth - 1.0).abs() <= 0.05);
            }
            assert_eq!(step.readings[1].0, report.measured_water_content);
            // the cells differ, so a sensor reading another's cell would show
            assert!((theta[(0.3 / dz) as usize] - theta[(0.125 / dz) as usize]).abs() > 1e-3);
        }
        // no sensor in the rooting cell: every sensor reads by reading_of
        let only_deep = SensedPlant::new(settings(), vec![0.4]).unwrap();
        assert_eq!(only_deep.own(), None);
        for bad in [vec![], vec![0.6], vec![f64::NAN], vec![-0.1]] {
            assert!(
                SensedPlant::new(settings(), bad.clone()).is_err(),
                "{bad:?}"
            );
        }
    }

    /// A daemon's simulated field whose primary sensor is not at the
    /// rooting depth: its measurements (no sensor id) carry θ of their own
    /// depth, and the named sensor at the rooting depth the plant's reading.
    #[test]
    fn a_simulated_fields_primary_sensor_reads_its_own_depth() {
        use crate::service::wire::{FieldSpec, SensorSpec};
        let field = FieldSpec {
            sensors: vec![SensorSpec::default_at(0.35), SensorSpec::default_at(0.125)]
                .into_iter()
                .enumerate()
                .map(|(k, s)| SensorSpec {
                    id: format!("s{k}"),
                    ..s
                })
                .collect(),
            ..FieldSpec::demo()
        };
        let sim = SimulationSpec {
            initial_head: -1.0,
            ..SimulationSpec::default()
        };
        let start = DateTime::parse_from_rfc3339("2026-06-01T00:00:00Z")
            .unwrap()
            .with_timezone(&Utc);
        let mut plant = SimulatedPlant::new(&field, sim, start, None).unwrap();
        let advance = plant
            .advance(start + TimeDelta::hours(6), 1e9, |t| {
                Ok::<_, ()>((2e-6, t + TimeDelta::hours(6)))
            })
            .unwrap();
        let n = advance.readings.len();
        assert!(
            n >= 4 && n.is_multiple_of(2),
            "two sensors at each time, {n}"
        );
        let theta = plant.plant().water_contents();
        let dz = plant.plant().column().cell_thickness();
        let last = &advance.readings[n - 2..];
        assert_eq!(last[0].sensor, None);
        assert_eq!(last[0].true_theta, Some(theta[(0.35 / dz) as usize]));
        assert_eq!(last[1].sensor.as_deref(), Some("s1"));
        assert_eq!(last[1].true_theta, Some(plant.plant().water_content()));
        assert!((theta[(0.35 / dz) as usize] - plant.plant().water_content()).abs() > 1e-3);
    }
}
