//! The closed loop of MODEL.md §4: a simulated field as the plant (with its
//! process and measurement noise), a controller fed the noisy measurement and
//! a weather forecast with error, scored by irrigation, zone violation and
//! solve time.

use std::time::Duration;

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use crate::soil::{Field, FieldSettings};
use crate::weather::{WeatherSeries, rate_to_mm};

use super::controller::Controller;
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
}

impl Default for ClosedLoopSettings {
    fn default() -> Self {
        ClosedLoopSettings {
            field: FieldSettings::default(),
            steps: 60,
            forecast_error: 0.0,
            forecast_seed: 0,
            scoring_zone: (0.18, 0.23),
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

    pub fn solve_times(&self) -> TimeStatistics {
        let mut ms: Vec<f64> = self
            .records
            .iter()
            .map(|r| r.solve_time.as_secs_f64() * 1e3)
            .collect();
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

    /// Control steps whose solve fell back to a safe plan.
    pub fn fallbacks(&self) -> usize {
        self.records
            .iter()
            .filter(|r| matches!(r.status, SolveStatus::Fallback(_)))
            .count()
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
    let mut field = Field::new(settings.field).map_err(ClosedLoopError::Field)?;
    let sampling_time = settings.field.sampling_time;
    let mut forecast_rng = ChaCha8Rng::seed_from_u64(settings.forecast_seed);
    let initial_theta = field.water_content();
    let first = field.measure();
    let mut controller = make(first);
    let horizon = controller.settings().horizon;
    let last = weather.len() - 1;
    let mut records = Vec::with_capacity(settings.steps);
    for step in 0..settings.steps {
        let forecast = weather.forecast(step, horizon, settings.forecast_error, &mut forecast_rng);
        let decision = controller.decide(&forecast, Some(&field));
        let truth = weather.steps()[step.min(last)];
        let report = field
            .step(truth.forcing(decision.setpoint, sampling_time))
            .map_err(|e| ClosedLoopError::Plant {
                step,
                message: e.to_string(),
            })?;
        controller.observe(
            decision.setpoint,
            truth.precip_mm,
            report.measured_water_content,
        );
        let solution = decision.solution;
        records.push(StepRecord {
            step,
            irrigation: decision.setpoint,
            precip_mm: truth.precip_mm,
            et0_mm: truth.et0_mm,
            true_theta: report.water_content,
            measured_theta: report.measured_water_content,
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
        water_balance: field.water_balance(),
    })
}
