//! The controller daemon (`rootzone serve`): settings, clock, storage, the
//! control loop with its simulated fields, the HTTP API and metrics. The only
//! part of the crate that knows tokio, axum, SQLite and JSON wire types.

pub mod api;
pub mod chart;
pub mod clock;
pub mod engine;
pub mod metrics;
pub mod settings;
pub mod store;
pub mod wire;

use std::collections::HashMap;
use std::path::Path;
use std::sync::{Arc, Mutex};

use chrono::{DateTime, TimeDelta, Utc};
use tokio::net::TcpListener;
use tokio::sync::Semaphore;
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;

use crate::surrogate::ModelFile;
use crate::surrogate::pipeline::{SINGLE_FILE, TWO_LAYER_FILE};

pub use clock::Clock;
pub use settings::Settings;

use engine::{Engine, Models};
use metrics::Metrics;
use wire::{Actuator, Field, Setpoint};

/// The shipped sandy-loam models, built into the binary.
const SHIPPED_TWO_LAYER: &str = include_str!("../../models/two-layer.json");
const SHIPPED_SINGLE: &str = include_str!("../../models/single-lstm.json");

/// How long shutdown waits for running cycles and deliveries.
pub const SHUTDOWN_GRACE: std::time::Duration = std::time::Duration::from_secs(5);

/// The daemon could not start.
#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    #[error(transparent)]
    Settings(#[from] settings::SettingsError),
    #[error(transparent)]
    Store(#[from] store::StoreError),
    #[error(transparent)]
    Model(#[from] crate::surrogate::ModelFileError),
    #[error("{0}")]
    Io(String),
}

/// Shared state of the running daemon.
pub struct AppState {
    pub engine: Arc<Engine>,
    pub clock: Clock,
    pub metrics: Metrics,
    pub token: String,
    pub settings: Settings,
    /// Bounds the control cycles and simulations running at once.
    permits: Arc<Semaphore>,
    /// Per field, woken when its measurements are stored (a cycle waiting
    /// for its boundary's measurement).
    measured: Mutex<HashMap<i64, Arc<tokio::sync::Notify>>>,
    /// Cancels a field's scheduled tasks (on delete or shutdown).
    field_tasks: Mutex<HashMap<i64, CancellationToken>>,
    shutdown: CancellationToken,
    tracker: TaskTracker,
    http: reqwest::Client,
}

impl AppState {
    /// The notification of field `id`'s stored measurements.
    pub(crate) fn measured(&self, id: i64) -> Arc<tokio::sync::Notify> {
        self.measured
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .entry(id)
            .or_default()
            .clone()
    }
}

/// A built daemon, ready to serve on its listener.
pub struct App {
    pub state: Arc<AppState>,
    listener: TcpListener,
}

fn read_token(dir: &Path) -> Result<String, ServeError> {
    let path = dir.join("api-token");
    if let Ok(text) = std::fs::read_to_string(&path) {
        let token = text.trim().to_string();
        if token.len() >= 8 {
            return Ok(token);
        }
    }
    let mut bytes = [0u8; 24];
    use std::io::Read;
    std::fs::File::open("/dev/urandom")
        .and_then(|mut f| f.read_exact(&mut bytes))
        .map_err(|e| ServeError::Io(format!("cannot read /dev/urandom: {e}")))?;
    let token: String = bytes.iter().map(|b| format!("{b:02x}")).collect();
    write_private(&path, &token)
        .map_err(|e| ServeError::Io(format!("cannot write {}: {e}", path.display())))?;
    Ok(token)
}

#[cfg(unix)]
fn write_private(path: &Path, text: &str) -> std::io::Result<()> {
    use std::io::Write;
    use std::os::unix::fs::OpenOptionsExt;
    let mut f = std::fs::OpenOptions::new()
        .write(true)
        .create(true)
        .truncate(true)
        .mode(0o600)
        .open(path)?;
    f.write_all(text.as_bytes())?;
    f.sync_all()
}

#[cfg(not(unix))]
fn write_private(path: &Path, text: &str) -> std::io::Result<()> {
    std::fs::write(path, text)
}

impl App {
    /// Opens the storage, loads the models, binds the listener.
    pub async fn build(settings: Settings) -> Result<App, ServeError> {
        settings.validate()?;
        let store = Arc::new(store::Store::open(&settings.data_dir)?);
        let token = match &settings.api_token {
            Some(t) => t.clone(),
            None => read_token(&settings.data_dir)?,
        };
        let models = match &settings.models_dir {
            Some(dir) => Models {
                two_layer: ModelFile::load(&dir.join(TWO_LAYER_FILE))?,
                lstm: ModelFile::load(&dir.join(SINGLE_FILE))?,
            },
            None => Models {
                two_layer: ModelFile::from_json(
                    SHIPPED_TWO_LAYER,
                    Path::new("(built-in) models/two-layer.json"),
                )?,
                lstm: ModelFile::from_json(
                    SHIPPED_SINGLE,
                    Path::new("(built-in) models/single-lstm.json"),
                )?,
            },
        };
        // an accelerated clock resumes where it stopped; real time is now
        let origin = match store.meta("clock")? {
            Some(t) if settings.clock.speedup != 1.0 => DateTime::parse_from_rfc3339(&t)
                .map(|t| t.to_utc())
                .unwrap_or_else(|_| Utc::now()),
            _ => Utc::now(),
        };
        let clock = match settings.clock.epoch {
            Some(epoch) => Clock::anchored(epoch, settings.clock.speedup),
            None => Clock::new(origin, settings.clock.speedup),
        };
        if store.fields()?.is_empty() {
            for spec in &settings.fields {
                store.create_field(spec, clock.now())?;
            }
        }
        let listener = TcpListener::bind(&settings.listen)
            .await
            .map_err(|e| ServeError::Io(format!("cannot listen on {}: {e}", settings.listen)))?;
        let state = Arc::new(AppState {
            engine: Arc::new(Engine::new(store, models)),
            clock,
            metrics: Metrics::new(),
            token,
            permits: Arc::new(Semaphore::new(settings.limits.worker_threads)),
            settings,
            measured: Mutex::new(HashMap::new()),
            field_tasks: Mutex::new(HashMap::new()),
            shutdown: CancellationToken::new(),
            tracker: TaskTracker::new(),
            http: reqwest::Client::builder()
                .timeout(std::time::Duration::from_secs(10))
                .build()
                .map_err(|e| ServeError::Io(format!("HTTP client: {e}")))?,
        });
        Ok(App { state, listener })
    }

    pub fn local_addr(&self) -> std::io::Result<std::net::SocketAddr> {
        self.listener.local_addr()
    }

    /// Serves until `shutdown` resolves, then lets running control cycles
    /// finish and closes the storage.
    pub async fn run(
        self,
        shutdown: impl std::future::Future<Output = ()> + Send + 'static,
    ) -> Result<(), ServeError> {
        let state = self.state;
        for field in state.engine.store.fields()? {
            start_field(&state, &field);
        }
        let router = api::router(state.clone());
        let cancel = state.shutdown.clone();
        let server = axum::serve(self.listener, router).with_graceful_shutdown(async move {
            tokio::select! {
                _ = shutdown => {}
                _ = cancel.cancelled() => {}
            }
        });
        let result = server.await;
        state.shutdown.cancel();
        // a solve under way stops as at its time budget and stores its
        // fallback; whatever still runs after the grace period is left
        state
            .engine
            .cancel
            .store(true, std::sync::atomic::Ordering::Relaxed);
        state.tracker.close();
        if tokio::time::timeout(SHUTDOWN_GRACE, state.tracker.wait())
            .await
            .is_err()
        {
            eprintln!(
                "shutdown: tasks still running after {SHUTDOWN_GRACE:?}; stopping without them"
            );
        }
        let _ = state
            .engine
            .store
            .set_meta("clock", &state.clock.now().to_rfc3339());
        result.map_err(|e| ServeError::Io(format!("server: {e}")))
    }
}

/// Starts the scheduled tasks of a field: its control loop and, for a
/// simulated field, its plant.
pub(crate) fn start_field(state: &Arc<AppState>, field: &Field) {
    let token = state.shutdown.child_token();
    if let Some(old) = state
        .field_tasks
        .lock()
        .unwrap_or_else(|p| p.into_inner())
        .insert(field.id, token.clone())
    {
        old.cancel();
    }
    let (s, id, t) = (state.clone(), field.id, token.clone());
    state
        .tracker
        .spawn(async move { control_loop(s, id, t).await });
    if field.spec.actuator == Actuator::Simulated {
        let (s, id) = (state.clone(), field.id);
        state
            .tracker
            .spawn(async move { plant_loop(s, id, token).await });
    }
}

/// Stops a field's scheduled tasks.
pub(crate) fn stop_field(state: &AppState, id: i64) {
    if let Some(t) = state
        .field_tasks
        .lock()
        .unwrap_or_else(|p| p.into_inner())
        .remove(&id)
    {
        t.cancel();
    }
    state
        .measured
        .lock()
        .unwrap_or_else(|p| p.into_inner())
        .remove(&id);
    state.engine.forget(id);
}

/// One cycle per control period, at the period boundaries of the clock.
async fn control_loop(state: Arc<AppState>, id: i64, cancel: CancellationToken) {
    loop {
        let Ok(Some(field)) = state.engine.store.field(id) else {
            return;
        };
        let next = clock::next_boundary(state.clock.now(), field.spec.control_period_s);
        tokio::select! {
            _ = state.clock.sleep_until(next) => {}
            _ = cancel.cancelled() => return,
        }
        if field.spec.actuator != Actuator::Simulated {
            let wait =
                TimeDelta::milliseconds((field.spec.effective_measurement_wait() * 1000.0) as i64);
            tokio::select! {
                _ = measurement_at(&state, id, next, next + wait) => {}
                _ = cancel.cancelled() => return,
            }
        }
        if let Err(e) = run_cycle(&state, field, next).await {
            eprintln!("field {id}: control cycle at {next}: {e}");
        }
    }
}

/// Returns once field `id` has a measurement stamped `at`, or at clock time
/// `until`.
async fn measurement_at(state: &AppState, id: i64, at: DateTime<Utc>, until: DateTime<Utc>) {
    loop {
        // registered before the check, so a store in between is not missed
        let notify = state.measured(id);
        let stored = notify.notified();
        tokio::pin!(stored);
        stored.as_mut().enable();
        let engine = state.engine.clone();
        let found = tokio::task::spawn_blocking(move || engine.store.measurement_before(id, at))
            .await
            .ok()
            .and_then(Result::ok)
            .flatten()
            .is_some_and(|m| m.time >= at);
        if found || state.clock.now() >= until {
            return;
        }
        tokio::select! {
            _ = stored => {}
            _ = state.clock.sleep_until(until) => return,
        }
    }
}

/// Advances a simulated plant every measurement interval.
async fn plant_loop(state: Arc<AppState>, id: i64, cancel: CancellationToken) {
    loop {
        let Ok(Some(field)) = state.engine.store.field(id) else {
            return;
        };
        let Some(sim) = field.spec.simulation else {
            return;
        };
        let next = clock::next_boundary(state.clock.now(), sim.measurement_interval_s);
        tokio::select! {
            _ = state.clock.sleep_until(next) => {}
            _ = cancel.cancelled() => return,
        }
        let Ok(_permit) = state.permits.clone().acquire_owned().await else {
            return;
        };
        let engine = state.engine.clone();
        let now = state.clock.now();
        match tokio::task::spawn_blocking(move || engine.advance_plant(&field, now)).await {
            Ok(Ok(n)) => state.metrics.measurements.inc_by(n as u64),
            Ok(Err(e)) => eprintln!("field {id}: simulation: {e}"),
            Err(e) => eprintln!("field {id}: simulation task: {e}"),
        }
    }
}

/// Runs one control cycle on the blocking pool, records it in the metrics
/// and publishes the setpoint.
pub(crate) async fn run_cycle(
    state: &Arc<AppState>,
    field: Field,
    at: DateTime<Utc>,
) -> Result<Setpoint, String> {
    let _permit = state
        .permits
        .clone()
        .acquire_owned()
        .await
        .map_err(|e| e.to_string())?;
    let engine = state.engine.clone();
    let f = field.clone();
    let setpoint = tokio::task::spawn_blocking(move || engine.control_cycle(&f, at))
        .await
        .map_err(|e| format!("control task: {e}"))?
        .map_err(|e| e.to_string())?;
    let m = &state.metrics;
    m.cycles
        .with_label_values(&[setpoint.status.as_str()])
        .inc();
    for flag in &setpoint.degraded {
        m.degraded.with_label_values(&[flag.as_str()]).inc();
    }
    m.solve_seconds.observe(setpoint.solve_ms / 1e3);
    let label = field.id.to_string();
    m.setpoint
        .with_label_values(&[label.as_str()])
        .set(setpoint.amount_mm);
    if let Ok(Some(latest)) = state.engine.store.measurement_before(field.id, at) {
        m.theta
            .with_label_values(&[label.as_str()])
            .set(latest.theta);
    }
    let _ = state
        .engine
        .store
        .set_meta("clock", &state.clock.now().to_rfc3339());
    if let Actuator::Webhook { url } = &field.spec.actuator {
        let (client, url, body) = (state.http.clone(), url.clone(), setpoint.clone());
        state
            .tracker
            .spawn(async move { publish(client, url, body).await });
    }
    Ok(setpoint)
}

/// POSTs a setpoint to a webhook: three attempts, 1 s and 2 s apart.
async fn publish(client: reqwest::Client, url: String, setpoint: Setpoint) {
    for attempt in 0..3u32 {
        match client.post(&url).json(&setpoint).send().await {
            Ok(r) if r.status().is_success() => return,
            Ok(r) => eprintln!(
                "webhook {url}: HTTP {} (attempt {})",
                r.status(),
                attempt + 1
            ),
            Err(e) => eprintln!("webhook {url}: {e} (attempt {})", attempt + 1),
        }
        tokio::time::sleep(std::time::Duration::from_secs(1 << attempt)).await;
    }
}

/// Resolves on SIGINT or SIGTERM.
pub async fn shutdown_signal() {
    let ctrl_c = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    #[cfg(unix)]
    let terminate = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let terminate = std::future::pending::<()>();
    tokio::select! {
        _ = ctrl_c => {}
        _ = terminate => {}
    }
}
