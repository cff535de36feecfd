//! A warm start: the shipped two-layer network refined for another soil.
//!
//! The per-field training jobs of the daemon (issue 17, part 3) start from
//! a base two-layer network (the shipped sandy-loam one) instead of random
//! weights: the data sets of [`pipeline`](super::pipeline) are generated
//! for the new soil at the same effective saturation (so the networks'
//! scaled inputs and outputs mean the same), and the whole network is
//! refined end to end ([`JointTwoLayer`]) for a few epochs. Then it is
//! scored against the Richards model of that soil on a fresh validation
//! set (its own seed), and the base network beside it.

use std::collections::BTreeMap;
use std::path::Path;
use std::time::Instant;

use super::dataset::{DatasetError, DatasetSpec, Excitation, Series, load_or_generate};
use super::file::{Metadata, ModelFile};
use super::network::{Surrogate, TwoLayerNet};
use super::pipeline::{
    ProgressEvent, SCORE_HORIZONS, SUB_MODEL_RANGES, WHOLE_RANGE, describe, noisier_windows,
    nrmse_scores, range_for, scaling_for, training_weather, validation_spec_for,
};
use super::rollout::{HORIZON, Predictor};
use super::train::{
    JointTwoLayer, SequenceData, Split, TrainConfig, TrainError, holdout, train_until,
};
use crate::soil::{FieldSettings, VanGenuchten};

/// How a fine-tuning run is sized.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FineTunePlan {
    /// Samples of the whole-range impulse set.
    pub impulse_samples: usize,
    /// Samples of each sub-model range's multi-level set (0: none).
    pub sub_model_samples: usize,
    /// Samples of the fresh validation set.
    pub validation_samples: usize,
    pub config: TrainConfig,
    pub holdout: f64,
    /// Steps of the free-running prediction each sample is scored on.
    pub horizon: usize,
    /// As [`TrainPlan::window_noise`](super::pipeline::TrainPlan::window_noise).
    pub window_noise: Option<f64>,
}

impl FineTunePlan {
    /// The daemon's default job: 60 % of the shipped plan's impulse data
    /// and 40 % of its sub-model data, at most 16 epochs at the shipped
    /// refinement's learning rate (measured with `examples/finetune.rs`:
    /// within 10 % of a from-scratch training on loam, in under 3 minutes
    /// on one core; ARCHITECTURE.md).
    pub fn default_job() -> FineTunePlan {
        FineTunePlan {
            impulse_samples: 60_000,
            sub_model_samples: 12_000,
            validation_samples: 3_000,
            config: TrainConfig {
                learning_rate: 1e-3,
                batch_size: 32,
                max_epochs: 16,
                patience: 3,
                ..TrainConfig::default()
            },
            holdout: 0.15,
            horizon: HORIZON,
            window_noise: Some(0.2),
        }
    }
}

/// The outcome of [`fine_tune`].
#[derive(Debug, Clone)]
pub struct FineTuned {
    /// The refined network, its scaling (for the soil) and metadata.
    pub file: ModelFile,
    /// NRMSE at 1/10/20 steps on the fresh validation set.
    pub scores: [f64; 3],
    /// The base network's NRMSE on the same set (scaled for the soil).
    pub base_scores: [f64; 3],
    pub epochs: usize,
    pub seconds: f64,
}

/// Fine-tuning failed or was cancelled.
#[derive(Debug, thiserror::Error)]
pub enum FineTuneError {
    #[error(transparent)]
    Data(#[from] DatasetError),
    #[error("training: {0}")]
    Train(TrainError),
    #[error("training diverged (non-finite loss)")]
    Diverged,
    #[error("cancelled")]
    Cancelled,
    #[error("invalid soil: {0}")]
    Soil(String),
}

/// The data sets of a run for `soil` with data seed `seed`: the impulse set
/// over the whole range, then the sub-model ranges' multi-level sets.
pub fn training_specs(plan: &FineTunePlan, soil: &VanGenuchten, seed: u64) -> Vec<DatasetSpec> {
    let mut specs = Vec::new();
    let (low, high) = range_for(WHOLE_RANGE, soil);
    specs.push(DatasetSpec {
        name: "whole-train".into(),
        excitation: Excitation::Impulse { low, high },
        samples: plan.impulse_samples,
        noise_fraction: 0.1,
        seed: seed.wrapping_mul(1000).wrapping_add(4),
    });
    if plan.sub_model_samples > 0 {
        for (i, range) in SUB_MODEL_RANGES.iter().enumerate() {
            let (low, high) = range_for(*range, soil);
            specs.push(DatasetSpec {
                name: format!("m{}-train", i + 1),
                excitation: Excitation::MultiLevel { low, high },
                samples: plan.sub_model_samples,
                noise_fraction: 0.1,
                seed: seed.wrapping_mul(1000).wrapping_add(i as u64 + 1),
            });
        }
    }
    specs
}

/// The validation seed of data seed `seed`: never one of its training sets'.
pub fn validation_seed(seed: u64) -> u64 {
    seed.wrapping_add(1_000_003)
}

/// The training data of a refinement from the series of
/// [`training_specs`] (in that order): every series pushed with the plan's
/// window noise, each split into training and held-out samples. The
/// daemon's jobs refine the two-layer network on it; `rootzone train`'s
/// last stage refines both the two-layer network and the single LSTM on it.
pub fn refinement_data(
    plan: &FineTunePlan,
    soil: &VanGenuchten,
    seed: u64,
    series: &[Series],
) -> (SequenceData, Vec<usize>, Vec<usize>) {
    let scaling = scaling_for(soil);
    let mut data = SequenceData::new(plan.horizon);
    let (mut tr, mut va) = (Vec::new(), Vec::new());
    for (i, series) in series.iter().enumerate() {
        let samples = data.push_series(&series.supply(), &series.measured, &series.et0, &scaling);
        if let Some(level) = plan.window_noise {
            noisier_windows(
                &mut data,
                series,
                &scaling,
                level,
                seed.wrapping_add(41 + i as u64),
            );
        }
        let (a, b) = holdout(&samples, plan.holdout);
        tr.extend(a);
        va.extend(b);
    }
    (data, tr, va)
}

/// Refines `base` for `soil` (named `soil_name` in the metadata) on data
/// drawn from `seed`, caching the data in `cache_dir`; `stop` is asked
/// between the stages and before every mini-batch. `base_name` describes
/// the base in the metadata (`base_model`).
#[allow(clippy::too_many_arguments)]
pub fn fine_tune(
    base: &TwoLayerNet,
    base_name: &str,
    soil: VanGenuchten,
    soil_name: &str,
    plan: &FineTunePlan,
    seed: u64,
    cache_dir: &Path,
    mut progress: impl FnMut(ProgressEvent),
    stop: &dyn Fn() -> bool,
) -> Result<FineTuned, FineTuneError> {
    soil.validate().map_err(FineTuneError::Soil)?;
    let start = Instant::now();
    let settings = FieldSettings {
        soil,
        ..FieldSettings::default()
    };
    let weather = training_weather();
    let cache_name = super::pipeline::cache_name(soil_name);
    let scaling = scaling_for(&soil);
    let mut get = |spec: &DatasetSpec| -> Result<Series, FineTuneError> {
        if stop() {
            return Err(FineTuneError::Cancelled);
        }
        progress(ProgressEvent::Stage {
            network: "data",
            what: format!("{} ({} samples)", spec.name, spec.samples),
            max_epochs: 0,
        });
        Ok(load_or_generate(
            spec,
            &cache_name,
            &settings,
            weather.steps(),
            cache_dir,
        )?)
    };
    let specs = training_specs(plan, &soil, seed);
    let mut series = Vec::new();
    for spec in &specs {
        series.push(get(spec)?);
    }
    let (data, tr, va) = refinement_data(plan, &soil, seed, &series);
    let validation_spec =
        validation_spec_for(3, plan.validation_samples, validation_seed(seed), &soil);
    let validation = get(&validation_spec)?;
    progress(ProgressEvent::Stage {
        network: "two-layer (fine-tune)",
        what: "training".into(),
        max_epochs: plan.config.max_epochs,
    });
    let mut joint = JointTwoLayer::new(base.clone());
    let config = TrainConfig {
        seed,
        ..plan.config
    };
    let (training, held_out) = Split::pair(&data, &tr, &va);
    let report = train_until(
        &mut joint,
        training,
        held_out,
        &config,
        |e| {
            progress(ProgressEvent::Epoch {
                network: "two-layer (fine-tune)",
                report: *e,
            })
        },
        stop,
    )
    .map_err(|e| match e {
        TrainError::Cancelled => FineTuneError::Cancelled,
        e => FineTuneError::Train(e),
    })?;
    if report.diverged {
        return Err(FineTuneError::Diverged);
    }
    progress(ProgressEvent::Finished {
        network: "two-layer (fine-tune)",
        seconds: start.elapsed().as_secs_f64(),
        best_validation_mse: report.best_validation_mse,
    });
    if stop() {
        return Err(FineTuneError::Cancelled);
    }
    progress(ProgressEvent::Stage {
        network: "validation",
        what: format!("{} ({} samples)", validation_spec.name, validation.len()),
        max_epochs: 0,
    });
    let net = joint.into_inner();
    let model = Surrogate::TwoLayer(net);
    let scores = nrmse_scores(&mut Predictor::new(model.clone(), scaling), &validation);
    let base_scores = nrmse_scores(
        &mut Predictor::new(Surrogate::TwoLayer(base.clone()), scaling),
        &validation,
    );
    let mut data_desc = BTreeMap::new();
    for (i, s) in specs.iter().enumerate() {
        data_desc.insert(format!("training_set_{}", i + 1), describe(s));
    }
    data_desc.insert("validation_set".into(), describe(&validation_spec));
    data_desc.insert("training_horizon".into(), plan.horizon.to_string());
    data_desc.insert("base_model".into(), base_name.to_string());
    data_desc.insert("epochs".into(), report.history.len().to_string());
    let mut score_map = BTreeMap::new();
    for (h, v) in SCORE_HORIZONS.iter().zip(scores) {
        score_map.insert(format!("nrmse_{h}"), v);
    }
    Ok(FineTuned {
        file: ModelFile {
            model,
            scaling,
            metadata: Metadata {
                soil: soil_name.to_string(),
                training_seed: seed,
                data: data_desc,
                scores: score_map,
            },
        },
        scores,
        base_scores,
        epochs: report.history.len(),
        seconds: start.elapsed().as_secs_f64(),
    })
}

/// The name of a soil by its parameters, as `rootzone train --soil-params`
/// writes it.
pub fn soil_params_name(soil: &VanGenuchten) -> String {
    format!(
        "ks={},alpha={},n={},theta_r={},theta_s={}",
        soil.saturated_conductivity,
        soil.alpha,
        soil.n,
        soil.residual_water_content,
        soil.saturated_water_content
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_validation_seed_is_none_of_the_training_seeds() {
        let plan = FineTunePlan::default_job();
        let soil = VanGenuchten {
            alpha: 3.6,
            n: 1.56,
            ..VanGenuchten::SANDY_LOAM
        };
        let seed = 7;
        let v = validation_spec_for(3, 10, validation_seed(seed), &soil).seed;
        for s in training_specs(&plan, &soil, seed) {
            assert_ne!(s.seed, v, "{}", s.name);
        }
    }

    /// The shipped two-layer network.
    fn shipped_two_layer() -> TwoLayerNet {
        match ModelFile::from_json(
            include_str!("../../models/two-layer.json"),
            Path::new("two-layer"),
        )
        .unwrap()
        .model
        {
            Surrogate::TwoLayer(t) => t,
            Surrogate::Single(_) => unreachable!(),
        }
    }

    #[test]
    fn the_largest_seed_runs_a_job() {
        // a seed is any u64 a client sends: the seeds derived from it wrap
        let base = shipped_two_layer();
        let plan = FineTunePlan {
            impulse_samples: 300,
            sub_model_samples: 0,
            validation_samples: 120,
            horizon: 5,
            config: TrainConfig {
                max_epochs: 1,
                ..FineTunePlan::default_job().config
            },
            ..FineTunePlan::default_job()
        };
        assert!(plan.window_noise.is_some(), "the noisy windows are drawn");
        let dir = tempfile::tempdir().unwrap();
        let r = fine_tune(
            &base,
            "shipped",
            VanGenuchten::SANDY_LOAM,
            "sandy-loam",
            &plan,
            u64::MAX,
            dir.path(),
            |_| {},
            &|| false,
        );
        let tuned = r.unwrap();
        assert!(
            tuned.scores.iter().all(|v| v.is_finite()),
            "{:?}",
            tuned.scores
        );
    }

    #[test]
    fn a_stop_before_the_start_cancels() {
        let base = shipped_two_layer();
        let dir = tempfile::tempdir().unwrap();
        let r = fine_tune(
            &base,
            "shipped",
            VanGenuchten::SANDY_LOAM,
            "sandy-loam",
            &FineTunePlan::default_job(),
            1,
            dir.path(),
            |_| {},
            &|| true,
        );
        assert!(matches!(r, Err(FineTuneError::Cancelled)), "{r:?}");
    }
}
