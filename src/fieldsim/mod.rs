//! `rootzone field-sim`: a separate process that simulates fields (the
//! Richards plant of MODEL.md §1–2) on the shared clock, registers them with
//! a controller, sends it noisy measurements and forecasts over HTTP, and
//! applies the setpoints the controller's webhook actuator POSTs back.
//!
//! Measurements wait in a bounded on-disk buffer until the controller
//! acknowledges them (the controller stores a resent (time, sensor) once), so
//! neither side being down loses what was measured.

use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use axum::Router;
use axum::extract::{Path as UrlPath, State};
use axum::http::StatusCode;
use axum::response::IntoResponse;
use axum::routing::post;
use chrono::{DateTime, TimeDelta, Utc};
use figment::Figment;
use figment::providers::{Env, Format, Serialized, Toml};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::service::clock::{Clock, next_boundary};
use crate::service::settings::ClockSettings;
use crate::service::webhook::{
    DELIVERY_HEADER, ReplayGuard, SIGNATURE_HEADER, TIMESTAMP_HEADER, verify,
};
use crate::service::wire::{Actuator, FieldSpec, Measurement, Setpoint, SimulationSpec};
use crate::sim::{PlantState, SimulatedPlant, midnight, scenario_forecast};

/// The keys the environment may set (see [`crate::service::settings::env_name`]).
pub const ENV_KEYS: &[&str] = &[
    "controller",
    "api_token",
    "sim_listen",
    "public_url",
    "sim_data_dir",
    "clock.speedup",
    "clock.epoch",
    "max_buffer",
    "sim_token",
    "max_catch_up_s",
];

/// Settings of the field simulator: defaults, a TOML file, then
/// `ROOTZONE_…` environment variables (the same names as the controller's
/// for the shared keys: `ROOTZONE_API_TOKEN`, `ROOTZONE_CLOCK__SPEEDUP`,
/// `ROOTZONE_CLOCK__EPOCH`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FieldSimSettings {
    /// Base URL of the controller (`--controller`, `ROOTZONE_CONTROLLER`).
    pub controller: String,
    /// The controller's API token.
    pub api_token: Option<String>,
    /// Address of the setpoint endpoint (`ROOTZONE_SIM_LISTEN`).
    pub sim_listen: String,
    /// The URL the controller reaches that endpoint at (default:
    /// `http://<sim_listen>`; in Docker, the service name).
    pub public_url: Option<String>,
    /// Folder of the measurement buffer and the plants' states.
    pub sim_data_dir: PathBuf,
    pub clock: ClockSettings,
    /// Largest number of buffered measurements per field (the oldest go).
    pub max_buffer: usize,
    /// The simulator's own token (`ROOTZONE_SIM_TOKEN`): an operator's
    /// `Authorization: Bearer` for its setpoint endpoint. Unset: generated
    /// into `sim_data_dir/sim-token` (0600). The controller authenticates
    /// instead by the HMAC signature of its webhook.
    #[serde(default)]
    pub sim_token: Option<String>,
    /// Longest span [s of clock time] a plant replays after a stop.
    #[serde(
        default = "crate::service::settings::default_catch_up",
        deserialize_with = "crate::service::settings::lenient_f64"
    )]
    pub max_catch_up_s: f64,
    /// The simulated fields (each with a `simulation` section).
    pub fields: Vec<FieldSpec>,
}

impl Default for FieldSimSettings {
    fn default() -> Self {
        FieldSimSettings {
            controller: "http://127.0.0.1:8080".into(),
            api_token: None,
            sim_listen: "127.0.0.1:9090".into(),
            public_url: None,
            sim_data_dir: PathBuf::from("field-data"),
            clock: ClockSettings {
                speedup: 1.0,
                epoch: None,
            },
            max_buffer: 100_000,
            sim_token: None,
            max_catch_up_s: crate::service::settings::default_catch_up(),
            fields: vec![FieldSpec {
                name: "sim-field".into(),
                actuator: Actuator::None,
                simulation: Some(SimulationSpec::default()),
                ..FieldSpec::demo()
            }],
        }
    }
}

/// The simulator could not run.
#[derive(Debug, thiserror::Error)]
#[error("field-sim: {0}")]
pub struct FieldSimError(pub String);

impl FieldSimSettings {
    pub fn load(file: Option<&Path>, controller: Option<&str>) -> Result<Self, FieldSimError> {
        let mut figment = Figment::from(Serialized::defaults(FieldSimSettings::default()));
        if let Some(path) = file {
            if !path.is_file() {
                return Err(FieldSimError(format!("{}: no such file", path.display())));
            }
            figment = figment.merge(Toml::file(path));
        }
        let mut s: FieldSimSettings = figment
            .merge(Env::prefixed("ROOTZONE_").split("__").only(ENV_KEYS))
            .extract()
            .map_err(|e| FieldSimError(format!("configuration: {e}")))?;
        if let Some(url) = controller {
            s.controller = url.to_string();
        }
        s.controller = s.controller.trim_end_matches('/').to_string();
        if !(s.controller.starts_with("http://") || s.controller.starts_with("https://")) {
            return Err(FieldSimError(format!(
                "--controller must be an http(s) URL, got '{}'",
                s.controller
            )));
        }
        if s.fields.is_empty() {
            return Err(FieldSimError("no fields to simulate".into()));
        }
        let bad = |m: String| Err(FieldSimError(m));
        crate::service::settings::listen_addresses("sim_listen", &s.sim_listen)
            .map_err(FieldSimError)?;
        s.clock.validate().map_err(FieldSimError)?;
        if !(1..=10_000_000).contains(&s.max_buffer) {
            return bad(format!(
                "max_buffer = {} must lie in [1, 10000000]",
                s.max_buffer
            ));
        }
        crate::service::wire::check_range(
            "max_catch_up_s",
            s.max_catch_up_s,
            (0.0, 30.0 * 86_400.0),
        )
        .map_err(FieldSimError)?;
        if let Some(t) = &s.sim_token
            && !(8..=200).contains(&t.trim().len())
        {
            return bad("sim_token must have 8 to 200 characters".into());
        }
        let mut names = std::collections::HashSet::new();
        for (i, f) in s.fields.iter().enumerate() {
            let Some(sim) = f.simulation.clone() else {
                return bad(format!(
                    "fields[{i}] '{}' needs a 'simulation' section",
                    f.name
                ));
            };
            let plain = FieldSpec {
                actuator: Actuator::None,
                simulation: None,
                ..f.clone()
            };
            plain
                .validate()
                .and_then(|()| sim.validate(f.control_period_s))
                .map_err(|e| FieldSimError(format!("fields[{i}]: {e}")))?;
            if !names.insert(f.name.clone()) {
                return bad(format!("fields[{i}]: the name '{}' is used twice", f.name));
            }
        }
        Ok(s)
    }
}

/// What the simulator keeps of one field.
struct SimField {
    name: String,
    spec: FieldSpec,
    sim: SimulationSpec,
    /// The controller's id, once registered.
    id: Option<i64>,
    plant: SimulatedPlant,
    /// Measurements not yet acknowledged by the controller.
    buffer: VecDeque<Measurement>,
    /// The latest setpoint received: (rate, valid from, valid until).
    setpoint: Option<(f64, DateTime<Utc>, DateTime<Utc>)>,
    last_forecast: Option<DateTime<Utc>>,
}

/// Stored per field: plant and buffer.
#[derive(Serialize, Deserialize)]
struct Saved {
    time: DateTime<Utc>,
    steps: usize,
    heads: Vec<f64>,
    amounts: [f64; 4],
    buffer: Vec<Measurement>,
    setpoint: Option<(f64, DateTime<Utc>, DateTime<Utc>)>,
    /// Whether the initial state was read (files of older versions: not
    /// known; reading it again is harmless, the controller keeps one
    /// measurement per time and sensor).
    #[serde(default)]
    started: bool,
    /// The scenario's day zero (files of older versions: the midnight
    /// before `time`).
    #[serde(default)]
    day_zero: Option<DateTime<Utc>>,
}

struct Shared {
    fields: Mutex<Vec<SimField>>,
    settings: FieldSimSettings,
    /// The operator's token for the setpoint endpoint.
    token: String,
    /// The secret the controller signs this simulator's setpoints with.
    secret: String,
    replays: Mutex<ReplayGuard>,
}

fn saved_path(dir: &Path, name: &str) -> PathBuf {
    let safe: String = name
        .chars()
        .map(|c| if c.is_ascii_alphanumeric() { c } else { '_' })
        .collect();
    dir.join(format!("field-{safe}.json"))
}

impl SimField {
    fn save(&self, dir: &Path) -> std::io::Result<()> {
        let state = self.plant.state();
        let saved = Saved {
            time: state.time,
            steps: state.steps,
            heads: state.heads,
            amounts: state.amounts,
            buffer: self.buffer.iter().cloned().collect(),
            setpoint: self.setpoint,
            started: self.plant.started(),
            day_zero: Some(self.plant.day_zero()),
        };
        let path = saved_path(dir, &self.name);
        let tmp = path.with_extension("tmp");
        std::fs::write(&tmp, serde_json::to_vec(&saved).unwrap_or_default())?;
        std::fs::rename(tmp, path)
    }

    /// Advances the plant to `now`, buffering every sensor's reading per
    /// interval (the true θ is not sent: the controller sees what a real
    /// field gives).
    fn advance(
        &mut self,
        now: DateTime<Utc>,
        max_buffer: usize,
        max_catch_up_s: f64,
    ) -> Result<bool, String> {
        let setpoint = self.setpoint;
        let advance = self.plant.advance(now, max_catch_up_s, |t| {
            Ok::<_, String>(match setpoint {
                Some((rate, from, until)) if from <= t && t < until => (rate, until),
                Some((_, from, _)) if t < from => (0.0, from),
                _ => (0.0, t),
            })
        })?;
        if let Some((from, to)) = advance.skipped {
            tracing::warn!(field = %self.name, from = %from, to = %to,
                "plant far behind the clock: skipped to replay at most {max_catch_up_s} s (max_catch_up_s)");
        }
        let stepped = !advance.readings.is_empty();
        for m in advance.readings {
            self.buffer.push_back(Measurement {
                true_theta: None,
                ..m
            });
        }
        while self.buffer.len() > max_buffer {
            self.buffer.pop_front();
        }
        match advance.failure {
            Some(e) => Err(e.to_string()),
            None => Ok(stepped),
        }
    }
}

/// Runs the simulator until `shutdown` resolves.
pub async fn run(
    settings: FieldSimSettings,
    shutdown: impl std::future::Future<Output = ()> + Send + 'static,
) -> Result<(), FieldSimError> {
    let clock = match settings.clock.epoch {
        Some(epoch) => Clock::anchored(epoch, settings.clock.speedup).map_err(FieldSimError)?,
        None => Clock::new(Utc::now(), settings.clock.speedup),
    };
    let listener = tokio::net::TcpListener::bind(&settings.sim_listen)
        .await
        .map_err(|e| FieldSimError(format!("cannot listen on {}: {e}", settings.sim_listen)))?;
    let local = listener
        .local_addr()
        .map_err(|e| FieldSimError(e.to_string()))?;
    let public = settings
        .public_url
        .clone()
        .unwrap_or_else(|| format!("http://{local}"));
    std::fs::create_dir_all(&settings.sim_data_dir).map_err(|e| {
        FieldSimError(format!(
            "cannot create {}: {e}",
            settings.sim_data_dir.display()
        ))
    })?;
    let token = match &settings.sim_token {
        Some(t) => t.trim().to_string(),
        None => private_secret(&settings.sim_data_dir, "sim-token")?,
    };
    let secret = private_secret(&settings.sim_data_dir, "webhook-secret")?;
    let mut fields = Vec::new();
    for spec in &settings.fields {
        let sim = spec.simulation.clone().unwrap_or_default();
        let now = clock.now();
        let start = sim.start.unwrap_or_else(|| {
            crate::service::clock::boundary_at_or_before(now, sim.measurement_interval_s)
        });
        let mut buffer = VecDeque::new();
        let mut setpoint = None;
        let saved = std::fs::read_to_string(saved_path(&settings.sim_data_dir, &spec.name))
            .ok()
            .and_then(|text| serde_json::from_str::<Saved>(&text).ok());
        let plant = match saved {
            Some(saved) => {
                let state = PlantState {
                    time: saved.time,
                    steps: saved.steps,
                    heads: saved.heads,
                    amounts: saved.amounts,
                    theta: 0.0,
                    theta_profile: Vec::new(),
                    infiltration_m: 0.0,
                    drainage_m: 0.0,
                    uptake_m: 0.0,
                    runoff_m: 0.0,
                };
                buffer = saved.buffer.into();
                setpoint = saved.setpoint;
                let day_zero = saved.day_zero.unwrap_or_else(|| midnight(saved.time));
                SimulatedPlant::new(spec, sim.clone(), start, Some(&state))
                    .map_err(FieldSimError)?
                    .resume_at(day_zero, saved.started)
            }
            None => SimulatedPlant::new(spec, sim.clone(), start, None).map_err(FieldSimError)?,
        };
        fields.push(SimField {
            name: spec.name.clone(),
            spec: FieldSpec {
                actuator: Actuator::Webhook {
                    url: format!("{public}/fields/{}/setpoint", encode(&spec.name)),
                    secret: Some(secret.clone()),
                },
                simulation: None,
                ..spec.clone()
            },
            sim,
            id: None,
            plant,
            buffer,
            setpoint,
            last_forecast: None,
        });
    }
    let shared = Arc::new(Shared {
        fields: Mutex::new(fields),
        settings: settings.clone(),
        token,
        secret,
        replays: Mutex::new(ReplayGuard::default()),
    });
    crate::service::install_tls();
    let http = reqwest::Client::builder()
        .timeout(Duration::from_secs(10))
        .build()
        .map_err(|e| FieldSimError(e.to_string()))?;
    let router = Router::new()
        .route("/fields/{name}/setpoint", post(receive_setpoint))
        .route("/healthz", axum::routing::get(|| async { "ok\n" }))
        .with_state(shared.clone());
    let cancel = tokio_util::sync::CancellationToken::new();
    let stop = cancel.clone();
    let server = tokio::spawn(async move {
        let _ = axum::serve(listener, router)
            .with_graceful_shutdown(async move { stop.cancelled().await })
            .await;
    });
    {
        use std::io::Write;
        let mut out = std::io::stdout();
        let token_source = if settings.sim_token.is_some() {
            "from the configuration".to_string()
        } else {
            format!("in {}", settings.sim_data_dir.join("sim-token").display())
        };
        let _ = writeln!(
            out,
            "rootzone field-sim: setpoints at {public}/fields/<name>/setpoint (signed by the \
             controller, or with the simulator's token {token_source}), controller {}",
            settings.controller
        );
        let _ = out.flush();
    }
    let work = work_loop(shared.clone(), clock, http);
    let result = tokio::select! {
        r = work => r,
        _ = shutdown => Ok(()),
    };
    cancel.cancel();
    let _ = server.await;
    let fields = shared.fields.lock().unwrap_or_else(|p| p.into_inner());
    for f in fields.iter() {
        let _ = f.save(&settings.sim_data_dir);
    }
    result
}

fn encode(name: &str) -> String {
    name.bytes()
        .map(|b| {
            if b.is_ascii_alphanumeric() || b == b'-' || b == b'_' {
                (b as char).to_string()
            } else {
                format!("%{b:02X}")
            }
        })
        .collect()
}

/// A refusal of the setpoint endpoint, as problem+json.
fn refuse(status: StatusCode, detail: impl Into<String>) -> axum::response::Response {
    crate::service::api::ApiError::new(status, detail).into_response()
}

/// A setpoint from the controller's webhook (HMAC-signed, not replayed) or
/// from an operator with the simulator's token; its rate must lie in
/// [0, irrigation_max] of the field.
async fn receive_setpoint(
    State(shared): State<Arc<Shared>>,
    UrlPath(name): UrlPath<String>,
    headers: axum::http::HeaderMap,
    body: axum::body::Bytes,
) -> axum::response::Response {
    let header = |h: &str| headers.get(h).and_then(|v| v.to_str().ok());
    let now = Utc::now().timestamp();
    match (header(SIGNATURE_HEADER), header(TIMESTAMP_HEADER)) {
        (Some(signature), Some(timestamp)) => {
            if let Err(e) = verify(&shared.secret, timestamp, signature, &body, now) {
                tracing::warn!(field = %name, error = %e, "setpoint refused: bad signature");
                return refuse(StatusCode::UNAUTHORIZED, format!("signature refused: {e}"));
            }
            let delivery = header(DELIVERY_HEADER).unwrap_or("");
            if delivery.is_empty() {
                return refuse(
                    StatusCode::BAD_REQUEST,
                    format!("{DELIVERY_HEADER} is missing"),
                );
            }
            let fresh = shared
                .replays
                .lock()
                .unwrap_or_else(|p| p.into_inner())
                .first_time(delivery, now);
            if !fresh {
                // a retry of a delivery already applied: acknowledged again
                return StatusCode::NO_CONTENT.into_response();
            }
        }
        _ => match crate::service::api::bearer(&headers) {
            None => {
                return refuse(
                    StatusCode::UNAUTHORIZED,
                    "a setpoint needs the controller's signature or \
                         'Authorization: Bearer <simulator token>'",
                );
            }
            Some(t) if !crate::service::api::same_secret(t, &shared.token) => {
                return refuse(StatusCode::FORBIDDEN, "the bearer token is not valid");
            }
            Some(_) => {}
        },
    }
    let setpoint: Setpoint = match serde_json::from_slice(&body) {
        Ok(s) => s,
        Err(e) => {
            return refuse(
                StatusCode::UNPROCESSABLE_ENTITY,
                format!("not a setpoint: {e}"),
            );
        }
    };
    let mut fields = shared.fields.lock().unwrap_or_else(|p| p.into_inner());
    let Some(f) = fields.iter_mut().find(|f| f.name == name) else {
        return refuse(StatusCode::NOT_FOUND, format!("no field '{name}'"));
    };
    let most = f.spec.irrigation_max;
    if !(setpoint.rate.is_finite() && (0.0..=most).contains(&setpoint.rate)) {
        return refuse(
            StatusCode::UNPROCESSABLE_ENTITY,
            format!("rate = {} must lie in [0, {most}] m/s", setpoint.rate),
        );
    }
    if setpoint.valid_until <= setpoint.valid_from {
        return refuse(
            StatusCode::UNPROCESSABLE_ENTITY,
            "valid_until must lie after valid_from",
        );
    }
    f.setpoint = Some((setpoint.rate, setpoint.valid_from, setpoint.valid_until));
    let _ = f.save(&shared.settings.sim_data_dir);
    StatusCode::NO_CONTENT.into_response()
}

/// A secret kept in `dir/name` (0600), made at first use.
fn private_secret(dir: &Path, name: &str) -> Result<String, FieldSimError> {
    let path = dir.join(name);
    if let Ok(text) = std::fs::read_to_string(&path)
        && text.trim().len() >= 16
    {
        return Ok(text.trim().to_string());
    }
    let secret = crate::service::random_hex(24).map_err(FieldSimError)?;
    crate::service::write_private(&path, &secret)
        .map_err(|e| FieldSimError(format!("cannot write {}: {e}", path.display())))?;
    Ok(secret)
}

/// Checks the controller's clock against ours: same speedup, and the same
/// time within a tolerance.
async fn check_clock(
    http: &reqwest::Client,
    settings: &FieldSimSettings,
    clock: &Clock,
) -> Result<Option<()>, FieldSimError> {
    let Ok(r) = http
        .get(format!("{}/v1/clock", settings.controller))
        .send()
        .await
    else {
        return Ok(None);
    };
    let Ok(v) = r.json::<serde_json::Value>().await else {
        return Ok(None);
    };
    let speedup = v["speedup"].as_f64().unwrap_or(f64::NAN);
    let their: Option<DateTime<Utc>> = v["now"].as_str().and_then(|t| t.parse().ok());
    let ours = clock.now();
    // a second of real time, at least a minute of clock time
    let tolerance = (clock.speedup() * 1.0).max(60.0);
    match their {
        Some(t)
            if (speedup - clock.speedup()).abs() < 1e-9
                && ((t - ours).num_milliseconds() as f64 / 1000.0).abs() <= tolerance =>
        {
            Ok(Some(()))
        }
        _ => Err(FieldSimError(format!(
            "clock mismatch with the controller: it runs at {speedup}× and reads {}, \
             this simulator runs at {}× and reads {}; configure the same \
             clock.speedup and clock.epoch on both",
            v["now"],
            clock.speedup(),
            ours.to_rfc3339()
        ))),
    }
}

/// The simulator's work: clock check, registration, the plants, sending.
async fn work_loop(
    shared: Arc<Shared>,
    clock: Clock,
    http: reqwest::Client,
) -> Result<(), FieldSimError> {
    let s = &shared.settings;
    let token = s.api_token.clone().unwrap_or_default();
    let mut backoff = Duration::from_millis(100);
    // wait for the controller, then insist on one clock
    let mut said = std::time::Instant::now();
    loop {
        if check_clock(&http, s, &clock).await?.is_some() {
            break;
        }
        if said.elapsed() >= Duration::from_secs(5) || backoff == Duration::from_millis(100) {
            tracing::warn!(
                "controller {} not reachable yet: retrying in {:.1} s",
                s.controller,
                backoff.as_secs_f64()
            );
            said = std::time::Instant::now();
        }
        tokio::time::sleep(backoff).await;
        backoff = (backoff * 2).min(Duration::from_secs(5));
    }
    let tick = Duration::from_secs_f64(
        (s.fields
            .iter()
            .filter_map(|f| f.simulation.clone())
            .map(|sim| sim.measurement_interval_s)
            .fold(f64::INFINITY, f64::min)
            / clock.speedup())
        .clamp(0.01, 5.0),
    );
    let mut backoff = Duration::ZERO;
    let mut waited_until = std::time::Instant::now();
    loop {
        let now = clock.now();
        // the plants and their measurements
        {
            let mut fields = shared.fields.lock().unwrap_or_else(|p| p.into_inner());
            for f in fields.iter_mut() {
                match f.advance(now, s.max_buffer, s.max_catch_up_s) {
                    Ok(true) => {
                        let _ = f.save(&s.sim_data_dir);
                    }
                    Ok(false) => {}
                    Err(e) => return Err(FieldSimError(format!("field '{}': {e}", f.name))),
                }
            }
        }
        if std::time::Instant::now() >= waited_until {
            match sync_with_controller(&shared, &http, &token, now).await {
                Ok(()) => backoff = Duration::ZERO,
                Err(e) => {
                    backoff =
                        (backoff * 2).clamp(Duration::from_millis(200), Duration::from_secs(10));
                    let wait = backoff.as_secs_f64();
                    match e {
                        // a rejected token or field does not get better by
                        // asking again: stop, saying why (exit code 2)
                        SyncError::Fatal(m) => {
                            return Err(FieldSimError(format!(
                                "the controller refused this simulator: {m}"
                            )));
                        }
                        SyncError::Refused(m) => tracing::error!(
                            "the controller refused this simulator: {m}; \
                             retrying in {wait:.1} s"
                        ),
                        SyncError::Down(m) => tracing::warn!(
                            "controller {} down ({m}): retrying in {wait:.1} s; \
                             measurements stay buffered",
                            s.controller
                        ),
                    }
                    waited_until = std::time::Instant::now() + backoff;
                }
            }
        }
        let next = next_boundary(now, 60.0).min(
            now + TimeDelta::milliseconds((tick.as_secs_f64() * clock.speedup() * 1000.0) as i64),
        );
        tokio::time::sleep(clock.real_until(next).clamp(Duration::from_millis(5), tick)).await;
    }
}

/// Why a round with the controller failed.
enum SyncError {
    /// It answered and refused something a retry may get through.
    Refused(String),
    /// It refused the token or a field: asking again cannot help.
    Fatal(String),
    /// It did not answer.
    Down(String),
}

fn down(e: reqwest::Error) -> SyncError {
    SyncError::Down(e.to_string())
}

/// The controller's refusal of `what`, said plainly.
fn refused(what: &str, status: StatusCode, body: String) -> SyncError {
    let detail = serde_json::from_str::<serde_json::Value>(&body)
        .ok()
        .and_then(|v| v["detail"].as_str().map(String::from))
        .unwrap_or(body);
    match status.as_u16() {
        401 | 403 => SyncError::Fatal(format!(
            "{what}: HTTP {status}, the API token was rejected ({detail}); set \
             ROOTZONE_API_TOKEN (or api_token) to the controller's token, which it keeps in \
             its data folder's api-token file"
        )),
        500..=599 => SyncError::Down(format!("{what}: HTTP {status} {detail}")),
        _ => SyncError::Refused(format!("{what}: HTTP {status} {detail}")),
    }
}

/// Registers unknown fields, sends buffered measurements and due forecasts.
async fn sync_with_controller(
    shared: &Arc<Shared>,
    http: &reqwest::Client,
    token: &str,
    now: DateTime<Utc>,
) -> Result<(), SyncError> {
    let base = &shared.settings.controller;
    // registration by name
    let unregistered: Vec<(usize, FieldSpec)> = {
        let fields = shared.fields.lock().unwrap_or_else(|p| p.into_inner());
        fields
            .iter()
            .enumerate()
            .filter(|(_, f)| f.id.is_none())
            .map(|(i, f)| (i, f.spec.clone()))
            .collect()
    };
    if !unregistered.is_empty() {
        let known: Vec<serde_json::Value> = http
            .get(format!("{base}/v1/fields"))
            .send()
            .await
            .map_err(down)?
            .json()
            .await
            .map_err(down)?;
        for (i, spec) in unregistered {
            let id = match known.iter().find(|f| f["name"] == spec.name.as_str()) {
                Some(f) => f["id"].as_i64(),
                None => {
                    let r = http
                        .post(format!("{base}/v1/fields"))
                        .bearer_auth(token)
                        .json(&spec)
                        .send()
                        .await
                        .map_err(down)?;
                    if !r.status().is_success() {
                        let status = r.status();
                        let text = r.text().await.unwrap_or_default();
                        return Err(refused(
                            &format!("registering '{}'", spec.name),
                            status,
                            text,
                        ));
                    }
                    r.json::<serde_json::Value>().await.map_err(down)?["id"].as_i64()
                }
            };
            shared.fields.lock().unwrap_or_else(|p| p.into_inner())[i].id = id;
        }
    }
    // measurements (up to 1000 per request) and forecasts
    let work: Vec<(
        usize,
        i64,
        Vec<Measurement>,
        Option<crate::service::wire::Forecast>,
    )> = {
        let mut fields = shared.fields.lock().unwrap_or_else(|p| p.into_inner());
        let mut out = Vec::new();
        for (i, f) in fields.iter_mut().enumerate() {
            let Some(id) = f.id else { continue };
            let batch: Vec<Measurement> = f.buffer.iter().take(1000).cloned().collect();
            let period = f.spec.control_period_s;
            let due = f
                .last_forecast
                .is_none_or(|t| (now - t).num_milliseconds() as f64 >= period * 1000.0);
            let forecast = due.then(|| {
                let mut rng = ChaCha8Rng::seed_from_u64(
                    f.sim.seed.wrapping_add(1000) ^ (now.timestamp() as u64).rotate_left(20),
                );
                // from the period boundary, a few steps longer than the
                // controller's horizon of 20
                let start = crate::service::clock::boundary_at_or_before(now, period);
                scenario_forecast(
                    f.sim.scenario,
                    f.plant.day_zero(),
                    start,
                    period,
                    24,
                    f.sim.forecast_error,
                    &mut rng,
                )
            });
            out.push((i, id, batch, forecast));
        }
        out
    };
    for (i, id, batch, forecast) in work {
        if !batch.is_empty() {
            let r = http
                .post(format!("{base}/v1/fields/{id}/measurements"))
                .bearer_auth(token)
                .json(&batch)
                .send()
                .await
                .map_err(down)?;
            if r.status().is_success() {
                let mut fields = shared.fields.lock().unwrap_or_else(|p| p.into_inner());
                let f = &mut fields[i];
                // drop exactly what was acknowledged (the front of the buffer)
                let last = batch.last().map(|m| m.time);
                while f.buffer.front().is_some_and(|m| Some(m.time) <= last) {
                    f.buffer.pop_front();
                }
                let _ = f.save(&shared.settings.sim_data_dir);
            } else if r.status() == StatusCode::NOT_FOUND {
                // the controller lost the field: register again
                shared.fields.lock().unwrap_or_else(|p| p.into_inner())[i].id = None;
            } else {
                let status = r.status();
                let text = r.text().await.unwrap_or_default();
                return Err(refused("sending measurements", status, text));
            }
        }
        if let Some(forecast) = forecast {
            let r = http
                .put(format!("{base}/v1/fields/{id}/forecast"))
                .bearer_auth(token)
                .json(&forecast)
                .send()
                .await
                .map_err(down)?;
            if r.status().is_success() {
                shared.fields.lock().unwrap_or_else(|p| p.into_inner())[i].last_forecast =
                    Some(now);
            } else {
                let status = r.status();
                let text = r.text().await.unwrap_or_default();
                return Err(refused("sending the forecast", status, text));
            }
        }
    }
    Ok(())
}
