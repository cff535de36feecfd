//! The closed loop of MODEL.md §4: a simulated field as the plant (with its
//! process and measurement noise), a controller fed the noisy measurement and
//! a weather forecast with error, scored by irrigation, zone violation and
//! solve time.

use std::time::Duration;

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use crate::sim::{SensedPlant, SensedStep};
use crate::soil::FieldSettings;
use crate::weather::{WeatherSeries, WeatherStep, rate_to_mm};

use super::controller::Controller;
use super::estimated::EstimatedRichards;
use super::mpc::SolveStatus;

/// The setting of one closed-loop run.
#[derive(Debug, Clone)]
pub struct ClosedLoopSettings {
    /// The plant (soil, noise levels, seed).
    pub field: FieldSettings,
    /// Control steps (MODEL.md: 60, five days).
    pub steps: usize,
    /// Forecast error level e: each forecast step is truth × (1 + U(−e, e)).
    pub forecast_error: f64,
    /// Seed of the forecast-error draws.
    pub forecast_seed: u64,
    /// The zone the violation is scored against (MODEL.md: [0.18, 0.23]).
    pub scoring_zone: (f64, f64),
    /// The ET0 [mm per step] the controller is told in place of the truth,
    /// observed and forecast, step by step from the start and repeated
    /// (a controller blind to the weather's ET0); None tells it the truth.
    pub told_et0: Option<Vec<f64>>,
}

impl Default for ClosedLoopSettings {
    fn default() -> Self {
        ClosedLoopSettings {
            field: FieldSettings::default(),
            steps: 60,
            forecast_error: 0.0,
            forecast_seed: 0,
            scoring_zone: (0.18, 0.23),
            told_et0: None,
        }
    }
}

/// One control step of a run.
#[derive(Debug, Clone, PartialEq)]
pub struct StepRecord {
    pub step: usize,
    /// Irrigation applied over the step [m/s].
    pub irrigation: f64,
    /// Rain over the step [mm] and ET0 [mm] (the truth).
    pub precip_mm: f64,
    pub et0_mm: f64,
    /// θ at the end of the step: noise-free and as measured.
    pub true_theta: f64,
    pub measured_theta: f64,
    /// The zone of the first prediction step (low_1, up_1).
    pub zone: (f64, f64),
    pub bias: f64,
    pub solve_time: Duration,
    pub iterations: usize,
    pub status: SolveStatus,
}

/// A whole run.
#[derive(Debug, Clone, PartialEq)]
pub struct ClosedLoopRun {
    /// θ at the start (noise-free).
    pub initial_theta: f64,
    pub records: Vec<StepRecord>,
    pub sampling_time: f64,
    pub scoring_zone: (f64, f64),
    /// The plant's water balance at the end.
    pub water_balance: crate::soil::WaterBalance,
}

/// Mean, median and 95th percentile of the solve times [ms].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TimeStatistics {
    pub mean_ms: f64,
    pub median_ms: f64,
    pub p95_ms: f64,
}

impl ClosedLoopRun {
    /// I_T = Σ u·Δ·1000 [mm].
    pub fn total_irrigation_mm(&self) -> f64 {
        self.records
            .iter()
            .map(|r| rate_to_mm(r.irrigation, self.sampling_time))
            .sum()
    }

    /// Mean over the steps of the noise-free θ's distance outside the scoring
    /// zone [m³/m³].
    pub fn zone_violation(&self) -> f64 {
        let (low, up) = self.scoring_zone;
        let total: f64 = self
            .records
            .iter()
            .map(|r| (low - r.true_theta).max(0.0) + (r.true_theta - up).max(0.0))
            .sum();
        total / self.records.len().max(1) as f64
    }

    /// Dry-side violation (MODEL.md §4, the headline): mean over the steps
    /// of max(0, low − θ_true) [m³/m³].
    pub fn dry_violation(&self) -> f64 {
        let low = self.scoring_zone.0;
        let total: f64 = self
            .records
            .iter()
            .map(|r| (low - r.true_theta).max(0.0))
            .sum();
        total / self.records.len().max(1) as f64
    }

    /// Wet-side violation after entry (MODEL.md §4): mean over all steps of
    /// max(0, θ_true − up), counted from the first step with θ_true ≤ up.
    pub fn wet_violation_after_entry(&self) -> f64 {
        let up = self.scoring_zone.1;
        let entry = self
            .records
            .iter()
            .position(|r| r.true_theta <= up)
            .unwrap_or(self.records.len());
        let total: f64 = self.records[entry..]
            .iter()
            .map(|r| (r.true_theta - up).max(0.0))
            .sum();
        total / self.records.len().max(1) as f64
    }

    pub fn solve_times(&self) -> TimeStatistics {
        time_statistics(
            self.records
                .iter()
                .map(|r| r.solve_time.as_secs_f64() * 1e3)
                .collect(),
        )
    }

    /// Control steps whose solve fell back to a safe plan.
    pub fn fallbacks(&self) -> usize {
        self.records
            .iter()
            .filter(|r| matches!(r.status, SolveStatus::Fallback(_)))
            .count()
    }
}

/// Mean, median and 95th percentile of durations in ms.
pub fn time_statistics(mut ms: Vec<f64>) -> TimeStatistics {
    if ms.is_empty() {
        return TimeStatistics {
            mean_ms: 0.0,
            median_ms: 0.0,
            p95_ms: 0.0,
        };
    }
    ms.sort_by(f64::total_cmp);
    let quantile = |q: f64| {
        // linear interpolation between order statistics
        let x = q * (ms.len() - 1) as f64;
        let (i, f) = (x.floor() as usize, x.fract());
        ms[i] + f * (ms[(i + 1).min(ms.len() - 1)] - ms[i])
    };
    TimeStatistics {
        mean_ms: ms.iter().sum::<f64>() / ms.len() as f64,
        median_ms: quantile(0.5),
        p95_ms: quantile(0.95),
    }
}

/// The closed loop could not run.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ClosedLoopError {
    #[error("field: {0}")]
    Field(String),
    #[error("the weather series is empty")]
    NoWeather,
    #[error("the plant failed at step {step}: {message}")]
    Plant { step: usize, message: String },
}

/// How the controller is built once the first measurement exists.
pub type ControllerFactory<'a> = dyn FnMut(f64) -> Controller + 'a;

/// Runs `settings.steps` control steps: at each, the controller gets the
/// measurement and a forecast of the horizon, its setpoint is applied to the
/// field over one sampling step under the true weather, and the window is
/// updated with the applied irrigation, the observed rain and the new
/// measurement. `make` builds the controller from the first measurement.
pub fn run_closed_loop(
    settings: &ClosedLoopSettings,
    weather: &WeatherSeries,
    make: &mut ControllerFactory<'_>,
) -> Result<ClosedLoopRun, ClosedLoopError> {
    if weather.is_empty() {
        return Err(ClosedLoopError::NoWeather);
    }
    // one sensor, the plant's own at the rooting depth
    let depth = settings.field.crop.rooting_depth;
    let mut plant =
        SensedPlant::new(settings.field, vec![depth]).map_err(ClosedLoopError::Field)?;
    let sampling_time = settings.field.sampling_time;
    let mut forecast_rng = ChaCha8Rng::seed_from_u64(settings.forecast_seed);
    let initial_theta = plant.plant().water_content();
    let first = plant.read_now().readings[0].0;
    let mut controller = make(first);
    let horizon = controller.settings().horizon;
    let last = weather.len() - 1;
    let mut records = Vec::with_capacity(settings.steps);
    // what the controller is told of a step's weather
    let told = |k: usize, w: WeatherStep| match settings.told_et0.as_deref() {
        Some(e) if !e.is_empty() => WeatherStep {
            et0_mm: e[k % e.len()],
            ..w
        },
        _ => w,
    };
    for step in 0..settings.steps {
        let mut forecast =
            weather.forecast(step, horizon, settings.forecast_error, &mut forecast_rng);
        for (k, w) in forecast.iter_mut().enumerate() {
            *w = told(step + k, *w);
        }
        let decision = controller.decide(&forecast, Some(plant.plant()));
        let truth = weather.steps()[step.min(last)];
        let sensed = plant
            .step(truth.forcing(decision.setpoint, sampling_time))
            .map_err(|e| ClosedLoopError::Plant {
                step,
                message: e.to_string(),
            })?;
        let (measured_theta, true_theta) = sensed.readings[0];
        controller.observe(decision.setpoint, &told(step, truth), measured_theta);
        let solution = decision.solution;
        records.push(StepRecord {
            step,
            irrigation: decision.setpoint,
            precip_mm: truth.precip_mm,
            et0_mm: truth.et0_mm,
            true_theta,
            measured_theta,
            zone: solution
                .zone
                .first()
                .copied()
                .unwrap_or((f64::NAN, f64::NAN)),
            bias: controller.bias(),
            solve_time: solution.solve_time,
            iterations: solution.iterations,
            status: solution.status,
        });
    }
    Ok(ClosedLoopRun {
        initial_theta,
        records,
        sampling_time,
        scoring_zone: settings.scoring_zone,
        water_balance: plant.plant().water_balance(),
    })
}

/// A controller of the observed closed loop ([`run_observed_loop`]).
#[derive(Debug, Clone)]
pub enum LoopController {
    /// The **oracle**: the Richards-model ZMPC given the plant's true soil and
    /// true state at every step. A yardstick for experiments, never a
    /// controller a deployment can run; the only one the loop shows the plant.
    Oracle(Controller),
    /// A surrogate controller: sees the reading of the first sensor, the
    /// applied irrigation and the observed rain.
    Surrogate(Controller),
    /// The Richards-model ZMPC on the estimated state and soil.
    Estimated(Box<EstimatedRichards>),
}

impl LoopController {
    fn horizon(&self) -> usize {
        match self {
            LoopController::Oracle(c) | LoopController::Surrogate(c) => c.settings().horizon,
            LoopController::Estimated(e) => e.settings().horizon,
        }
    }
}

/// What the estimator knew after one step of an observed run.
#[derive(Debug, Clone, PartialEq)]
pub struct EstimateRecord {
    pub step: usize,
    /// Estimated and true θ in the cell of the rooting depth (the controlled output).
    pub sensor_theta: f64,
    pub true_sensor_theta: f64,
    /// RMS over the cells of estimated − true θ.
    pub profile_rmse: f64,
    /// Wall time of the predict + update [ms].
    pub estimator_ms: f64,
    /// The estimator diverged at this step and was reset to its prior.
    pub reset: bool,
}

/// A run of [`run_observed_loop`]: the closed-loop run, and for the
/// estimated controller what it estimated.
#[derive(Debug, Clone, PartialEq)]
pub struct ObservedRun {
    pub run: ClosedLoopRun,
    pub estimates: Vec<EstimateRecord>,
    /// The final parameter estimates (estimated controller only).
    pub parameters: Vec<crate::estimate::ParameterEstimate>,
    pub resets: usize,
    pub replaced_members: u64,
    /// How often the "unknown" prior's selection ran again.
    pub reselections: u64,
    /// The texture the "unknown" prior's selection kept, if it ran.
    pub selected_texture: Option<crate::soil::Texture>,
}

/// Steps after which the estimation errors are scored (the first day).
pub const ESTIMATE_SCORED_FROM: usize = 12;

impl ObservedRun {
    fn rms(&self, f: impl Fn(&EstimateRecord) -> f64) -> Option<f64> {
        let scored: Vec<f64> = self
            .estimates
            .iter()
            .filter(|e| e.step >= ESTIMATE_SCORED_FROM)
            .map(f)
            .collect();
        (!scored.is_empty())
            .then(|| (scored.iter().map(|v| v * v).sum::<f64>() / scored.len() as f64).sqrt())
    }

    /// RMS of the estimated − true θ at the rooting depth after the first day.
    pub fn sensor_rmse(&self) -> Option<f64> {
        self.rms(|e| e.sensor_theta - e.true_sensor_theta)
    }

    /// RMS over time (after the first day) of the profile RMS error.
    pub fn profile_rmse(&self) -> Option<f64> {
        self.rms(|e| e.profile_rmse)
    }

    pub fn estimator_times(&self) -> TimeStatistics {
        time_statistics(self.estimates.iter().map(|e| e.estimator_ms).collect())
    }
}

/// Builds the controller from the first readings (one per sensor depth).
pub type LoopFactory<'a> = dyn FnMut(&[f64]) -> LoopController + 'a;

/// The closed loop with sensors at `sensor_depths` [m] and a controller
/// that sees only what a deployment sees, except the oracle. The reading of
/// the sensor in the rooting-depth cell is the field's own measurement (its
/// noise stream, as in [`run_closed_loop`]); other depths read θ of their
/// cell with the same relative noise from their own stream. At every step
/// the controller gets a forecast of the horizon, its setpoint is applied
/// over one sampling step under the true weather, and it observes the
/// applied irrigation, the observed weather of that step and the readings.
pub fn run_observed_loop(
    settings: &ClosedLoopSettings,
    sensor_depths: &[f64],
    weather: &WeatherSeries,
    make: &mut LoopFactory<'_>,
) -> Result<ObservedRun, ClosedLoopError> {
    if weather.is_empty() {
        return Err(ClosedLoopError::NoWeather);
    }
    let mut plant =
        SensedPlant::new(settings.field, sensor_depths.to_vec()).map_err(ClosedLoopError::Field)?;
    let column = *plant.plant().column();
    let own = plant.own();
    let measured = |step: &SensedStep| -> Vec<f64> { step.readings.iter().map(|r| r.0).collect() };
    let sampling_time = settings.field.sampling_time;
    let mut forecast_rng = ChaCha8Rng::seed_from_u64(settings.forecast_seed);
    let initial_theta = plant.plant().water_content();
    let first = measured(&plant.read_now());
    let mut controller = make(&first);
    let horizon = controller.horizon();
    let last = weather.len() - 1;
    let mut records = Vec::with_capacity(settings.steps);
    let mut estimates = Vec::new();
    for step in 0..settings.steps {
        let forecast = weather.forecast(step, horizon, settings.forecast_error, &mut forecast_rng);
        let decision = match &mut controller {
            LoopController::Oracle(c) => c.decide(&forecast, Some(plant.plant())),
            LoopController::Surrogate(c) => c.decide(&forecast, None),
            LoopController::Estimated(e) => e.decide(&forecast),
        };
        let truth = weather.steps()[step.min(last)];
        let forcing = truth.forcing(decision.setpoint, sampling_time);
        let sensed = plant.step(forcing).map_err(|e| ClosedLoopError::Plant {
            step,
            message: e.to_string(),
        })?;
        let readings = measured(&sensed);
        let field = plant.plant();
        let mut bias = 0.0;
        match &mut controller {
            LoopController::Oracle(c) | LoopController::Surrogate(c) => {
                let primary = own.map_or(readings[0], |k| readings[k]);
                c.observe(decision.setpoint, &truth, primary);
                bias = c.bias();
            }
            LoopController::Estimated(e) => {
                let indexed: Vec<(usize, f64)> = readings.iter().copied().enumerate().collect();
                let reset = matches!(
                    e.observe(forcing, &indexed),
                    Err(crate::estimate::EstimateError::Diverged(_))
                );
                let profile = e.estimator().profile();
                let true_theta = field.water_contents();
                let sensor = column.sensor_cell();
                let profile_rmse = (profile
                    .iter()
                    .zip(&true_theta)
                    .map(|(p, t)| (p.theta_mean - t).powi(2))
                    .sum::<f64>()
                    / true_theta.len() as f64)
                    .sqrt();
                estimates.push(EstimateRecord {
                    step,
                    sensor_theta: profile[sensor].theta_mean,
                    true_sensor_theta: true_theta[sensor],
                    profile_rmse,
                    estimator_ms: e.last_estimate_time().as_secs_f64() * 1e3,
                    reset,
                });
            }
        }
        let solution = decision.solution;
        records.push(StepRecord {
            step,
            irrigation: decision.setpoint,
            precip_mm: truth.precip_mm,
            et0_mm: truth.et0_mm,
            true_theta: field.water_content(),
            measured_theta: own.map_or(readings[0], |k| readings[k]),
            zone: solution
                .zone
                .first()
                .copied()
                .unwrap_or((f64::NAN, f64::NAN)),
            bias,
            solve_time: solution.solve_time,
            iterations: solution.iterations,
            status: solution.status,
        });
    }
    let (parameters, resets, replaced_members, reselections, selected_texture) = match &controller {
        LoopController::Estimated(e) => (
            e.estimator().parameters(),
            e.resets(),
            e.estimator().statistics().replaced_members,
            e.estimator().statistics().reselections,
            e.estimator().selected_texture(),
        ),
        _ => (Vec::new(), 0, 0, 0, None),
    };
    Ok(ObservedRun {
        run: ClosedLoopRun {
            initial_theta,
            records,
            sampling_time,
            scoring_zone: settings.scoring_zone,
            water_balance: plant.plant().water_balance(),
        },
        estimates,
        parameters,
        resets,
        replaced_members,
        reselections,
        selected_texture,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::control::MpcSettings;
    use crate::weather::DRY_SCENARIO;

    /// The closed loop reads a plant's sensors as a simulated field does
    /// (`sim::SensedPlant`, which the daemon and the field simulator use):
    /// the same plant at the same step reads the same, each other sensor
    /// within the noise level of its cell's truth; the plant's own sensor
    /// reads as the plant does.
    #[test]
    fn the_closed_loop_reads_other_sensors_as_a_simulated_field_does() {
        let (noise, seed) = (0.05, 11);
        let field = FieldSettings {
            measurement_noise: noise,
            seed,
            initial_head: -0.3,
            ..FieldSettings::default()
        };
        let settings = ClosedLoopSettings {
            field,
            steps: 1,
            ..ClosedLoopSettings::default()
        };
        let weather = WeatherSeries::parse(DRY_SCENARIO, "weather-dry.csv").unwrap();
        // the plant's own sensor (0.125 m) second, two others around it
        let depths = [0.3, 0.125, 0.45];
        let mut first = Vec::new();
        run_observed_loop(&settings, &depths, &weather, &mut |r: &[f64]| {
            first = r.to_vec();
            LoopController::Oracle(Controller::oracle(MpcSettings::default(), 7200.0))
        })
        .unwrap();
        let simulated = SensedPlant::new(field, depths.to_vec())
            .unwrap()
            .read_now()
            .readings;
        let mut plant = crate::soil::Field::new(field).unwrap();
        let dz = plant.column().cell_thickness();
        for k in [0, 2] {
            let (measured, truth) = simulated[k];
            assert_eq!(first[k], measured, "sensor {k}");
            assert_eq!(truth, plant.water_contents()[(depths[k] / dz) as usize]);
            assert!(measured != truth && (measured / truth - 1.0).abs() <= noise);
        }
        assert_eq!(first[1], plant.measure());
    }
}
