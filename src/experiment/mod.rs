//! The paper's experiments: tables, figures and reports.

pub mod plot;
pub mod surrogates;

use std::path::{Path, PathBuf};
use std::str::FromStr;

use crate::surrogate::ModelFileError;
use crate::surrogate::dataset::DatasetError;

/// Which experiment to run.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ExperimentId {
    E1,
    E2,
    E3,
}

impl FromStr for ExperimentId {
    type Err = ExperimentError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.to_ascii_lowercase().as_str() {
            "e1" => Ok(ExperimentId::E1),
            "e2" => Ok(ExperimentId::E2),
            "e3" => Ok(ExperimentId::E3),
            other => Err(ExperimentError::Input(format!(
                "unknown experiment '{other}' (expected e1, e2 or e3)"
            ))),
        }
    }
}

/// Where an experiment reads models and writes its results.
#[derive(Debug, Clone, PartialEq)]
pub struct ExperimentOptions {
    pub models: PathBuf,
    pub out: PathBuf,
    /// Seed of the fresh validation data.
    pub seed: u64,
    pub cache: PathBuf,
    /// Samples per validation set.
    pub samples: usize,
}

/// An experiment could not run.
#[derive(Debug, thiserror::Error)]
pub enum ExperimentError {
    #[error("{0}")]
    Input(String),
    #[error(transparent)]
    ModelFile(#[from] ModelFileError),
    #[error(transparent)]
    Data(#[from] DatasetError),
    #[error(transparent)]
    Plot(#[from] plot::PlotError),
    #[error("cannot write {path}: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
}

/// Writes `text` to `path` (creating its folder); returns the path.
pub(crate) fn write_file(path: &Path, text: &str) -> Result<PathBuf, ExperimentError> {
    let io = |source| ExperimentError::Io {
        path: path.display().to_string(),
        source,
    };
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).map_err(io)?;
    }
    std::fs::write(path, text).map_err(io)?;
    Ok(path.to_path_buf())
}

/// Runs experiment `id`; returns the files written.
pub fn run_experiment(
    id: ExperimentId,
    options: &ExperimentOptions,
) -> Result<Vec<PathBuf>, ExperimentError> {
    if options.samples < 200 {
        return Err(ExperimentError::Input(format!(
            "--samples must be at least 200, got {}",
            options.samples
        )));
    }
    std::fs::create_dir_all(&options.out).map_err(|source| ExperimentError::Io {
        path: options.out.display().to_string(),
        source,
    })?;
    match id {
        ExperimentId::E1 => surrogates::e1(options),
        ExperimentId::E2 => surrogates::e2(options),
        ExperimentId::E3 => surrogates::e3(options),
    }
}
