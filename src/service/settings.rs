//! The daemon's settings: embedded defaults, then a TOML file, then
//! environment variables (`ROOTZONE_…`, nested keys with `__`), validated
//! once at start.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};

use figment::Figment;
use figment::providers::{Env, Format, Serialized, Toml};
use serde::{Deserialize, Serialize};

use super::wire::FieldSpec;

/// The keys the environment may set (`ROOTZONE_` + the key in capitals,
/// `.` written `__`); other `ROOTZONE_…` variables are not the controller's.
pub const ENV_KEYS: &[&str] = &[
    "listen",
    "data_dir",
    "api_token",
    "models_dir",
    "clock.speedup",
    "clock.epoch",
    "limits.max_batch",
    "limits.max_future_skew_s",
    "limits.worker_threads",
];

/// The environment variable of a settings key.
pub fn env_name(key: &str) -> String {
    format!("ROOTZONE_{}", key.replace('.', "__").to_uppercase())
}

/// Everything `rootzone serve` needs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Settings {
    /// Address and port of the HTTP API (`ROOTZONE_LISTEN`).
    pub listen: String,
    /// Folder of the database and the generated API token (`ROOTZONE_DATA_DIR`).
    pub data_dir: PathBuf,
    /// Bearer token for mutating requests (`ROOTZONE_API_TOKEN`); generated
    /// into `data_dir/api-token` (mode 0600) at first start when unset.
    pub api_token: Option<String>,
    /// Folder of the surrogate model files (`two-layer.json`,
    /// `single-lstm.json`); unset: the shipped models built into the binary.
    pub models_dir: Option<PathBuf>,
    pub clock: ClockSettings,
    pub limits: Limits,
    /// Fields created at first start (when the database holds none).
    pub fields: Vec<FieldSpec>,
}

/// The clock all of the daemon runs on.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ClockSettings {
    /// Simulated seconds per real second: 1 is real time, 720 turns 2 h
    /// into 10 s (`ROOTZONE_CLOCK__SPEEDUP`).
    pub speedup: f64,
    /// A shared epoch (RFC 3339, `ROOTZONE_CLOCK__EPOCH`): clock time is then
    /// epoch + (real time − epoch) × speedup, the same in every process
    /// configured alike (the controller and a field simulator). Unset: the
    /// clock starts at the real time (or, accelerated, where it stopped).
    #[serde(default)]
    pub epoch: Option<chrono::DateTime<chrono::Utc>>,
}

/// Limits on input.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Limits {
    /// Largest number of measurements in one request.
    pub max_batch: usize,
    /// How far in the future (clock time) a timestamp may lie [s].
    pub max_future_skew_s: f64,
    /// Threads of the blocking pool that runs control cycles and simulations.
    pub worker_threads: usize,
}

impl Default for Settings {
    /// Storage under `./data`, the API on 127.0.0.1:8080, real time, one
    /// simulated sandy-loam field with the shipped two-layer model.
    fn default() -> Self {
        Settings {
            listen: "127.0.0.1:8080".into(),
            data_dir: PathBuf::from("data"),
            api_token: None,
            models_dir: None,
            clock: ClockSettings {
                speedup: 1.0,
                epoch: None,
            },
            limits: Limits {
                max_batch: 10_000,
                max_future_skew_s: 300.0,
                worker_threads: 2,
            },
            fields: vec![FieldSpec::demo()],
        }
    }
}

/// The settings could not be read or are not valid.
#[derive(Debug, thiserror::Error)]
#[error("configuration: {0}")]
pub struct SettingsError(pub String);

impl Settings {
    /// Defaults, then `file` (if given), then the environment.
    pub fn load(file: Option<&Path>) -> Result<Settings, SettingsError> {
        let mut figment = Figment::from(Serialized::defaults(Settings::default()));
        if let Some(path) = file {
            if !path.is_file() {
                return Err(SettingsError(format!("{}: no such file", path.display())));
            }
            figment = figment.merge(Toml::file(path));
        }
        let settings: Settings = figment
            .merge(Env::prefixed("ROOTZONE_").split("__").only(ENV_KEYS))
            .extract()
            .map_err(|e| SettingsError(e.to_string()))?;
        settings.validate()?;
        Ok(settings)
    }

    pub fn validate(&self) -> Result<(), SettingsError> {
        let bad = |m: String| Err(SettingsError(m));
        if self.listen.parse::<SocketAddr>().is_err() {
            return bad(format!(
                "listen: '{}' is not an address:port (e.g. 127.0.0.1:8080)",
                self.listen
            ));
        }
        if !(self.clock.speedup.is_finite() && self.clock.speedup > 0.0) {
            return bad(format!(
                "clock.speedup must be > 0, got {}",
                self.clock.speedup
            ));
        }
        if self.limits.max_batch == 0 || self.limits.worker_threads == 0 {
            return bad("limits.max_batch and limits.worker_threads must be ≥ 1".into());
        }
        if !(self.limits.max_future_skew_s.is_finite() && self.limits.max_future_skew_s >= 0.0) {
            return bad("limits.max_future_skew_s must be ≥ 0".into());
        }
        if let Some(token) = &self.api_token
            && token.trim().len() < 8
        {
            return bad("api_token must have at least 8 characters".into());
        }
        for (i, field) in self.fields.iter().enumerate() {
            field
                .validate()
                .map_err(|m| SettingsError(format!("fields[{i}]: {m}")))?;
        }
        Ok(())
    }
}
