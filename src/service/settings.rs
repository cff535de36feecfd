//! The daemon's settings: embedded defaults, then a TOML file, then
//! environment variables (`ROOTZONE_…`, nested keys with `__`), validated
//! once at start.

use std::net::SocketAddr;

use super::wire::{check_range, check_time};
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
    "limits.max_catch_up_s",
    "limits.late_window_s",
    "limits.training_jobs",
    "training.nrmse_gate",
    "training.max_epochs",
    "training.impulse_samples",
    "training.sub_model_samples",
    "training.validation_samples",
    "training.threads",
    "log.format",
    "log.level",
    "webhooks.allow_link_local",
    "forecasts.poll_interval_s",
    "forecasts.retry_s",
    "forecasts.max_backoff_s",
    "forecasts.stale_after_s",
    "forecasts.timeout_s",
    "forecasts.contact",
    "forecasts.location_decimals",
    "mqtt.url",
    "mqtt.client_id",
    "mqtt.username",
    "mqtt.password",
    "mqtt.topic_prefix",
    "mqtt.discovery",
    "mqtt.discovery_prefix",
    "mqtt.keep_alive_s",
    "mqtt.reconnect_min_s",
    "mqtt.reconnect_max_s",
    "mqtt.max_payload_bytes",
    "mqtt.queue",
    "mqtt.batch_max",
    "storage.url",
    "replicas.id",
    "replicas.lease_s",
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
    #[serde(default)]
    pub log: LogSettings,
    #[serde(default)]
    pub webhooks: WebhookSettings,
    /// Per-field surrogate training jobs (`service::training`).
    #[serde(default)]
    pub training: super::training::TrainingSettings,
    /// Polled forecast providers (`ROOTZONE_FORECASTS__…`).
    #[serde(default)]
    pub forecasts: crate::adapters::forecast::ForecastSettings,
    /// MQTT with Home Assistant discovery (`ROOTZONE_MQTT__…`); off unless
    /// `mqtt.url` is set.
    #[serde(default)]
    pub mqtt: crate::adapters::mqtt::MqttSettings,
    /// Where the data lives (`ROOTZONE_STORAGE__URL`); unset: the SQLite
    /// file in `data_dir`.
    #[serde(default)]
    pub storage: StorageSettings,
    /// Several replicas on one PostgreSQL (`ROOTZONE_REPLICAS__…`): this
    /// replica's id and the fields' lease.
    #[serde(default)]
    pub replicas: super::replicas::ReplicaSettings,
    /// Fields created at first start (when the database holds none).
    pub fields: Vec<FieldSpec>,
}

/// `[storage]`: the database.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StorageSettings {
    /// `postgres://user:password@host:port/database` for a PostgreSQL
    /// server (several replicas may share it), or `sqlite:<folder>`; unset:
    /// `sqlite:` + `data_dir`.
    pub url: Option<String>,
}

impl Settings {
    /// The database these settings name.
    pub fn storage_location(&self) -> Result<crate::store::Location, SettingsError> {
        match &self.storage.url {
            None => Ok(crate::store::Location::Sqlite(self.data_dir.clone())),
            Some(url) => crate::store::Location::parse(url)
                .map_err(|e| SettingsError(format!("storage.url: {e}"))),
        }
    }
}

/// The clock all of the daemon runs on.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ClockSettings {
    /// Simulated seconds per real second, in (0, 100000]: 1 is real time,
    /// 720 turns 2 h into 10 s (`ROOTZONE_CLOCK__SPEEDUP`; `1e3` is fine).
    #[serde(deserialize_with = "lenient_f64")]
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
    /// How far in the future (clock time) a timestamp may lie [s], in
    /// [0, 86400].
    #[serde(deserialize_with = "lenient_f64")]
    pub max_future_skew_s: f64,
    /// Threads of the blocking pool that runs control cycles and
    /// simulations, 1 … 64; as many low-priority threads bring deferred
    /// state estimates up to date (`service::deferred`).
    pub worker_threads: usize,
    /// Longest span [s of clock time] a simulated plant replays after a
    /// stop (or from a `simulation.start` in the past), in [0, 30 days];
    /// the rest is skipped with a warning.
    #[serde(default = "default_catch_up", deserialize_with = "lenient_f64")]
    pub max_catch_up_s: f64,
    /// How late [s of clock time] a measurement may arrive and still be
    /// assimilated by the state estimate, in [0, 86400]: each cycle
    /// re-runs the estimator from its settled state this far back, so
    /// readings that arrive late or out of order within it count.
    #[serde(default = "default_late_window", deserialize_with = "lenient_f64")]
    pub late_window_s: f64,
    /// Surrogate training jobs running at once, 1 … 8 (default 1; more
    /// wait, queued).
    #[serde(default = "super::training::default_training_jobs")]
    pub training_jobs: usize,
}

/// The default late-reading window: 1 hour.
pub fn default_late_window() -> f64 {
    3600.0
}

/// The default catch-up span: 2 days.
pub fn default_catch_up() -> f64 {
    2.0 * 86_400.0
}

/// Logging: human-readable lines or JSON, and the level (`RUST_LOG`, when
/// set, overrides `level`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LogSettings {
    /// `text` or `json` (`ROOTZONE_LOG__FORMAT`).
    pub format: LogFormat,
    /// A tracing filter, e.g. `info` or `rootzone=debug,tower_http=info`
    /// (`ROOTZONE_LOG__LEVEL`).
    pub level: String,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LogFormat {
    #[default]
    Text,
    Json,
}

impl Default for LogSettings {
    fn default() -> Self {
        LogSettings {
            format: LogFormat::Text,
            level: "info".into(),
        }
    }
}

/// Where webhooks may go.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct WebhookSettings {
    /// Allow targets at link-local and cloud-metadata addresses
    /// (`ROOTZONE_WEBHOOKS__ALLOW_LINK_LOCAL`; off by default).
    pub allow_link_local: bool,
}

/// A number given as a number or as text (`1e3`, as environment variables
/// carry it).
pub fn lenient_f64<'de, D: serde::Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    #[derive(Deserialize)]
    #[serde(untagged)]
    enum Number {
        Value(f64),
        Text(String),
    }
    match Number::deserialize(d)? {
        Number::Value(v) => Ok(v),
        Number::Text(t) => t
            .trim()
            .parse()
            .map_err(|_| serde::de::Error::custom(format!("'{t}' is not a number"))),
    }
}

/// Largest clock speedup.
pub const MAX_SPEEDUP: f64 = 100_000.0;

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
                max_catch_up_s: default_catch_up(),
                late_window_s: default_late_window(),
                training_jobs: super::training::default_training_jobs(),
            },
            log: LogSettings::default(),
            webhooks: WebhookSettings::default(),
            training: Default::default(),
            forecasts: Default::default(),
            mqtt: Default::default(),
            storage: Default::default(),
            replicas: Default::default(),
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
        listen_addresses("listen", &self.listen).map_err(SettingsError)?;
        self.clock.validate().map_err(SettingsError)?;
        let l = &self.limits;
        if !(1..=1_000_000).contains(&l.max_batch) {
            return bad(format!(
                "limits.max_batch = {} must lie in [1, 1000000]",
                l.max_batch
            ));
        }
        if !(1..=64).contains(&l.worker_threads) {
            return bad(format!(
                "limits.worker_threads = {} must lie in [1, 64]",
                l.worker_threads
            ));
        }
        check_range(
            "limits.max_future_skew_s",
            l.max_future_skew_s,
            (0.0, 86_400.0),
        )
        .map_err(SettingsError)?;
        check_range(
            "limits.max_catch_up_s",
            l.max_catch_up_s,
            (0.0, 30.0 * 86_400.0),
        )
        .map_err(SettingsError)?;
        check_range("limits.late_window_s", l.late_window_s, (0.0, 86_400.0))
            .map_err(SettingsError)?;
        if !(1..=8).contains(&l.training_jobs) {
            return bad(format!(
                "limits.training_jobs = {} must lie in [1, 8]",
                l.training_jobs
            ));
        }
        self.training.validate().map_err(SettingsError)?;
        self.forecasts.validate().map_err(SettingsError)?;
        self.mqtt.validate().map_err(SettingsError)?;
        self.storage_location()?;
        self.replicas.validate().map_err(SettingsError)?;
        if tracing_subscriber::EnvFilter::try_new(&self.log.level).is_err() {
            return bad(format!(
                "log.level = '{}' is not a tracing filter (e.g. info, debug, rootzone=debug)",
                self.log.level
            ));
        }
        if let Some(token) = &self.api_token
            && !(8..=200).contains(&token.trim().len())
        {
            return bad("api_token must have 8 to 200 characters".into());
        }
        let mut names = std::collections::HashSet::new();
        for (i, field) in self.fields.iter().enumerate() {
            field
                .validate()
                .map_err(|m| SettingsError(format!("fields[{i}]: {m}")))?;
            if !names.insert(field.name.as_str()) {
                return bad(format!(
                    "fields[{i}]: the name '{}' is used twice; names are unique",
                    field.name
                ));
            }
        }
        Ok(())
    }
}

impl ClockSettings {
    /// Speedup in (0, 100000]; an epoch, and the clock it gives now, in the
    /// years 2000 … 2199.
    pub fn validate(&self) -> Result<(), String> {
        let s = self.speedup;
        if !(s.is_finite() && s > 0.0 && s <= MAX_SPEEDUP) {
            return Err(format!(
                "clock.speedup = {s} must lie in (0, {MAX_SPEEDUP}]"
            ));
        }
        if let Some(epoch) = self.epoch {
            check_time("clock.epoch", epoch)?;
            super::clock::Clock::anchored(epoch, s)
                .map_err(|e| format!("clock.epoch with clock.speedup {s}: {e}"))?;
        }
        Ok(())
    }
}

/// The addresses `host:port` stands for (a name such as `localhost:8080`,
/// or an IP address), or a message naming `key`.
pub fn listen_addresses(key: &str, text: &str) -> Result<Vec<SocketAddr>, String> {
    use std::net::ToSocketAddrs;
    let hint = format!("{key}: '{text}' is not host:port (e.g. 127.0.0.1:8080 or localhost:8080)");
    let Some((_, port)) = text.rsplit_once(':') else {
        return Err(hint);
    };
    if port.parse::<u16>().is_err() {
        return Err(hint);
    }
    let addrs: Vec<SocketAddr> = text
        .to_socket_addrs()
        .map_err(|e| format!("{key}: cannot resolve '{text}': {e}"))?
        .collect();
    if addrs.is_empty() {
        return Err(format!("{key}: '{text}' resolves to no address"));
    }
    Ok(addrs)
}
