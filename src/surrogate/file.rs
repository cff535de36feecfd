//! The model file: a self-describing, versioned JSON document.
//!
//! ```json
//! {
//!   "format": "rootzone-surrogate",
//!   "version": 2,
//!   "architecture": { "kind": "two-layer", "sub_models": [[32], [32], [32, 32]], "combiner_hidden": 16 },
//!   "scaling": { "u0": 1e-8, "u_max": 1e-5, "y_min": 0.12, "y_max": 0.41, "et0_ref": 1e-7 },
//!   "metadata": { "soil": "loam", "training_seed": 1, "data": { … }, "scores": { … } },
//!   "weights": [ … ]
//! }
//! ```
//!
//! `architecture.kind` is `"lstm"` (with `"hidden": [h₁, h₂?]`) or
//! `"two-layer"`. `weights` is [`Surrogate::params`]: all parameters, model
//! after model (M1, M2, M3, M_A), each in its layer layout, written as decimal
//! strings (`"-0.14384829467088284"`, Rust's shortest round-trip form) so that
//! every weight reads back bit for bit: serde_json's default float parser (without
//! its `float_roundtrip` feature) may be off by one unit in the last place.
//!
//! Version 2 added the ET0 input. A version-1 file (inputs ū and ȳ, no
//! `et0_ref`) still loads: its networks get a zero weight on ē, so they
//! predict what they did, blind to ET0, and are saved as version 2.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::network::{
    MAX_HIDDEN, Mlp, SequenceNet, Surrogate, TwoLayerNet, lstm_architecture_problem,
};
use super::rollout::Predictor;
use super::scaling::{DEFAULT_ET0_REF, Et0Scaling, InputScaling, OutputScaling, Scaling};

/// Value of the `format` field.
pub const FORMAT: &str = "rootzone-surrogate";
/// The version this build writes (it reads this one and [`LEGACY_VERSION`]).
pub const VERSION: u32 = 2;
/// The version before the ET0 input, still read.
pub const LEGACY_VERSION: u32 = 1;

/// Free-form description of how a model was made.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Metadata {
    pub soil: String,
    pub training_seed: u64,
    /// Data settings (names, sizes, noise, …) as text.
    pub data: BTreeMap<String, String>,
    /// Validation scores (e.g. NRMSE per horizon).
    pub scores: BTreeMap<String, f64>,
}

/// A trained surrogate with its scaling and metadata.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelFile {
    pub model: Surrogate,
    pub scaling: Scaling,
    pub metadata: Metadata,
}

/// A model file could not be written or read.
#[derive(Debug, thiserror::Error)]
pub enum ModelFileError {
    #[error("cannot {action} {path}: {source}")]
    Io {
        action: &'static str,
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}:{line}:{column}: malformed model file: {message}")]
    Malformed {
        path: PathBuf,
        line: usize,
        column: usize,
        message: String,
    },
    #[error(
        "{path}: format {found_format:?} version {found_version}, expected {FORMAT:?} version {LEGACY_VERSION} or {VERSION}"
    )]
    WrongFormat {
        path: PathBuf,
        found_format: String,
        found_version: u64,
    },
    #[error("{path}: invalid model: {message}")]
    Invalid { path: PathBuf, message: String },
    #[error("{path}: the architecture has {expected} weights, the file {found}")]
    WeightsLength {
        path: PathBuf,
        expected: usize,
        found: usize,
    },
}

#[derive(Serialize, Deserialize)]
struct HeaderDto {
    format: String,
    version: u64,
}

#[derive(Serialize, Deserialize)]
#[serde(tag = "kind", deny_unknown_fields)]
enum ArchitectureDto {
    #[serde(rename = "lstm")]
    Lstm { hidden: Vec<usize> },
    #[serde(rename = "two-layer")]
    TwoLayer {
        sub_models: Vec<Vec<usize>>,
        combiner_hidden: usize,
    },
}

#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct ScalingDto {
    u0: f64,
    u_max: f64,
    y_min: f64,
    y_max: f64,
    /// Absent in version 1.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    et0_ref: Option<f64>,
}

#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct MetadataDto {
    soil: String,
    training_seed: u64,
    #[serde(default)]
    data: BTreeMap<String, String>,
    #[serde(default)]
    scores: BTreeMap<String, f64>,
}

#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct FileDto {
    format: String,
    version: u64,
    architecture: ArchitectureDto,
    scaling: ScalingDto,
    metadata: MetadataDto,
    weights: Vec<String>,
}

impl ModelFile {
    /// A predictor for recursive prediction with this model.
    pub fn predictor(&self) -> Predictor {
        Predictor::new(self.model.clone(), self.scaling)
    }

    fn to_dto(&self) -> FileDto {
        let architecture = match &self.model {
            Surrogate::Single(net) => ArchitectureDto::Lstm {
                hidden: net.hidden_sizes(),
            },
            Surrogate::TwoLayer(m) => ArchitectureDto::TwoLayer {
                sub_models: m.sub_models.iter().map(SequenceNet::hidden_sizes).collect(),
                combiner_hidden: m.combiner.hidden(),
            },
        };
        let s = self.scaling;
        FileDto {
            format: FORMAT.to_string(),
            version: u64::from(VERSION),
            architecture,
            scaling: ScalingDto {
                u0: s.input.u0,
                u_max: s.input.u_max,
                y_min: s.output.y_min,
                y_max: s.output.y_max,
                et0_ref: Some(s.et0.reference),
            },
            metadata: MetadataDto {
                soil: self.metadata.soil.clone(),
                training_seed: self.metadata.training_seed,
                data: self.metadata.data.clone(),
                scores: self.metadata.scores.clone(),
            },
            weights: self.model.params().iter().map(f64::to_string).collect(),
        }
    }

    /// The JSON text of the file.
    pub fn to_json(&self) -> String {
        // serialising plain structs, maps and numbers cannot fail
        serde_json::to_string_pretty(&self.to_dto()).unwrap_or_default()
    }

    /// Parses the JSON text of a model file; `path` names it in errors.
    pub fn from_json(text: &str, path: &Path) -> Result<ModelFile, ModelFileError> {
        let malformed = |e: serde_json::Error| ModelFileError::Malformed {
            path: path.to_path_buf(),
            line: e.line(),
            column: e.column(),
            message: e.to_string(),
        };
        let invalid = |message: String| ModelFileError::Invalid {
            path: path.to_path_buf(),
            message,
        };
        // Check format and version before the rest, whose schema may differ.
        let header: HeaderDto = serde_json::from_str(text).map_err(malformed)?;
        let legacy = header.version == u64::from(LEGACY_VERSION);
        if header.format != FORMAT || !(legacy || header.version == u64::from(VERSION)) {
            return Err(ModelFileError::WrongFormat {
                path: path.to_path_buf(),
                found_format: header.format,
                found_version: header.version,
            });
        }
        let dto: FileDto = serde_json::from_str(text).map_err(malformed)?;
        let scaling = Scaling {
            input: InputScaling {
                u0: dto.scaling.u0,
                u_max: dto.scaling.u_max,
            },
            output: OutputScaling {
                y_min: dto.scaling.y_min,
                y_max: dto.scaling.y_max,
            },
            et0: Et0Scaling {
                reference: match (legacy, dto.scaling.et0_ref) {
                    (true, _) => DEFAULT_ET0_REF,
                    (false, Some(r)) => r,
                    (false, None) => {
                        return Err(invalid("scaling.et0_ref is missing".into()));
                    }
                },
            },
        };
        if let Some(problem) = scaling.problem() {
            return Err(invalid(problem.to_string()));
        }
        let mut model = match &dto.architecture {
            ArchitectureDto::Lstm { hidden } => {
                if let Some(problem) = lstm_architecture_problem(hidden) {
                    return Err(invalid(problem));
                }
                Surrogate::Single(SequenceNet::new(hidden, 0))
            }
            ArchitectureDto::TwoLayer {
                sub_models,
                combiner_hidden,
            } => {
                let [h1, h2, h3] = sub_models.as_slice() else {
                    return Err(invalid(format!(
                        "3 sub-models expected, found {}",
                        sub_models.len()
                    )));
                };
                for h in [h1, h2, h3] {
                    if let Some(problem) = lstm_architecture_problem(h) {
                        return Err(invalid(problem));
                    }
                }
                if !(1..=MAX_HIDDEN).contains(combiner_hidden) {
                    return Err(invalid(format!(
                        "combiner hidden size must be in 1..={MAX_HIDDEN}, found {combiner_hidden}"
                    )));
                }
                Surrogate::TwoLayer(TwoLayerNet {
                    sub_models: [
                        SequenceNet::new(h1, 0),
                        SequenceNet::new(h2, 0),
                        SequenceNet::new(h3, 0),
                    ],
                    combiner: Mlp::new(*combiner_hidden, 0),
                })
            }
        };
        let mut weights = Vec::with_capacity(dto.weights.len());
        for (i, w) in dto.weights.iter().enumerate() {
            match w.parse::<f64>() {
                Ok(v) if v.is_finite() => weights.push(v),
                _ => return Err(invalid(format!("weight {i} is not a finite number: {w:?}"))),
            }
        }
        let set = if legacy {
            model.set_legacy_params(&weights)
        } else {
            model.set_params(&weights)
        };
        set.map_err(|e| ModelFileError::WeightsLength {
            path: path.to_path_buf(),
            expected: e.expected,
            found: e.found,
        })?;
        Ok(ModelFile {
            model,
            scaling,
            metadata: Metadata {
                soil: dto.metadata.soil,
                training_seed: dto.metadata.training_seed,
                data: dto.metadata.data,
                scores: dto.metadata.scores,
            },
        })
    }

    /// Writes the file (to a temporary sibling, then renamed into place).
    pub fn save(&self, path: &Path) -> Result<(), ModelFileError> {
        let io = |action, source| ModelFileError::Io {
            action,
            path: path.to_path_buf(),
            source,
        };
        if self.model.params().iter().any(|w| !w.is_finite()) {
            return Err(ModelFileError::Invalid {
                path: path.to_path_buf(),
                message: "non-finite weights cannot be saved".into(),
            });
        }
        let mut tmp = path.as_os_str().to_owned();
        tmp.push(".tmp");
        let tmp = PathBuf::from(tmp);
        std::fs::write(&tmp, self.to_json()).map_err(|e| io("write", e))?;
        std::fs::rename(&tmp, path).map_err(|e| io("replace", e))
    }

    /// Reads and checks a model file.
    pub fn load(path: &Path) -> Result<ModelFile, ModelFileError> {
        let text = std::fs::read_to_string(path).map_err(|source| ModelFileError::Io {
            action: "read",
            path: path.to_path_buf(),
            source,
        })?;
        ModelFile::from_json(&text, path)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::surrogate::network::tests::jiggle;

    fn sample() -> ModelFile {
        let mut model = Surrogate::TwoLayer(TwoLayerNet {
            sub_models: [
                SequenceNet::new(&[3], 1),
                SequenceNet::new(&[4], 2),
                SequenceNet::new(&[3, 2], 3),
            ],
            combiner: Mlp::new(5, 4),
        });
        let mut p = model.params();
        jiggle(&mut p, 6, 0.1);
        model.set_params(&p).unwrap();
        let mut metadata = Metadata {
            soil: "loam".into(),
            training_seed: 42,
            ..Metadata::default()
        };
        metadata.data.insert("samples".into(), "3000".into());
        metadata.scores.insert("nrmse_20".into(), 0.0123);
        ModelFile {
            model,
            scaling: Scaling::default(),
            metadata,
        }
    }

    fn predictions_at(file: &ModelFile, et0: f64) -> Vec<f64> {
        let past_y: Vec<f64> = (0..20).map(|i| 0.2 + 0.004 * i as f64).collect();
        let past = crate::surrogate::Past {
            u: &[2e-7; 20],
            y: &past_y,
            et0: &[et0; 20],
        };
        let future_u = [1e-6, 0.0, 5e-6, 3e-7, 0.0];
        let mut out = vec![0.0; 5];
        file.predictor()
            .predict(past, &future_u, &[et0; 5], 0.0, &mut out)
            .unwrap();
        out
    }

    fn predictions(file: &ModelFile) -> Vec<f64> {
        predictions_at(file, 5e-8)
    }

    #[test]
    fn a_version_1_file_loads_blind_to_et0() {
        let file = sample();
        // the version-1 form: no et0_ref, and no input weights of ē
        let mut dto: serde_json::Value = serde_json::from_str(&file.to_json()).unwrap();
        dto["version"] = 1.into();
        dto["scaling"].as_object_mut().unwrap().remove("et0_ref");
        let Surrogate::TwoLayer(m) = &file.model else {
            unreachable!()
        };
        let mut legacy = Vec::new();
        for net in &m.sub_models {
            let row = 4 * net.hidden_sizes()[0];
            let p = net.params();
            legacy.extend_from_slice(&p[..2 * row]);
            legacy.extend_from_slice(&p[3 * row..]);
        }
        legacy.extend_from_slice(m.combiner.params());
        dto["weights"] = legacy.iter().map(|w| w.to_string()).collect();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("old.json");
        std::fs::write(&path, dto.to_string()).unwrap();
        let old = ModelFile::load(&path).unwrap();
        assert_eq!(old.scaling, Scaling::default());
        // blind to ET0: the same prediction at any ET0, and it differs from
        // the version-2 model's, which sees it
        let dry = predictions_at(&old, 0.0);
        assert_eq!(predictions_at(&old, 9e-8), dry);
        assert_ne!(predictions_at(&file, 9e-8), predictions_at(&file, 0.0));
        // saved again, it is a version-2 file that predicts the same
        old.save(&path).unwrap();
        assert!(
            std::fs::read_to_string(&path)
                .unwrap()
                .contains("\"version\": 2")
        );
        assert_eq!(predictions_at(&ModelFile::load(&path).unwrap(), 0.0), dry);
        // a version-2 file must give et0_ref
        let mut dto: serde_json::Value = serde_json::from_str(&file.to_json()).unwrap();
        dto["scaling"].as_object_mut().unwrap().remove("et0_ref");
        std::fs::write(&path, dto.to_string()).unwrap();
        assert!(matches!(
            ModelFile::load(&path),
            Err(ModelFileError::Invalid { .. })
        ));
    }

    #[test]
    fn round_trip_keeps_predictions_and_metadata() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("model.json");
        let file = sample();
        file.save(&path).unwrap();
        let back = ModelFile::load(&path).unwrap();
        assert_eq!(back, file);
        assert_eq!(predictions(&back), predictions(&file));
        assert_eq!(back.metadata.scores["nrmse_20"], 0.0123);
        // single LSTM too
        let single = ModelFile {
            model: Surrogate::Single(SequenceNet::new(&[3, 3], 9)),
            ..sample()
        };
        single.save(&path).unwrap();
        assert_eq!(ModelFile::load(&path).unwrap(), single);
    }

    #[test]
    fn bad_files_give_the_matching_error() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("model.json");
        let text = sample().to_json();

        std::fs::write(&path, &text[..text.len() / 2]).unwrap();
        match ModelFile::load(&path) {
            Err(ModelFileError::Malformed { path: p, line, .. }) => {
                assert_eq!(p, path);
                assert!(line > 1);
            }
            other => panic!("{other:?}"),
        }

        let v3 = text.replacen("\"version\": 2", "\"version\": 3", 1);
        assert_ne!(v3, text);
        std::fs::write(&path, v3).unwrap();
        match ModelFile::load(&path) {
            Err(ModelFileError::WrongFormat {
                found_format,
                found_version,
                ..
            }) => {
                assert_eq!((found_format.as_str(), found_version), (FORMAT, 3));
            }
            other => panic!("{other:?}"),
        }

        let mut dto: serde_json::Value = serde_json::from_str(&text).unwrap();
        let n = sample().model.n_params();
        dto["weights"].as_array_mut().unwrap().pop();
        std::fs::write(&path, dto.to_string()).unwrap();
        match ModelFile::load(&path) {
            Err(ModelFileError::WeightsLength {
                expected, found, ..
            }) => assert_eq!((expected, found), (n, n - 1)),
            other => panic!("{other:?}"),
        }

        dto["architecture"]["sub_models"] = serde_json::json!([[3], [4]]);
        std::fs::write(&path, dto.to_string()).unwrap();
        assert!(matches!(
            ModelFile::load(&path),
            Err(ModelFileError::Invalid { .. })
        ));

        match ModelFile::load(&dir.path().join("missing.json")) {
            Err(ModelFileError::Io { action, .. }) => assert_eq!(action, "read"),
            other => panic!("{other:?}"),
        }
    }
}
