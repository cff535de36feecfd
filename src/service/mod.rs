//! The controller daemon (`rootzone serve`): settings, clock, storage, the
//! control loop with its simulated fields, the HTTP API and metrics. The only
//! part of the crate that knows tokio, axum, SQLite and JSON wire types.

pub mod api;
pub mod chart;
pub mod clock;
pub mod cycle;
pub mod engine;
pub mod explain;
pub mod history;
pub mod metrics;
pub mod replicas;
pub mod settings;
pub use crate::store;
pub mod training;
pub mod valve;
pub mod water;
pub mod webhook;
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
    /// This replica's id (the holder named in leases and cycle runs).
    pub replica: String,
    pub settings: Settings,
    /// The per-field surrogate training jobs.
    pub training: Arc<training::Jobs>,
    /// The MQTT client (`mqtt.url` set).
    pub mqtt: Option<Arc<crate::adapters::mqtt::client::Mqtt>>,
    /// Bounds the control cycles and simulations running at once.
    permits: Arc<Semaphore>,
    /// Per field, woken when its measurements are stored (a cycle waiting
    /// for its boundary's measurement).
    measured: Mutex<HashMap<i64, Arc<tokio::sync::Notify>>>,
    /// Cancels a field's scheduled tasks (on delete or shutdown).
    field_tasks: Mutex<HashMap<i64, CancellationToken>>,
    shutdown: CancellationToken,
    tracker: TaskTracker,
}

impl AppState {
    /// Every field, read on the blocking pool; none when the store fails
    /// (the background loops that call this try again at their next tick).
    pub(crate) async fn all_fields(&self) -> Vec<Field> {
        let engine = self.engine.clone();
        tokio::task::spawn_blocking(move || engine.store.fields())
            .await
            .ok()
            .and_then(Result::ok)
            .unwrap_or_default()
    }

    /// The notification of field `id`'s stored measurements (woken, with
    /// `notify_waiters`, after every commit of new ones).
    pub fn measured(&self, id: i64) -> Arc<tokio::sync::Notify> {
        self.measured
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .entry(id)
            .or_default()
            .clone()
    }

    /// Cancelled when the daemon shuts down.
    pub fn shutdown_token(&self) -> CancellationToken {
        self.shutdown.clone()
    }
}

/// A built daemon, ready to serve on its listener.
pub struct App {
    pub state: Arc<AppState>,
    listener: TcpListener,
    /// The MQTT event loop, polled once the app runs.
    mqtt_loop: Option<rumqttc::EventLoop>,
}

fn read_token(dir: &Path) -> Result<String, ServeError> {
    let path = dir.join("api-token");
    if let Ok(text) = std::fs::read_to_string(&path) {
        let token = text.trim().to_string();
        if token.len() >= 8 {
            return Ok(token);
        }
    }
    let token = random_hex(24).map_err(ServeError::Io)?;
    write_private(&path, &token)
        .map_err(|e| ServeError::Io(format!("cannot write {}: {e}", path.display())))?;
    Ok(token)
}

/// A replica's id when none is set: host name, process id and a random
/// suffix (a restarted process is a new replica).
fn default_replica_id() -> String {
    let host = std::fs::read_to_string("/etc/hostname")
        .ok()
        .map(|h| h.trim().to_string())
        .filter(|h| !h.is_empty())
        .unwrap_or_else(|| "rootzone".into());
    let host: String = host
        .chars()
        .filter(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '-' | '_'))
        .take(40)
        .collect();
    let suffix = random_hex(3).unwrap_or_default();
    format!("{host}-{}-{suffix}", std::process::id())
}

/// Logging through `tracing` to stderr: `RUST_LOG` when set, else the
/// settings' level; text or JSON lines.
pub fn init_logging(log: &settings::LogSettings) {
    use tracing_subscriber::EnvFilter;
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| {
        EnvFilter::try_new(&log.level).unwrap_or_else(|_| EnvFilter::new("info"))
    });
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr);
    let _ = match log.format {
        settings::LogFormat::Json => builder.json().try_init(),
        settings::LogFormat::Text => builder.try_init(),
    };
}

/// Makes rustls use the ring crypto provider for every outgoing HTTPS call
/// (reqwest is built with rustls and no provider of its own).
pub fn install_tls() {
    let _ = rustls::crypto::ring::default_provider().install_default();
}

/// Gives a webhook actuator without a secret a new one; returns it (to be
/// shown once), or None when there was nothing to make.
pub(crate) fn give_secret(spec: &mut wire::FieldSpec) -> Result<Option<String>, String> {
    match &mut spec.actuator {
        Actuator::Webhook { secret, .. } if secret.is_none() => {
            let s = random_hex(32)?;
            *secret = Some(s.clone());
            Ok(Some(s))
        }
        _ => Ok(None),
    }
}

/// `bytes` random bytes from the system's generator, as hex.
pub(crate) fn random_hex(bytes: usize) -> Result<String, String> {
    let mut buf = vec![0u8; bytes];
    use std::io::Read;
    std::fs::File::open("/dev/urandom")
        .and_then(|mut f| f.read_exact(&mut buf))
        .map_err(|e| format!("cannot read /dev/urandom: {e}"))?;
    Ok(hex::encode(buf))
}

#[cfg(unix)]
pub(crate) fn write_private(path: &Path, text: &str) -> std::io::Result<()> {
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
pub(crate) fn write_private(path: &Path, text: &str) -> std::io::Result<()> {
    std::fs::write(path, text)
}

impl App {
    /// Opens the storage, loads the models, binds the listener.
    pub async fn build(settings: Settings) -> Result<App, ServeError> {
        settings.validate()?;
        install_tls();
        let store = Arc::new(store::Store::connect(&settings.storage_location()?)?);
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
                .ok()
                .filter(|t| wire::check_time("clock", *t).is_ok())
                .unwrap_or_else(Utc::now),
            _ => Utc::now(),
        };
        let clock = match settings.clock.epoch {
            Some(epoch) => Clock::anchored(epoch, settings.clock.speedup)
                .map_err(|e| settings::SettingsError(format!("clock.epoch: {e}")))?,
            None => Clock::new(origin, settings.clock.speedup),
        };
        if store.fields()?.is_empty() {
            for spec in &settings.fields {
                let mut spec = spec.clone();
                // a configured webhook without a secret: one is made and
                // logged once, for the receiver
                if let Some(s) = give_secret(&mut spec).map_err(ServeError::Io)? {
                    tracing::warn!(field = %spec.name, secret = %s,
                        "webhook secret generated (set actuator.secret in the configuration to choose it)");
                }
                store.create_field(&spec, clock.now())?;
            }
        }
        let listener = TcpListener::bind(&settings.listen)
            .await
            .map_err(|e| ServeError::Io(format!("cannot listen on {}: {e}", settings.listen)))?;
        if let Ok(addr) = listener.local_addr()
            && !addr.ip().is_loopback()
        {
            tracing::warn!(%addr, "listening beyond loopback: the read API (GET) answers anyone who \
                can reach it, and a client needs the token only to change things; \
                put it behind a firewall or a TLS proxy");
        }
        let base_name = match &settings.models_dir {
            Some(dir) => dir.join(TWO_LAYER_FILE).display().to_string(),
            None => "(built-in) models/two-layer.json".to_string(),
        };
        let training = Arc::new(training::Jobs::new(
            settings.training,
            settings.limits.training_jobs,
            training::Base::of(&models.two_layer, &base_name),
            &settings.data_dir,
        ));
        let own_models = training::OwnModels::at(settings.data_dir.join("surrogates"));
        let (mqtt, mqtt_loop) = match crate::adapters::mqtt::client::Mqtt::new(&settings.mqtt)
            .map_err(settings::SettingsError)?
        {
            Some((client, eventloop)) => (Some(Arc::new(client)), Some(eventloop)),
            None => (None, None),
        };
        let replica = default_replica_id();
        let state = Arc::new(AppState {
            engine: Arc::new(
                Engine::new(store, models)
                    .forecast_settings(settings.forecasts.clone())
                    .catch_up_limit(settings.limits.max_catch_up_s)
                    .late_window(settings.limits.late_window_s)
                    .own_models(own_models),
            ),
            training,
            mqtt,
            clock,
            metrics: Metrics::new(),
            token,
            replica,
            permits: Arc::new(Semaphore::new(settings.limits.worker_threads)),
            settings,
            measured: Mutex::new(HashMap::new()),
            field_tasks: Mutex::new(HashMap::new()),
            shutdown: CancellationToken::new(),
            tracker: TaskTracker::new(),
        });
        Ok(App {
            state,
            listener,
            mqtt_loop,
        })
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
        if let (Some(mqtt), Some(eventloop)) = (state.mqtt.clone(), self.mqtt_loop) {
            let s = state.clone();
            state
                .tracker
                .spawn(async move { crate::adapters::mqtt::client::run(s, mqtt, eventloop).await });
        }
        // every field's first cycle runs now, then at its period boundaries
        for field in state.engine.store.fields()? {
            spawn_field(&state, &field, true);
        }
        let s = state.clone();
        state.tracker.spawn(async move { forecast_loop(s).await });
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
        state.training.cancel_all();
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
            tracing::warn!(
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
    if let Some(mqtt) = &state.mqtt {
        mqtt.announce(state, field);
    }
    spawn_field(state, field, false)
}

/// Runs a field's first cycle now (at creation and at start): a simulated
/// plant first takes its reading, so the cycle starts from a measurement.
pub(crate) async fn first_cycle(state: &Arc<AppState>, field: &Field) {
    let now = state.clock.now();
    if field.spec.actuator == Actuator::Simulated
        && let Ok(permit) = state.permits.clone().acquire_owned().await
    {
        let (engine, f) = (state.engine.clone(), field.clone());
        match tokio::task::spawn_blocking(move || engine.advance_plant(&f, now)).await {
            Ok(Ok(n)) => state.metrics.measurements.inc_by(n as u64),
            Ok(Err(e)) => tracing::warn!(field = field.id, error = %e, "simulation"),
            Err(e) => tracing::error!(field = field.id, error = %e, "simulation task failed"),
        }
        drop(permit);
    }
    if let Err(e) = run_cycle(state, field.clone(), now, false).await {
        tracing::warn!(field = field.id, error = %e, "first control cycle");
    }
}

fn spawn_field(state: &Arc<AppState>, field: &Field, cycle_now: bool) {
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
        .spawn(async move { control_loop(s, id, t, cycle_now).await });
    // (cycle_now: the daemon's start; a new field has had its first cycle)
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
async fn control_loop(state: Arc<AppState>, id: i64, cancel: CancellationToken, cycle_now: bool) {
    if cycle_now && let Ok(Some(field)) = state.engine.store.field(id) {
        tokio::select! {
            _ = first_cycle(&state, &field) => {}
            _ = cancel.cancelled() => return,
        }
    }
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
        if let Err(e) = run_cycle(&state, field, next, true).await {
            tracing::warn!(field = id, at = %next, error = %e, "control cycle failed");
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

/// Polls the fields' forecast sources (`crate::adapters::forecast`): every
/// `forecasts.retry_s` of clock time the sources that are due (their poll
/// interval or backoff over) are requested, once per distinct source.
async fn forecast_loop(state: Arc<AppState>) {
    let settings = state.settings.forecasts.clone();
    let tick = settings.retry_s.min(settings.poll_interval_s);
    let poller = match crate::adapters::forecast::Poller::new(settings, state.engine.store.clone())
    {
        Ok(p) => p,
        Err(e) => {
            tracing::error!(error = %e, "no forecast poller");
            return;
        }
    };
    let mut warned = false;
    loop {
        let fields = state.all_fields().await;
        let polled: Vec<Field> = fields
            .into_iter()
            .filter(|f| f.spec.forecast_source.is_some())
            .collect();
        if !polled.is_empty() {
            if !warned && poller.settings().contact.trim().is_empty() {
                tracing::warn!(
                    "forecasts.contact is not set: providers ask for a contact in the                     User-Agent (MET Norway may block requests without one)"
                );
                warned = true;
            }
            match poller.poll(state.clock.now(), &polled).await {
                Ok(r) if r.requests > 0 => tracing::info!(
                    sources = r.sources,
                    requests = r.requests,
                    updated = r.updated,
                    not_modified = r.not_modified,
                    failed = r.failed,
                    fields = r.fields_updated,
                    "forecast poll"
                ),
                Ok(_) => {}
                Err(e) => tracing::warn!(error = %e, "forecast poll"),
            }
        }
        let next = clock::add_seconds(state.clock.now(), tick);
        tokio::select! {
            _ = state.clock.sleep_until(next) => {}
            _ = state.shutdown.cancelled() => return,
        }
    }
}

/// Advances a simulated plant every measurement interval.
async fn plant_loop(state: Arc<AppState>, id: i64, cancel: CancellationToken) {
    loop {
        let Ok(Some(field)) = state.engine.store.field(id) else {
            return;
        };
        let Some(sim) = field.spec.simulation.clone() else {
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
            Ok(Err(e)) => tracing::warn!(field = id, error = %e, "simulation"),
            Err(e) => tracing::error!(field = id, error = %e, "simulation task failed"),
        }
    }
}

/// Runs one control cycle on the blocking pool (in a span naming the field,
/// model, status, iterations and solve time), records it in the metrics and
/// publishes the setpoint.
///
/// A scheduled cycle (`scheduled`: `at` is a period boundary) runs once per
/// (field, boundary) across every replica: Ok(None) when the store refused
/// it (run already, or the lease ended).
pub(crate) async fn run_cycle(
    state: &Arc<AppState>,
    field: Field,
    at: DateTime<Utc>,
    scheduled: bool,
) -> Result<Option<Setpoint>, String> {
    use tracing::Instrument;
    let span = tracing::info_span!(
        "cycle",
        field = field.id,
        model = field.spec.model.name(),
        at = %at,
        status = tracing::field::Empty,
        iterations = tracing::field::Empty,
        solve_ms = tracing::field::Empty,
        amount_mm = tracing::field::Empty,
    );
    run_cycle_in(state, field, at, scheduled, span.clone())
        .instrument(span)
        .await
}

async fn run_cycle_in(
    state: &Arc<AppState>,
    field: Field,
    at: DateTime<Utc>,
    scheduled: bool,
    span: tracing::Span,
) -> Result<Option<Setpoint>, String> {
    let _permit = state
        .permits
        .clone()
        .acquire_owned()
        .await
        .map_err(|e| e.to_string())?;
    let engine = state.engine.clone();
    let f = field.clone();
    let replica = state.replica.clone();
    let decided = tokio::task::spawn_blocking(move || {
        let run = scheduled.then_some(store::CycleRun {
            boundary: at,
            replica: &replica,
        });
        engine.control_cycle(&f, at, run)
    })
    .await;
    let setpoint = match decided {
        Ok(Ok(Some(setpoint))) => setpoint,
        Ok(Ok(None)) => {
            tracing::info!("this boundary has run already (or the lease ended): not published");
            state.metrics.cycles_refused.inc();
            return Ok(None);
        }
        Ok(Err(e)) => return Err(e.to_string()),
        Err(e) => {
            // a panic's text stays in the log
            tracing::error!(error = %e, "control cycle panicked");
            return Err("the control cycle failed (see the daemon's log)".into());
        }
    };
    span.record("status", setpoint.status.as_str());
    span.record("iterations", setpoint.iterations);
    span.record("solve_ms", setpoint.solve_ms);
    span.record("amount_mm", setpoint.amount_mm);
    tracing::info!(degraded = ?setpoint.degraded, "setpoint published");
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
    // the setpoint this one replaces has applied all it will
    if let Ok(latest) = state.engine.store.recent_setpoints(field.id, 2)
        && let [_, previous] = latest.as_slice()
    {
        let mm = water::applied_mm(
            std::slice::from_ref(previous),
            previous.valid_from,
            setpoint.valid_from.max(previous.valid_from),
        );
        m.water_mm.with_label_values(&[label.as_str()]).inc_by(mm);
        if let Some(system) = &field.spec.irrigation_system {
            m.water_m3
                .with_label_values(&[label.as_str()])
                .inc_by(system.cubic_metres(mm));
        }
    }
    if let Ok(Some(latest)) = state.engine.store.measurement_before(field.id, at) {
        m.theta
            .with_label_values(&[label.as_str()])
            .set(latest.theta);
    }
    let _ = state
        .engine
        .store
        .set_meta("clock", &state.clock.now().to_rfc3339());
    if let Some(mqtt) = state.mqtt.clone() {
        // the state document reads the store: off the executor
        let (s, f, sp) = (state.clone(), field.clone(), setpoint.clone());
        let _ = tokio::task::spawn_blocking(move || mqtt.publish_setpoint(&s, &f, &sp)).await;
    }
    if let Actuator::Webhook { url, secret } = &field.spec.actuator {
        use tracing::Instrument;
        let body = serde_json::to_vec(&setpoint).map_err(|e| e.to_string())?;
        let (url, secret) = (url.clone(), secret.clone());
        let allow = state.settings.webhooks.allow_link_local;
        let cancel = state.shutdown.clone();
        let delivered = m.webhooks.clone();
        state.tracker.spawn(
            async move {
                let ok = webhook::deliver(&url, secret.as_deref(), body, allow, &cancel).await;
                delivered
                    .with_label_values(&[if ok { "delivered" } else { "failed" }])
                    .inc();
            }
            .instrument(tracing::Span::current()),
        );
    }
    Ok(Some(setpoint))
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
