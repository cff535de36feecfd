//! `rootzone train`: data, the five networks, scores, model files, report.
//!
//! Order of work (MODEL.md §3 and the paper's sections 3–4):
//!
//! 1. data: one multi-level set per sub-model inside its range, one impulse
//!    set over the whole range, and a fresh validation set for each (output
//!    noise 0.1 for training, 0.2 for validation, own seeds), cached; the
//!    training input windows get extra noise up to the validation data's
//!    level ([`noisier_windows`], `--window-noise`), the targets do not;
//! 2. M1, M2, M3, each on its own set;
//! 3. the single LSTM benchmark on the impulse set;
//! 4. the combiner M_A on the sub-models' free-running predictions over the
//!    impulse set, then again on the predictions they make when fed the
//!    combination (as in the two-layer network's own rollout);
//! 5. the two-layer network refined end to end on all of its data, the
//!    impulse set and the three sub-model sets ([`JointTwoLayer`]);
//! 6. both compared networks, the two-layer one and the single LSTM, refined
//!    on the same fresh data (a second draw of the impulse and sub-model
//!    sets, [`TrainPlan::refinement`]) with the same settings, the daemon's
//!    fine-tuning plan: fresh data, not more epochs on the same samples, is
//!    what lowers both networks' validation error (ARCHITECTURE.md);
//! 7. open-loop NRMSE at 1, 10, 20 steps on the validation sets, model files
//!    and `training-report.md`.
//!
//! Every random draw (data, initial weights, shuffling) derives from the
//! plan's seed.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::dataset::{DatasetError, DatasetSpec, Excitation, Series, load_or_generate};
use super::evaluate::recursive_nrmse;
use super::file::{Metadata, ModelFile, ModelFileError};
use super::finetune::{FineTunePlan, refinement_data, training_specs};
use super::network::{Mlp, SequenceNet, Surrogate, TwoLayerNet};
use super::rollout::{HORIZON, Predictor};
use super::scaling::Scaling;
use super::train::{
    EpochReport, JointTwoLayer, SequenceData, Split, TabularData, TrainConfig, TrainError,
    TrainReport, Trainable, combiner_data, combiner_data_closed_loop, holdout, train,
};
use crate::soil::{FieldSettings, VanGenuchten};
use crate::weather::{DRY_SCENARIO, WeatherSeries};

/// Horizons of the open-loop scores.
pub const SCORE_HORIZONS: [usize; 3] = [1, 10, 20];
/// Operating ranges of M1, M2, M3 (MODEL.md §3).
pub const SUB_MODEL_RANGES: [(f64, f64); 3] = [(0.12, 0.27), (0.21, 0.32), (0.29, 0.40)];
/// The whole range.
pub const WHOLE_RANGE: (f64, f64) = (0.12, 0.40);
/// File names of the trained networks.
pub const SUB_MODEL_FILES: [&str; 3] = ["m1.json", "m2.json", "m3.json"];
pub const SINGLE_FILE: &str = "single-lstm.json";
pub const TWO_LAYER_FILE: &str = "two-layer.json";

/// Everything a training run needs.
#[derive(Debug, Clone, PartialEq)]
pub struct TrainPlan {
    pub seed: u64,
    /// The soil the networks are trained for (default sandy loam, the
    /// paper's). The water-content ranges of the data sets (MODEL.md §3,
    /// given for sandy loam) are carried to it by effective saturation.
    pub soil: VanGenuchten,
    /// Training samples per sub-model set and of the impulse set.
    pub sub_model_samples: usize,
    pub impulse_samples: usize,
    /// Samples of each validation set.
    pub validation_samples: usize,
    /// Hidden sizes of M1, M2, M3 and of the single LSTM.
    pub sub_model_hidden: [Vec<usize>; 3],
    pub single_hidden: Vec<usize>,
    pub combiner_hidden: usize,
    pub sub_model_config: TrainConfig,
    pub single_config: TrainConfig,
    pub combiner_config: TrainConfig,
    pub joint_config: TrainConfig,
    /// Fraction of each training set held out for early stopping.
    pub holdout: f64,
    /// Steps of the free-running prediction each training sample is scored on.
    pub horizon: usize,
    /// Noise level, as a fraction of the whole range, that the training input
    /// windows are brought up to (see [`noisier_windows`]); `None` leaves them
    /// as measured. Both plans: 0.2, the validation data's level.
    pub window_noise: Option<f64>,
    /// The last stage: both the two-layer network and the single LSTM
    /// refined on fresh data drawn from `seed + 10` (`None`: no refinement).
    pub refinement: Option<FineTunePlan>,
}

impl TrainPlan {
    /// The shipped models: MODEL.md sizes, hidden size 8 everywhere (chosen
    /// with E2 and the rollout benchmark: 16 units gave no better E1/E2 scores
    /// at twice the rollout cost).
    pub fn full(seed: u64) -> TrainPlan {
        let sequence = TrainConfig {
            learning_rate: 3e-3,
            batch_size: 32,
            max_epochs: 60,
            patience: 12,
            seed,
            ..TrainConfig::default()
        };
        TrainPlan {
            seed,
            soil: VanGenuchten::SANDY_LOAM,
            sub_model_samples: 30_000,
            impulse_samples: 100_000,
            validation_samples: 5_000,
            sub_model_hidden: [vec![8], vec![8], vec![8, 8]],
            single_hidden: vec![8, 8],
            combiner_hidden: 8,
            sub_model_config: sequence,
            single_config: sequence,
            combiner_config: TrainConfig {
                learning_rate: 3e-3,
                max_epochs: 200,
                patience: 20,
                ..sequence
            },
            joint_config: TrainConfig {
                learning_rate: 1e-3,
                max_epochs: 60,
                patience: 10,
                ..sequence
            },
            holdout: 0.15,
            horizon: HORIZON,
            window_noise: Some(0.2),
            refinement: Some(FineTunePlan::default_job()),
        }
    }

    /// Tiny networks on small data, for tests and smoke runs (well under a
    /// minute).
    pub fn quick(seed: u64) -> TrainPlan {
        let sequence = TrainConfig {
            learning_rate: 1e-2,
            batch_size: 32,
            max_epochs: 12,
            patience: 12,
            seed,
            ..TrainConfig::default()
        };
        TrainPlan {
            seed,
            soil: VanGenuchten::SANDY_LOAM,
            sub_model_samples: 1_500,
            impulse_samples: 2_500,
            validation_samples: 600,
            sub_model_hidden: [vec![4], vec![4], vec![4, 4]],
            single_hidden: vec![4, 4],
            combiner_hidden: 4,
            sub_model_config: sequence,
            single_config: sequence,
            combiner_config: TrainConfig {
                max_epochs: 60,
                ..sequence
            },
            joint_config: TrainConfig {
                learning_rate: 3e-3,
                max_epochs: 4,
                ..sequence
            },
            holdout: 0.2,
            horizon: 10,
            window_noise: Some(0.2),
            refinement: Some(FineTunePlan {
                impulse_samples: 1_000,
                sub_model_samples: 300,
                validation_samples: 0,
                config: TrainConfig {
                    learning_rate: 3e-3,
                    max_epochs: 2,
                    ..sequence
                },
                holdout: 0.2,
                horizon: 10,
                window_noise: Some(0.2),
            }),
        }
    }

    /// The data seed of the refinement stage: fresh draws, none of the
    /// first stages' sets.
    pub fn refinement_seed(&self) -> u64 {
        self.seed.wrapping_add(10)
    }

    /// Training set of sub-model `i` (0..3).
    pub fn sub_model_data(&self, i: usize) -> DatasetSpec {
        let (low, high) = range_for(SUB_MODEL_RANGES[i], &self.soil);
        DatasetSpec {
            name: format!("m{}-train", i + 1),
            excitation: Excitation::MultiLevel { low, high },
            samples: self.sub_model_samples,
            noise_fraction: 0.1,
            seed: self.seed.wrapping_mul(1000).wrapping_add(i as u64 + 1),
        }
    }

    /// The whole-range impulse training set.
    pub fn impulse_data(&self) -> DatasetSpec {
        DatasetSpec {
            name: "whole-train".into(),
            excitation: {
                let (low, high) = range_for(WHOLE_RANGE, &self.soil);
                Excitation::Impulse { low, high }
            },
            samples: self.impulse_samples,
            noise_fraction: 0.1,
            seed: self.seed.wrapping_mul(1000).wrapping_add(4),
        }
    }
}

/// A sandy-loam water-content range carried to `soil` by effective
/// saturation Se = (θ − θr)/(θs − θr); sandy loam's own is returned as is.
pub fn range_for(range: (f64, f64), soil: &VanGenuchten) -> (f64, f64) {
    (theta_for(range.0, soil), theta_for(range.1, soil))
}

/// A sandy-loam water content carried to `soil` at the same effective
/// saturation.
pub fn theta_for(theta: f64, soil: &VanGenuchten) -> f64 {
    let sl = VanGenuchten::SANDY_LOAM;
    if *soil == sl {
        return theta;
    }
    let se = (theta - sl.residual_water_content)
        / (sl.saturated_water_content - sl.residual_water_content);
    soil.residual_water_content + se * (soil.saturated_water_content - soil.residual_water_content)
}

/// The scaling of networks for `soil`: the input scaling as shipped, the
/// output range [0.12, 0.41] of sandy loam carried to the soil.
pub fn scaling_for(soil: &VanGenuchten) -> Scaling {
    let mut s = Scaling::default();
    s.output.y_min = theta_for(s.output.y_min, soil);
    s.output.y_max = theta_for(s.output.y_max, soil);
    s
}

/// Validation set `which` (0..3: sub-model ranges, multi-level; 3: whole
/// range, impulse) with output noise 0.2 and the given seed.
pub fn validation_spec(which: usize, samples: usize, seed: u64) -> DatasetSpec {
    validation_spec_for(which, samples, seed, &VanGenuchten::SANDY_LOAM)
}

/// [`validation_spec`] with its range carried to `soil`.
pub fn validation_spec_for(
    which: usize,
    samples: usize,
    seed: u64,
    soil: &VanGenuchten,
) -> DatasetSpec {
    let (name, excitation) = if which < 3 {
        let (low, high) = range_for(SUB_MODEL_RANGES[which], soil);
        (
            format!("m{}-validation", which + 1),
            Excitation::MultiLevel { low, high },
        )
    } else {
        let (low, high) = range_for(WHOLE_RANGE, soil);
        (
            "whole-validation".to_string(),
            Excitation::Impulse { low, high },
        )
    };
    DatasetSpec {
        name,
        excitation,
        samples,
        noise_fraction: 0.2,
        seed: seed.wrapping_mul(1000).wrapping_add(500 + which as u64),
    }
}

/// A training run failed.
#[derive(Debug, thiserror::Error)]
pub enum PipelineError {
    #[error(transparent)]
    Data(#[from] DatasetError),
    #[error(transparent)]
    ModelFile(#[from] ModelFileError),
    #[error("training {network}: {source}")]
    Train {
        network: &'static str,
        source: TrainError,
    },
    #[error("training {0} diverged (non-finite loss)")]
    Diverged(&'static str),
    #[error("cannot write {path}: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
}

/// What a training run reports as it goes.
#[derive(Debug, Clone, PartialEq)]
pub enum ProgressEvent {
    /// A stage starts (data generation, a network).
    Stage {
        network: &'static str,
        what: String,
        max_epochs: usize,
    },
    Epoch {
        network: &'static str,
        report: EpochReport,
    },
    /// A network is trained.
    Finished {
        network: &'static str,
        seconds: f64,
        best_validation_mse: f64,
    },
}

/// One trained network's summary.
#[derive(Debug, Clone, PartialEq)]
pub struct NetworkSummary {
    pub name: &'static str,
    pub hidden: String,
    pub parameters: usize,
    pub epochs: usize,
    pub best_epoch: usize,
    pub initial_validation_mse: f64,
    pub best_validation_mse: f64,
    pub seconds: f64,
}

/// The outcome of [`run_training`].
#[derive(Debug, Clone, PartialEq)]
pub struct TrainingOutcome {
    pub networks: Vec<NetworkSummary>,
    /// (file name, NRMSE at 1/10/20 steps on its validation set).
    pub scores: Vec<(String, [f64; 3])>,
    pub files: Vec<PathBuf>,
    pub report: PathBuf,
    pub seconds: f64,
}

/// Open-loop NRMSE at 1, 10, 20 steps (every window of the series).
pub fn nrmse_scores(predictor: &mut Predictor, series: &Series) -> [f64; 3] {
    let scores = recursive_nrmse(series, &SCORE_HORIZONS, 1, |past, fu, fe| {
        let mut out = vec![0.0; fu.len()];
        match predictor.predict(past, fu, fe, 0.0, &mut out) {
            Ok(()) => out,
            Err(_) => vec![f64::NAN; fu.len()],
        }
    });
    [scores[0], scores[1], scores[2]]
}

/// The weather whose diurnal ET0 shape the training data is generated with
/// (the dry scenario; the daily totals and the rain are drawn, see
/// [`super::dataset`]).
pub fn training_weather() -> WeatherSeries {
    WeatherSeries::parse(DRY_SCENARIO, "embedded weather-dry.csv")
        .expect("the embedded weather scenario parses")
}

/// Trains `model` and reports the epochs as they end.
fn fit<M: Trainable>(
    network: &'static str,
    model: &mut M,
    training: Split<'_, M::Data>,
    validation: Split<'_, M::Data>,
    config: &TrainConfig,
    progress: &mut impl FnMut(ProgressEvent),
) -> Result<(TrainReport, f64), PipelineError> {
    progress(ProgressEvent::Stage {
        network,
        what: "training".into(),
        max_epochs: config.max_epochs,
    });
    let start = Instant::now();
    let report = train(model, training, validation, config, |e| {
        progress(ProgressEvent::Epoch {
            network,
            report: *e,
        })
    })
    .map_err(|source| PipelineError::Train { network, source })?;
    if report.diverged {
        return Err(PipelineError::Diverged(network));
    }
    let seconds = start.elapsed().as_secs_f64();
    progress(ProgressEvent::Finished {
        network,
        seconds,
        best_validation_mse: report.best_validation_mse,
    });
    Ok((report, seconds))
}

fn summary(
    name: &'static str,
    hidden: String,
    parameters: usize,
    report: &TrainReport,
    seconds: f64,
) -> NetworkSummary {
    NetworkSummary {
        name,
        hidden,
        parameters,
        epochs: report.history.len(),
        best_epoch: report.best_epoch,
        initial_validation_mse: report.initial_validation_mse,
        best_validation_mse: report.best_validation_mse,
        seconds,
    }
}

/// The file-name-safe form of a soil's name that keys the data cache.
pub fn cache_name(soil_name: &str) -> String {
    soil_name
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '.' {
                c
            } else {
                '_'
            }
        })
        .collect()
}

/// Runs the whole plan for its soil, named `soil_name` (a texture name or
/// `ks=…,alpha=…,n=…,theta_r=…,theta_s=…`, recorded in the model files),
/// writing the model files and `training-report.md` into `out_dir`,
/// caching data in `cache_dir`.
pub fn run_training(
    plan: &TrainPlan,
    soil_name: &str,
    out_dir: &Path,
    cache_dir: &Path,
    mut progress: impl FnMut(ProgressEvent),
) -> Result<TrainingOutcome, PipelineError> {
    let start = Instant::now();
    let settings = FieldSettings {
        soil: plan.soil,
        ..FieldSettings::default()
    };
    let weather = training_weather();
    let cache_name = cache_name(soil_name);
    let cache_name = cache_name.as_str();
    let scaling = scaling_for(&plan.soil);
    let get = |spec: &DatasetSpec, progress: &mut dyn FnMut(ProgressEvent)| {
        progress(ProgressEvent::Stage {
            network: "data",
            what: format!("{} ({} samples)", spec.name, spec.samples),
            max_epochs: 0,
        });
        load_or_generate(spec, cache_name, &settings, weather.steps(), cache_dir)
    };
    let split = |samples: Vec<usize>| holdout(&samples, plan.holdout);
    // appends a series and gives its input windows the plan's noise, drawn
    // from `noise_seed`: the same seed gives the same windows
    let push_windows = |data: &mut SequenceData, series: &Series, noise_seed: u64| {
        let samples = data.push_series(&series.supply(), &series.measured, &series.et0, &scaling);
        if let Some(level) = plan.window_noise {
            noisier_windows(data, series, &scaling, level, noise_seed);
        }
        samples
    };
    let sub_model_noise_seed = |i: usize| plan.seed.wrapping_add(41 + i as u64);

    // 1–2: sub-models
    let mut networks = Vec::new();
    let mut subs = Vec::new();
    let mut sub_series = Vec::new();
    for i in 0..3 {
        let series = get(&plan.sub_model_data(i), &mut progress)?;
        let mut data = SequenceData::new(plan.horizon);
        let (tr, va) = split(push_windows(&mut data, &series, sub_model_noise_seed(i)));
        let mut net = SequenceNet::new(
            &plan.sub_model_hidden[i],
            plan.seed.wrapping_add(11 + i as u64),
        );
        let name = ["M1", "M2", "M3"][i];
        let (training, validation) = Split::pair(&data, &tr, &va);
        let (report, seconds) = fit(
            name,
            &mut net,
            training,
            validation,
            &plan.sub_model_config,
            &mut progress,
        )?;
        networks.push(summary(
            name,
            format!("{:?}", plan.sub_model_hidden[i]),
            net.n_params(),
            &report,
            seconds,
        ));
        subs.push(net);
        sub_series.push(series);
    }
    let subs: [SequenceNet; 3] = match subs.try_into() {
        Ok(s) => s,
        Err(_) => unreachable!("three sub-models were trained"),
    };

    // 3: the single LSTM on the impulse data
    let impulse = get(&plan.impulse_data(), &mut progress)?;
    let mut data = SequenceData::new(plan.horizon);
    let (tr, va) = split(push_windows(
        &mut data,
        &impulse,
        plan.seed.wrapping_add(44),
    ));
    let (whole_train, whole_val) = Split::pair(&data, &tr, &va);
    let mut single = SequenceNet::new(&plan.single_hidden, plan.seed.wrapping_add(21));
    let (report, seconds) = fit(
        "single LSTM",
        &mut single,
        whole_train,
        whole_val,
        &plan.single_config,
        &mut progress,
    )?;
    networks.push(summary(
        "single LSTM",
        format!("{:?}", plan.single_hidden),
        single.n_params(),
        &report,
        seconds,
    ));

    // 4: the combiner, in two rounds
    let mut combiner = Mlp::new(plan.combiner_hidden, plan.seed.wrapping_add(31));
    let tab_fit = |combiner: &mut Mlp,
                   a: &TabularData,
                   b: &TabularData,
                   progress: &mut dyn FnMut(ProgressEvent)|
     -> Result<(TrainReport, f64), PipelineError> {
        let ia: Vec<usize> = (0..a.targets.len()).collect();
        let ib: Vec<usize> = (0..b.targets.len()).collect();
        fit(
            "M_A",
            combiner,
            Split {
                data: a,
                samples: &ia,
            },
            Split {
                data: b,
                samples: &ib,
            },
            &plan.combiner_config,
            &mut |e| progress(e),
        )
    };
    let (a, b) = (
        combiner_data(&subs, &data, &tr),
        combiner_data(&subs, &data, &va),
    );
    let (_, first_seconds) = tab_fit(&mut combiner, &a, &b, &mut progress)?;
    let (a, b) = (
        combiner_data_closed_loop(&subs, &combiner, &data, &tr),
        combiner_data_closed_loop(&subs, &combiner, &data, &va),
    );
    let (report, seconds) = tab_fit(&mut combiner, &a, &b, &mut progress)?;
    networks.push(summary(
        "M_A",
        format!("[{0}, {0}]", plan.combiner_hidden),
        combiner.n_params(),
        &report,
        first_seconds + seconds,
    ));

    // 5: end-to-end refinement
    let mut joint = JointTwoLayer::new(TwoLayerNet {
        sub_models: subs.clone(),
        combiner,
    });
    // on the impulse set and the sub-models' sets (with the same windows as
    // their own training): the two-layer network is trained on all of its data
    let (mut joint_data, mut joint_tr, mut joint_va) = (data.clone(), tr.clone(), va.clone());
    for (i, series) in sub_series.iter().enumerate() {
        let (a, b) = split(push_windows(
            &mut joint_data,
            series,
            sub_model_noise_seed(i),
        ));
        joint_tr.extend(a);
        joint_va.extend(b);
    }
    let (training, validation) = Split::pair(&joint_data, &joint_tr, &joint_va);
    let (report, seconds) = fit(
        "two-layer (joint)",
        &mut joint,
        training,
        validation,
        &plan.joint_config,
        &mut progress,
    )?;
    let mut two_layer = joint.into_inner();
    networks.push(summary(
        "two-layer (joint)",
        "M1–M3 + M_A".into(),
        Surrogate::TwoLayer(two_layer.clone()).n_params(),
        &report,
        seconds,
    ));

    // 6: both compared networks refined on the same fresh data
    let mut refinement_sets = Vec::new();
    if let Some(refine) = &plan.refinement {
        let seed = plan.refinement_seed();
        refinement_sets = training_specs(refine, &plan.soil, seed);
        let mut series = Vec::new();
        for spec in &refinement_sets {
            series.push(get(spec, &mut progress)?);
        }
        let (data, tr, va) = refinement_data(refine, &plan.soil, seed, &series);
        let config = TrainConfig {
            seed,
            ..refine.config
        };
        let (training, validation) = Split::pair(&data, &tr, &va);
        let mut joint = JointTwoLayer::new(two_layer);
        let (report, seconds) = fit(
            "two-layer (refined)",
            &mut joint,
            training,
            validation,
            &config,
            &mut progress,
        )?;
        two_layer = joint.into_inner();
        networks.push(summary(
            "two-layer (refined)",
            "M1–M3 + M_A".into(),
            Surrogate::TwoLayer(two_layer.clone()).n_params(),
            &report,
            seconds,
        ));
        let (report, seconds) = fit(
            "single LSTM (refined)",
            &mut single,
            training,
            validation,
            &config,
            &mut progress,
        )?;
        networks.push(summary(
            "single LSTM (refined)",
            format!("{:?}", plan.single_hidden),
            single.n_params(),
            &report,
            seconds,
        ));
    }

    // 7: scores and files
    std::fs::create_dir_all(out_dir).map_err(|source| PipelineError::Io {
        path: out_dir.display().to_string(),
        source,
    })?;
    let mut scores = Vec::new();
    let mut files = Vec::new();
    let validation = |which: usize, progress: &mut dyn FnMut(ProgressEvent)| {
        let spec = validation_spec_for(which, plan.validation_samples, plan.seed, &plan.soil);
        progress(ProgressEvent::Stage {
            network: "data",
            what: format!("{} ({} samples)", spec.name, spec.samples),
            max_epochs: 0,
        });
        load_or_generate(&spec, cache_name, &settings, weather.steps(), cache_dir)
            .map(|s| (spec, s))
    };
    let mut write = |file: &str,
                     model: Surrogate,
                     spec: &DatasetSpec,
                     series: &Series,
                     train_specs: Vec<DatasetSpec>|
     -> Result<[f64; 3], PipelineError> {
        let mut predictor = Predictor::new(model.clone(), scaling);
        let s = nrmse_scores(&mut predictor, series);
        let mut metadata = Metadata {
            soil: soil_name.to_string(),
            training_seed: plan.seed,
            ..Metadata::default()
        };
        for (i, t) in train_specs.iter().enumerate() {
            metadata
                .data
                .insert(format!("training_set_{}", i + 1), describe(t));
        }
        metadata
            .data
            .insert("validation_set".into(), describe(spec));
        metadata
            .data
            .insert("training_horizon".into(), plan.horizon.to_string());
        for (h, v) in SCORE_HORIZONS.iter().zip(s) {
            metadata.scores.insert(format!("nrmse_{h}"), v);
        }
        let path = out_dir.join(file);
        ModelFile {
            model,
            scaling,
            metadata,
        }
        .save(&path)?;
        files.push(path);
        scores.push((file.to_string(), s));
        Ok(s)
    };
    for i in 0..3 {
        let (spec, series) = validation(i, &mut progress)?;
        write(
            SUB_MODEL_FILES[i],
            Surrogate::Single(subs[i].clone()),
            &spec,
            &series,
            vec![plan.sub_model_data(i)],
        )?;
    }
    let (spec, series) = validation(3, &mut progress)?;
    write(
        SINGLE_FILE,
        Surrogate::Single(single),
        &spec,
        &series,
        std::iter::once(plan.impulse_data())
            .chain(refinement_sets.iter().cloned())
            .collect(),
    )?;
    write(
        TWO_LAYER_FILE,
        Surrogate::TwoLayer(two_layer),
        &spec,
        &series,
        vec![
            plan.sub_model_data(0),
            plan.sub_model_data(1),
            plan.sub_model_data(2),
            plan.impulse_data(),
        ]
        .into_iter()
        .chain(refinement_sets)
        .collect(),
    )?;
    let seconds = start.elapsed().as_secs_f64();
    let report = out_dir.join("training-report.md");
    std::fs::write(
        &report,
        training_report(plan, soil_name, &networks, &scores, seconds),
    )
    .map_err(|source| PipelineError::Io {
        path: report.display().to_string(),
        source,
    })?;
    Ok(TrainingOutcome {
        networks,
        scores,
        files,
        report,
        seconds,
    })
}

/// Gives the input windows of `data` (one series, already pushed) noise of
/// the variance of Uniform(±`level`·(y_max − y_min)) over the whole range,
/// by adding independent uniform noise to the measured outputs they read;
/// the targets stay as measured.
///
/// The measurements a network is given in use (the validation sets: 0.2 of
/// the range, MODEL.md §2) are noisier than its training data (0.1 of its own
/// set's range); a network that saw only the training noise follows the
/// window's last samples too closely. The extra amplitude `a` makes the
/// variances add up: a² = (level·R)² − (noise of the set)², in scaled units.
pub fn noisier_windows(
    data: &mut SequenceData,
    series: &Series,
    scaling: &Scaling,
    level: f64,
    seed: u64,
) {
    let (min, max) = series
        .water_content
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| {
            (a.min(v), b.max(v))
        });
    let own = series
        .measured
        .iter()
        .zip(&series.water_content)
        .map(|(m, y)| (m - y).abs())
        .fold(0.0, f64::max);
    let whole = level * (WHOLE_RANGE.1 - WHOLE_RANGE.0).max(max - min);
    let extra = (whole * whole - own * own).max(0.0).sqrt() / scaling.output.span();
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let start = data.y.len() - series.len();
    // earlier series keep their windows (as measured, or made noisier before)
    if data.y_input.len() < start {
        data.y_input = data.y[..start].to_vec();
    }
    data.y_input.truncate(start);
    data.y_input.extend(
        data.y[start..]
            .iter()
            .map(|&y| y + extra * (2.0 * rng.random::<f64>() - 1.0)),
    );
}

/// One line describing a data set (for model files and reports).
pub fn describe(spec: &DatasetSpec) -> String {
    let (low, high) = spec.excitation.range();
    let kind = match spec.excitation {
        Excitation::MultiLevel { .. } => "multi-level",
        Excitation::Impulse { .. } => "impulse",
    };
    format!(
        "{}: {kind} in [{low}, {high}], {} samples, output noise {} of the range, seed {}",
        spec.name, spec.samples, spec.noise_fraction, spec.seed
    )
}

fn training_report(
    plan: &TrainPlan,
    soil: &str,
    networks: &[NetworkSummary],
    scores: &[(String, [f64; 3])],
    seconds: f64,
) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "# Training report\n");
    let _ = writeln!(
        s,
        "Soil {soil}, seed {}, {:.1} s in all (data generation included). \
         Training samples: {} per sub-model, {} impulse; validation sets of {} \
         samples (output noise 0.2 of the range, seeds of their own); each \
         sample scored on a free-running {}-step prediction. {}\n",
        plan.seed,
        seconds,
        plan.sub_model_samples,
        plan.impulse_samples,
        plan.validation_samples,
        plan.horizon,
        match plan.window_noise {
            Some(level) => format!(
                "The input windows are brought to the noise of Uniform(±{level} of \
                 the whole range) by extra uniform noise; the targets stay as measured."
            ),
            None => "The input windows are as measured.".to_string(),
        }
    );
    if let Some(refine) = &plan.refinement {
        let _ = writeln!(
            s,
            "Last, the two-layer network and the single LSTM are both refined on the same \
             fresh data (seed {}: {} impulse samples, {} per sub-model range) with the same \
             settings (learning rate {}, at most {} epochs, patience {}).\n",
            plan.refinement_seed(),
            refine.impulse_samples,
            refine.sub_model_samples,
            refine.config.learning_rate,
            refine.config.max_epochs,
            refine.config.patience
        );
    }
    let _ = writeln!(
        s,
        "| network | hidden | parameters | epochs | best epoch | initial val. MSE | best val. MSE | time [s] |"
    );
    let _ = writeln!(s, "|---|---|---:|---:|---:|---:|---:|---:|");
    for n in networks {
        let _ = writeln!(
            s,
            "| {} | {} | {} | {} | {} | {:.3e} | {:.3e} | {:.1} |",
            n.name,
            n.hidden,
            n.parameters,
            n.epochs,
            n.best_epoch,
            n.initial_validation_mse,
            n.best_validation_mse,
            n.seconds
        );
    }
    let _ = writeln!(
        s,
        "\nMSE in scaled units, on the held-out part of the training data.\n\n\
         ## Open-loop NRMSE on the validation sets\n"
    );
    let _ = writeln!(s, "| model file | 1 step | 10 steps | 20 steps |");
    let _ = writeln!(s, "|---|---:|---:|---:|");
    for (file, v) in scores {
        let _ = writeln!(s, "| {file} | {:.4} | {:.4} | {:.4} |", v[0], v[1], v[2]);
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A synthetic series: a slow sine over [0.15, 0.35] with uniform output
    /// noise of ±`noise`.
    fn series(len: usize, noise: f64, seed: u64) -> Series {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let water_content: Vec<f64> = (0..len)
            .map(|k| 0.25 + 0.1 * (k as f64 / 50.0).sin())
            .collect();
        let measured = water_content
            .iter()
            .map(|y| y + noise * (2.0 * rng.random::<f64>() - 1.0))
            .collect();
        Series {
            irrigation: vec![1e-7; len],
            rain: vec![0.0; len],
            et0: vec![4e-8; len],
            water_content,
            measured,
        }
    }

    #[test]
    fn noisier_windows_reach_the_requested_noise_and_leave_the_targets() {
        let scaling = Scaling::default();
        let span = scaling.output.span();
        // range of the clean series 0.2 < the whole range 0.28: the level
        // refers to the whole range
        let first = series(40_000, 0.02, 1);
        let second = series(30_000, 0.01, 2);
        let mut data = SequenceData::new(HORIZON);
        data.push_series(&first.irrigation, &first.measured, &first.et0, &scaling);
        let targets_before = data.y.clone();
        noisier_windows(&mut data, &first, &scaling, 0.2, 9);
        data.push_series(&second.irrigation, &second.measured, &second.et0, &scaling);
        noisier_windows(&mut data, &second, &scaling, 0.2, 10);
        assert_eq!(data.y[..first.len()], targets_before[..]);
        assert_eq!(data.y_input.len(), data.y.len());
        // window noise against the clean output: variance of Uniform(±0.2·0.28)
        let want = (0.2f64 * 0.28).powi(2) / 3.0;
        for (offset, s) in [(0, &first), (first.len(), &second)] {
            let n = s.len() as f64;
            let (mut mean, mut var) = (0.0, 0.0);
            for (k, y) in s.water_content.iter().enumerate() {
                let e = data.y_input[offset + k] * span + scaling.output.y_min - y;
                mean += e / n;
                var += e * e / n;
            }
            assert!(mean.abs() < 1e-3, "{mean}");
            assert!((var / want - 1.0).abs() < 0.03, "{var} vs {want}");
        }
        // the same seed gives the same windows
        let mut again = SequenceData::new(HORIZON);
        again.push_series(&first.irrigation, &first.measured, &first.et0, &scaling);
        noisier_windows(&mut again, &first, &scaling, 0.2, 9);
        assert_eq!(again.y_input[..], data.y_input[..first.len()]);
    }
}
