//! A running controller: the zone MPC with one prediction model and the
//! state that model needs between control steps (the surrogate's window and
//! bias correction), one decision per sampling step.

use crate::estimate::{EstimateError, Estimator};
use crate::soil::Field;
use crate::surrogate::Predictor;
use std::collections::VecDeque;

use crate::weather::{WeatherStep, mm_to_rate};

use super::model::{PredictionModel, RichardsModel, SurrogateModel};
use super::mpc::{MpcSettings, Solution, ZoneMpc};

/// The prediction model a controller uses.
#[derive(Debug, Clone)]
enum Model {
    /// A surrogate with its window and the last `period` residuals
    /// y_meas(t) − ŷ(t | t−1) the bias is the mean of.
    Surrogate {
        model: Box<SurrogateModel>,
        residuals: VecDeque<f64>,
        period: usize,
    },
    /// The Richards model from the full (true) state of a field.
    Richards,
}

/// The zone MPC and the state of its prediction model.
#[derive(Debug, Clone)]
pub struct Controller {
    mpc: ZoneMpc,
    model: Model,
    sampling_time: f64,
    /// Steps observed since the start.
    observed: usize,
    /// The latest measured θ (the first one at the start).
    last_measured: Option<f64>,
    /// A surrogate's reading filter ([`Controller::with_reading_filter`]).
    filter: Option<Box<Estimator>>,
}

/// The controller's decision for one step.
#[derive(Debug, Clone, PartialEq)]
pub struct Decision {
    /// The irrigation rate to apply over the next step [m/s], in [0, u_max].
    pub setpoint: f64,
    pub solution: Solution,
}

impl Controller {
    /// A surrogate controller (single LSTM or two-layer network) with a
    /// single-bias correction: at every step, the mean of y_meas(t) −
    /// ŷ(t | t−1) over the last `bias_period` steps, held over the horizon
    /// (MODEL.md §3, closed loop), and the
    /// first measurement `first` (the window is padded with it, MODEL.md §4).
    pub fn surrogate(
        settings: MpcSettings,
        predictor: Predictor,
        bias_period: usize,
        first: f64,
        sampling_time: f64,
    ) -> Controller {
        Controller {
            mpc: ZoneMpc::new(settings),
            model: Model::Surrogate {
                model: Box::new(SurrogateModel::padded(predictor, first)),
                residuals: VecDeque::with_capacity(bias_period.max(1)),
                period: bias_period.max(1),
            },
            sampling_time,
            observed: 0,
            last_measured: Some(first),
            filter: None,
        }
    }

    /// A surrogate controller whose window and bias see the reading
    /// filtered: at every step the ensemble filter `estimator` (its first
    /// sensor is the one read) assimilates the reading with the applied
    /// irrigation and the observed weather, and its mean θ at that sensor
    /// takes the reading's place in the window and in the residual
    /// y(t) − ŷ(t | t−1). A noisy reading below the zone then no longer
    /// moves the whole predicted horizon by 1.5 times its error (the window's
    /// last θ plus half of it again through the f = 2 bias), which the zone
    /// MPC, unable to take water back, answers with irrigation. A filter
    /// that diverges is reset to its prior at the reading, and that step's
    /// reading is used as it is. The sound start still looks at the raw
    /// reading. (No effect on the Richards controller.)
    pub fn with_reading_filter(mut self, estimator: Estimator) -> Controller {
        self.filter = Some(Box::new(estimator));
        self
    }

    /// The reading filter, if the controller has one.
    pub fn reading_filter(&self) -> Option<&Estimator> {
        self.filter.as_deref()
    }

    /// The **oracle**: the Richards model reading the true soil and the full
    /// true state of the field it is given at every decision. A yardstick
    /// for experiments only; no deployment has a plant's truth (see
    /// [`super::EstimatedRichards`] for the controller that estimates it).
    pub fn oracle(settings: MpcSettings, sampling_time: f64) -> Controller {
        Controller {
            mpc: ZoneMpc::new(settings),
            model: Model::Richards,
            sampling_time,
            observed: 0,
            last_measured: None,
            filter: None,
        }
    }

    pub fn settings(&self) -> &MpcSettings {
        &self.mpc.settings
    }

    /// The bias in force (0 for the Richards model).
    pub fn bias(&self) -> f64 {
        match &self.model {
            Model::Surrogate { model, .. } => model.bias,
            Model::Richards => 0.0,
        }
    }

    /// Records the last step: `irrigation` applied [m/s], the `weather`
    /// observed over it (rain and ET0), `measured` θ at its end. Updates the
    /// window and refits the bias on the bias-free one-step prediction of
    /// that step.
    pub fn observe(&mut self, irrigation: f64, weather: &WeatherStep, measured: f64) {
        self.observed += 1;
        if measured.is_finite() {
            self.last_measured = Some(measured);
        }
        let measured = match self.filter.as_deref_mut() {
            Some(filter) => filtered(
                filter,
                weather.forcing(irrigation, self.sampling_time),
                self.sampling_time,
                measured,
            ),
            None => measured,
        };
        if let Model::Surrogate {
            model,
            residuals,
            period,
        } = &mut self.model
        {
            let supply = irrigation + mm_to_rate(weather.precip_mm, self.sampling_time);
            let et0 = mm_to_rate(weather.et0_mm, self.sampling_time);
            if measured.is_finite() {
                // the one-step prediction of the step just observed, under
                // its observed ET0
                if let Ok(predicted) = model.one_step(supply, et0) {
                    if residuals.len() == *period {
                        residuals.pop_front();
                    }
                    residuals.push_back(measured - predicted);
                    model.bias = super::policy::bias(residuals.make_contiguous());
                }
                model.push(supply, measured, et0);
            }
        }
    }

    /// Solves the zone MPC for the next step under `forecast` (one entry per
    /// horizon step). The Richards controller needs `field` (its true state);
    /// without one it falls back to no irrigation and says so.
    pub fn decide(&mut self, forecast: &[WeatherStep], field: Option<&Field>) -> Decision {
        let n = self.mpc.settings.horizon;
        let rate = |k: usize, of: fn(&WeatherStep) -> f64| {
            forecast
                .get(k)
                .or(forecast.last())
                .map_or(0.0, |w| mm_to_rate(of(w), self.sampling_time))
        };
        let rain: Vec<f64> = (0..n).map(|k| rate(k, |w| w.precip_mm)).collect();
        let et0: Vec<f64> = (0..n).map(|k| rate(k, |w| w.et0_mm)).collect();
        let mut richards;
        let (model, start_up): (Result<&mut dyn PredictionModel, String>, _) =
            match (&mut self.model, field) {
                (Model::Surrogate { model, .. }, _) => {
                    model.rain = rain;
                    model.et0 = et0;
                    // the first measurement and each one observed since
                    // are the samples
                    let start_up = super::policy::StartUp::window(
                        self.observed + 1,
                        crate::surrogate::evaluate::WINDOW,
                        self.last_measured,
                    );
                    (Ok(model.as_mut()), Some(start_up))
                }
                (Model::Richards, Some(field)) => {
                    richards = RichardsModel::new(field, forecast);
                    (Ok(&mut richards), None)
                }
                (Model::Richards, None) => (
                    Err("the Richards model needs the field state".to_string()),
                    None,
                ),
            };
        let step = super::policy::step(&mut self.mpc, model, start_up);
        let (setpoint, solution) = (step.rate, step.solution);
        Decision { setpoint, solution }
    }
}

/// The standard deviation of a reading θ·(1 + U(−m, m)) (the simulated
/// sensors' relative uniform noise of level `level`) near θ = `theta`, at
/// least that of 0.5 % noise: the sensor error an estimator is told.
pub fn relative_noise_sd(level: f64, theta: f64) -> f64 {
    level.max(0.005) * theta / 3f64.sqrt()
}

/// The reading filter of a surrogate trained on `soil`
/// ([`Controller::with_reading_filter`]): the ensemble filter of
/// [`crate::estimate`] around that soil (its texture spreads), one sensor at
/// the rooting depth whose error has standard deviation `sensor_sd`
/// [m³/m³], its members at rest at the first reading `first`.
pub fn reading_filter(
    soil: crate::soil::VanGenuchten,
    first: f64,
    sensor_sd: f64,
    seed: u64,
) -> Result<Estimator, String> {
    use crate::estimate::{EstimatorSettings, InitialGuess, Prior, Sensor};
    let crop = crate::soil::Crop::default();
    Estimator::new(
        Prior::Soil(soil),
        crop,
        vec![Sensor {
            id: "root".into(),
            depth: crop.rooting_depth,
            noise: sensor_sd,
        }],
        InitialGuess::Reading(first),
        EstimatorSettings {
            seed,
            ..EstimatorSettings::default()
        },
    )
}

/// The filter's mean θ at its first sensor after forecasting the step and
/// assimilating `reading` (the reading itself when the filter fails; a
/// diverged one is reset). A step without a finite reading is forecast
/// only, so the filter keeps pace with the field.
fn filtered(filter: &mut Estimator, forcing: crate::soil::Forcing, dt: f64, reading: f64) -> f64 {
    let readings = [(0, reading)];
    if !reading.is_finite() {
        if filter.predict(forcing, dt).is_err() {
            tracing::debug!("reading filter: the forecast of a step without a reading failed");
        }
        return reading;
    }
    match filter
        .predict(forcing, dt)
        .and_then(|()| filter.update(&readings))
    {
        Ok(_) => filter
            .sensor_theta(0)
            .filter(|t| t.is_finite())
            .unwrap_or(reading),
        Err(EstimateError::Diverged(_)) => {
            filter.reset_to_prior(&readings);
            reading
        }
        Err(_) => reading,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::surrogate::ModelFile;
    use crate::weather::WeatherStep;

    fn two_layer() -> ModelFile {
        ModelFile::from_json(
            include_str!("../../models/two-layer.json"),
            std::path::Path::new("two-layer"),
        )
        .unwrap()
    }

    #[test]
    fn a_surrogate_starting_above_its_zone_does_not_irrigate_until_it_has_a_window() {
        for (theta, rain_mm) in [(0.2605, 0.0), (0.256, 1.5)] {
            let mut c = Controller::surrogate(
                MpcSettings::default(),
                two_layer().predictor(),
                2,
                theta,
                7200.0,
            );
            let forecast = vec![
                WeatherStep {
                    start_hour: 0.0,
                    et0_mm: 0.33,
                    precip_mm: rain_mm,
                };
                20
            ];
            let d = c.decide(&forecast, None);
            assert_eq!(d.setpoint, 0.0, "θ {theta}: {:?}", d.solution.plan);
            // a field below its zone is irrigated from the start
            let mut dry = Controller::surrogate(
                MpcSettings::default(),
                two_layer().predictor(),
                2,
                0.15,
                7200.0,
            );
            let forecast = vec![
                WeatherStep {
                    start_hour: 0.0,
                    et0_mm: 0.33,
                    precip_mm: 0.0,
                };
                20
            ];
            assert!(dry.decide(&forecast, None).setpoint > 0.0);
        }
    }

    /// The window of a filtered surrogate lies closer to the true θ than the
    /// readings do: a sandy-loam field with 5 % relative reading noise,
    /// 40 dry steps under pulses of irrigation; the same controller without
    /// the filter holds the raw readings.
    #[test]
    fn the_reading_filter_brings_the_window_closer_to_the_truth() {
        use crate::soil::{Field, FieldSettings};
        let level = 0.05;
        let mut field = Field::new(FieldSettings {
            measurement_noise: level,
            seed: 11,
            ..FieldSettings::default()
        })
        .unwrap();
        let first = field.measure();
        let sd = relative_noise_sd(level, 0.2);
        let filter = reading_filter(crate::soil::VanGenuchten::SANDY_LOAM, first, sd, 5).unwrap();
        let settings = MpcSettings::default();
        let mut plain = Controller::surrogate(settings, two_layer().predictor(), 2, first, 7200.0);
        let mut filtered = plain.clone().with_reading_filter(filter);
        assert!(plain.reading_filter().is_none() && filtered.reading_filter().is_some());
        let dry =
            crate::weather::WeatherSeries::parse(crate::weather::DRY_SCENARIO, "dry").unwrap();
        let (mut raw_sq, mut filtered_sq) = (0.0, 0.0);
        for k in 0..40 {
            let weather = dry.steps()[k % dry.len()];
            let irrigation = if k % 6 == 2 { 2e-6 } else { 0.0 };
            let report = field.step(weather.forcing(irrigation, 7200.0)).unwrap();
            plain.observe(irrigation, &weather, report.measured_water_content);
            filtered.observe(irrigation, &weather, report.measured_water_content);
            let last = |c: &Controller| match &c.model {
                Model::Surrogate { model, .. } => *model.past_y.last().unwrap(),
                Model::Richards => unreachable!("a surrogate"),
            };
            // the plain window holds the reading itself
            assert_eq!(last(&plain), report.measured_water_content);
            if k >= 10 {
                raw_sq += (last(&plain) - report.water_content).powi(2);
                filtered_sq += (last(&filtered) - report.water_content).powi(2);
            }
        }
        let (raw, filt) = (raw_sq.sqrt(), filtered_sq.sqrt());
        assert!(
            filt < 0.7 * raw,
            "filtered RMS error {filt} against raw {raw}"
        );
    }

    /// A step without a reading is forecast (the filter keeps pace with the
    /// field), and a reading the filter cannot explain (θ jumping from 0.2
    /// to 0.38 in one dry step) makes it diverge: it is reset at that
    /// reading, and the window takes the reading itself.
    #[test]
    fn a_filter_that_diverges_is_reset_and_the_reading_is_used() {
        let first = 0.2;
        let sd = relative_noise_sd(0.02, 0.2);
        let filter = reading_filter(crate::soil::VanGenuchten::SANDY_LOAM, first, sd, 5).unwrap();
        let mut c = Controller::surrogate(
            MpcSettings::default(),
            two_layer().predictor(),
            2,
            first,
            7200.0,
        )
        .with_reading_filter(filter);
        let dry = WeatherStep {
            start_hour: 12.0,
            et0_mm: 0.5,
            precip_mm: 0.0,
        };
        let last = |c: &Controller| match &c.model {
            Model::Surrogate { model, .. } => *model.past_y.last().unwrap(),
            Model::Richards => unreachable!("a surrogate"),
        };
        let start = c.reading_filter().unwrap().time();
        // a step without a reading is forecast: the filter keeps pace
        c.observe(0.0, &dry, f64::NAN);
        assert_eq!(c.reading_filter().unwrap().time(), start + 7200.0);
        c.observe(0.0, &dry, 0.199);
        // an ordinary reading is filtered: not the reading itself
        assert_ne!(last(&c), 0.199);
        assert!((last(&c) - 0.199).abs() < 0.01, "{}", last(&c));
        c.observe(0.0, &dry, 0.38);
        assert_eq!(last(&c), 0.38);
        // the reset filter starts at rest at that reading
        let after = c.reading_filter().unwrap().sensor_theta(0).unwrap();
        assert!((after - 0.38).abs() < 0.01, "{after}");
    }
}
