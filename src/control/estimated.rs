//! The Richards-model zone MPC on the **estimated** state and soil: a
//! controller that sees only the sensors' readings, the irrigation it applied,
//! the observed weather and the forecasts. It runs the ensemble filter of
//! [`crate::estimate`] between steps and starts each solve from the
//! estimator's mean state ([`Estimator::mean_heads`]) with its mean soil
//! ([`Estimator::soil`]). It never reads a plant: that is the oracle's
//! privilege ([`super::Controller::oracle`]).

use std::time::{Duration, Instant};

use crate::estimate::{EstimateError, Estimator, UpdateReport};
use crate::soil::{Crop, Forcing, VanGenuchten};
use crate::weather::WeatherStep;

use super::controller::Decision;
use super::model::PredictionModel;
use super::model::RichardsModel;
use super::mpc::{MpcSettings, ZoneMpc};
use super::policy;
use super::zone::ZoneSettings;

/// What a Richards decision uses of a state estimate, as plain data: the
/// mean heads (top first) and the estimated soil of a column `depth` deep.
/// The daemon's cycle reads it from the stored estimate, the in-process
/// controller from its running filter ([`EstimateView::of`]).
#[derive(Debug, Clone)]
pub struct EstimateView {
    pub heads: Vec<f64>,
    pub soil: VanGenuchten,
    pub depth: f64,
    /// Standard deviation of the estimated θ in the model's output cell
    /// (the zone's back-off, [`policy::backed_off`]).
    pub output_sd: f64,
    /// Whether the "unknown" prior is still selecting the texture (the
    /// Richards model is not settled: [`policy::StartUp`]).
    pub selecting: bool,
}

impl EstimateView {
    pub fn of(estimator: &Estimator) -> EstimateView {
        EstimateView {
            heads: estimator.mean_heads(),
            soil: estimator.soil(),
            depth: estimator.settings().depth,
            output_sd: estimator.output_sd(),
            selecting: estimator.selecting(),
        }
    }
}

/// One Richards-model control step on a state estimate, written once for
/// the in-process [`EstimatedRichards`] and the daemon's
/// `service::cycle::decide`: the model starts from the estimated heads with
/// the estimated soil (its θ bounds too), the zone asked for (`zone`) has
/// its lower bound backed off by the estimate's uncertainty
/// ([`policy::backed_off`]), and while the texture is being selected the
/// sound start holds a field whose `measured` θ is above the zone
/// ([`policy::StartUp`]). Returns the step and the model it planned on (a
/// model that cannot be built is the step's fallback reason).
pub fn step_on_estimate(
    mpc: &mut ZoneMpc,
    zone: ZoneSettings,
    estimate: &EstimateView,
    crop: Crop,
    weather: &[WeatherStep],
    period: f64,
    measured: Option<f64>,
) -> (policy::Step, Option<RichardsModel>) {
    let soil = estimate.soil;
    mpc.settings.theta_r = soil.residual_water_content;
    mpc.settings.theta_s = soil.saturated_water_content;
    mpc.settings.zone = policy::backed_off(zone, estimate.output_sd);
    let mut model = RichardsModel::from_state(
        soil,
        crop,
        estimate.depth,
        estimate.heads.clone(),
        weather,
        period,
    )
    .map_err(|e| format!("no Richards model on the estimate: {e}"));
    let start_up = estimate.selecting.then_some(policy::StartUp {
        settled: false,
        measured,
    });
    let step = policy::step(
        mpc,
        model
            .as_mut()
            .map(|m| m as &mut dyn PredictionModel)
            .map_err(|e| e.clone()),
        start_up,
    );
    (step, model.ok())
}

/// The estimated-Richards controller.
#[derive(Debug, Clone)]
pub struct EstimatedRichards {
    mpc: ZoneMpc,
    /// The zone asked for; the solve aims at it backed off by the
    /// estimate's uncertainty ([`policy::backed_off`]).
    zone: ZoneSettings,
    estimator: Estimator,
    crop: Crop,
    sampling_time: f64,
    /// Times the estimator diverged and was reset to its prior.
    resets: usize,
    /// Wall time of the last predict + update.
    last_estimate_time: Duration,
    last_error: Option<String>,
    /// The sensor at the rooting depth (else the first one), and its latest
    /// reading: the sound start's θ while the texture is selected.
    root_sensor: usize,
    last_reading: Option<f64>,
}

impl EstimatedRichards {
    pub fn new(
        settings: MpcSettings,
        estimator: Estimator,
        crop: Crop,
        sampling_time: f64,
    ) -> EstimatedRichards {
        let (depth, cells) = (estimator.settings().depth, estimator.settings().cells);
        let root = crate::estimate::cell_of(crop.rooting_depth, depth, cells);
        let root_sensor = estimator
            .sensors()
            .iter()
            .position(|s| crate::estimate::cell_of(s.depth, depth, cells) == root)
            .unwrap_or(0);
        EstimatedRichards {
            zone: settings.zone,
            mpc: ZoneMpc::new(settings),
            estimator,
            crop,
            sampling_time,
            resets: 0,
            last_estimate_time: Duration::ZERO,
            last_error: None,
            root_sensor,
            last_reading: None,
        }
    }

    /// The reading the field started from (the sound start's θ until the
    /// first [`EstimatedRichards::observe`]).
    pub fn with_reading(mut self, theta: f64) -> EstimatedRichards {
        self.last_reading = theta.is_finite().then_some(theta);
        self
    }

    pub fn settings(&self) -> &MpcSettings {
        &self.mpc.settings
    }

    pub fn estimator(&self) -> &Estimator {
        &self.estimator
    }

    /// Times the estimator was reset (each a `degraded: ["estimator-reset"]`).
    pub fn resets(&self) -> usize {
        self.resets
    }

    pub fn last_estimate_time(&self) -> Duration {
        self.last_estimate_time
    }

    /// Why the last observation degraded the estimate, if it did.
    pub fn last_error(&self) -> Option<&str> {
        self.last_error.as_deref()
    }

    /// Solves the zone MPC from the estimate under `forecast`
    /// ([`step_on_estimate`], as the daemon's cycle does).
    pub fn decide(&mut self, forecast: &[WeatherStep]) -> Decision {
        let view = EstimateView::of(&self.estimator);
        let (step, _) = step_on_estimate(
            &mut self.mpc,
            self.zone,
            &view,
            self.crop,
            forecast,
            self.sampling_time,
            self.last_reading,
        );
        Decision {
            setpoint: step.rate,
            solution: step.solution,
        }
    }

    /// Records the last step: the forcing it ran under (applied irrigation,
    /// observed ET0 and rain) and the readings (sensor index, θ) at its end.
    /// A diverged estimator is reset to its prior, its members at rest at
    /// the readings; the error is returned for the caller to record.
    pub fn observe(
        &mut self,
        forcing: Forcing,
        readings: &[(usize, f64)],
    ) -> Result<UpdateReport, EstimateError> {
        let start = Instant::now();
        if let Some(&(_, theta)) = readings.iter().find(|&&(k, _)| k == self.root_sensor)
            && theta.is_finite()
        {
            self.last_reading = Some(theta);
        }
        let outcome = self
            .estimator
            .predict(forcing, self.sampling_time)
            .and_then(|()| self.estimator.update(readings));
        let result = match outcome {
            Err(EstimateError::Diverged(why)) => {
                self.resets += 1;
                // the fresh members start at rest at these readings
                self.estimator.reset_to_prior(readings);
                self.last_error = Some(why.clone());
                Err(EstimateError::Diverged(why))
            }
            other => {
                self.last_error = other.as_ref().err().map(|e| e.to_string());
                other
            }
        };
        self.last_estimate_time = start.elapsed();
        result
    }
}
