//! The controller daemon (`rootzone serve`): settings, clock, storage, the
//! control loop with its simulated fields, the HTTP API and metrics. The only
//! part of the crate that knows tokio, axum, SQLite and JSON wire types.

pub mod api;
pub mod chart;
pub mod clock;
pub mod cycle;
pub mod deferred;
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
    /// State estimates the cycles left to be brought up to date.
    pub deferred: deferred::Deferred,
    pub clock: Clock,
    pub metrics: Metrics,
    pub token: String,
    /// This replica's id (the holder named in leases and cycle runs).
    pub replica: String,
    /// The fields' leases (PostgreSQL); None: this process runs every field.
    pub leases: Option<Arc<replicas::Leases>>,
    /// The fields whose cycle runs now (a lease is not released under one).
    running: Mutex<std::collections::HashSet<i64>>,
    /// Wakes the lease loop (a field was created, changed or deleted).
    rebalance: tokio::sync::Notify,
    pub settings: Settings,
    /// The per-field surrogate training jobs.
    pub training: Arc<training::Jobs>,
    /// The MQTT client (`mqtt.url` set).
    pub mqtt: Option<Arc<crate::adapters::mqtt::client::Mqtt>>,
    /// Bounds the control cycles and simulations running at once.
    permits: Arc<Semaphore>,
    /// When a cycle last stored the clock's time (see [`save_clock`]).
    clock_saved: Mutex<Option<std::time::Instant>>,
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

    /// Whether this replica may run field `id`'s cycles now: always on
    /// SQLite; on PostgreSQL while it holds a lease that has not lapsed.
    pub fn holds(&self, id: i64) -> bool {
        self.leases.as_ref().is_none_or(|l| l.holds(id))
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
                match store.create_field(&spec, clock.now()) {
                    // another replica starting beside this one made it
                    Err(store::StoreError::Conflict(_)) => {}
                    other => {
                        other?;
                    }
                }
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
        let replica = settings.replicas.replica_id();
        // several replicas on PostgreSQL: fields are leased; on SQLite this
        // process runs every field
        let leases = match (&settings.storage.url, store.kind()) {
            (Some(url), "postgres") => {
                // the database lease is ¾ of lease_s, renewed every quarter
                // of that: a dead replica's fields are taken within lease_s
                let lease = settings.replicas.wall_lease(clock.speedup()).mul_f64(0.75);
                let pool = replicas::pool(url, lease).map_err(|e| ServeError::Io(e.to_string()))?;
                Some(Arc::new(replicas::Leases::new(
                    pool,
                    replica.clone(),
                    lease,
                )))
            }
            _ => None,
        };
        tracing::info!(replica = %replica, storage = store.kind(), "storage open");
        let engine = Arc::new(
            Engine::new(store, models)
                .forecast_settings(settings.forecasts.clone())
                .catch_up_limit(settings.limits.max_catch_up_s)
                .late_window(settings.limits.late_window_s)
                .own_models(own_models)
                .defer_estimates(true),
        );
        let metrics = Metrics::new();
        let deferred = deferred::Deferred::start(
            engine.clone(),
            replica.clone(),
            settings.limits.worker_threads,
            metrics.estimates_deferred.clone(),
            metrics.estimates_pending.clone(),
        );
        let state = Arc::new(AppState {
            engine,
            deferred,
            training,
            mqtt,
            clock,
            metrics,
            token,
            replica,
            leases,
            running: Mutex::new(std::collections::HashSet::new()),
            rebalance: tokio::sync::Notify::new(),
            permits: Arc::new(Semaphore::new(settings.limits.worker_threads)),
            clock_saved: Mutex::new(None),
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
        state
            .metrics
            .replica
            .with_label_values(&[state.replica.as_str(), state.engine.store.kind()])
            .set(1.0);
        state.metrics.database_up.set(1);
        match state.leases.clone() {
            // every field's first cycle runs now, then at its period boundaries
            None => {
                for field in state.engine.store.fields()? {
                    spawn_field(&state, &field, Start::Now);
                }
            }
            // the fields this replica leases, as it gains them
            Some(leases) => {
                let s = state.clone();
                state
                    .tracker
                    .spawn(async move { lease_loop(s, leases).await });
                listen_for_changes(&state);
            }
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
        state.deferred.stop();
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
        if let Some(leases) = &state.leases {
            // the others take this replica's fields at their next tick
            if let Err(e) = leases.release_all().await {
                tracing::warn!(error = %e, "leases not released; they expire");
            }
        }
        result.map_err(|e| ServeError::Io(format!("server: {e}")))
    }
}

/// Starts the scheduled tasks of a new field: its control loop and, for a
/// simulated field, its plant (on PostgreSQL: on the replica that gains its
/// lease, asked to look now).
pub(crate) fn start_field(state: &Arc<AppState>, field: &Field) {
    if let Some(mqtt) = &state.mqtt {
        mqtt.announce(state, field);
    }
    match &state.leases {
        None => spawn_field(state, field, Start::Wait),
        Some(_) => {
            if !state.holds(field.id) {
                // the first cycle ran here: the holder's plant is the one
                state.engine.forget(field.id);
            }
            state.rebalance.notify_one();
        }
    }
}

/// How a field's control loop begins.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Start {
    /// A cycle now (the daemon's start on SQLite).
    Now,
    /// At the next boundary (a new field has had its first cycle).
    Wait,
    /// This replica gained the field's lease: the latest boundary's cycle
    /// now if no replica has run it, then the next boundaries.
    CatchUp,
}

/// The lease loop of a replica on PostgreSQL: every quarter lease (or when
/// a field changes) it renews, gains and releases leases
/// ([`replicas::Leases::tick`]) and starts or stops the fields' tasks to
/// match. When the database is lost the ticks fail, the leases lapse
/// before the database would give them to another replica, and the
/// fields' loops skip their cycles (`holds` is false) until it returns.
async fn lease_loop(state: Arc<AppState>, leases: Arc<replicas::Leases>) {
    let m = &state.metrics;
    m.replica
        .with_label_values(&[state.replica.as_str(), "postgres"])
        .set(1.0);
    loop {
        let engine = state.engine.clone();
        let fields = tokio::task::spawn_blocking(move || engine.store.fields())
            .await
            .ok()
            .and_then(Result::ok);
        match fields {
            Some(fields) => {
                let ids: Vec<i64> = fields.iter().map(|f| f.id).collect();
                let busy = state
                    .running
                    .lock()
                    .unwrap_or_else(|p| p.into_inner())
                    .clone();
                match leases.tick(&ids, &busy).await {
                    Ok(change) => {
                        m.database_up.set(1);
                        for id in &change.lost {
                            stop_field(&state, *id);
                        }
                        for id in &change.gained {
                            if let Some(f) = fields.iter().find(|f| f.id == *id) {
                                // a plant another replica moved on: reread
                                state.engine.forget(*id);
                                spawn_field(&state, f, Start::CatchUp);
                            }
                        }
                        if !change.gained.is_empty() || !change.lost.is_empty() {
                            tracing::info!(
                                gained = change.gained.len(),
                                lost = change.lost.len(),
                                held = change.held.len(),
                                "leases"
                            );
                        }
                    }
                    Err(e) => {
                        m.database_up.set(0);
                        tracing::warn!(error = %e, "lease renewal failed; cycles pause when the leases lapse");
                    }
                }
            }
            None => {
                m.database_up.set(0);
                tracing::warn!("the database is unavailable; cycles pause when the leases lapse");
            }
        }
        let status = leases.status();
        m.leases_held.set(status.held as i64);
        m.lease_age_seconds
            .set(status.last_renewal_age_s.unwrap_or(f64::NAN));
        tokio::select! {
            _ = tokio::time::sleep(leases.tick_interval()) => {}
            _ = state.rebalance.notified() => {}
            _ = state.shutdown.cancelled() => return,
        }
    }
}

/// Forwards the database's notifications: stored measurements wake the
/// cycle waiting for them on this replica, changed fields the lease loop.
fn listen_for_changes(state: &Arc<AppState>) {
    const CHANNELS: &[&str] = &[store::CHANNEL_MEASURED, store::CHANNEL_FIELDS];
    let Some(config) = state
        .settings
        .storage
        .url
        .as_deref()
        .and_then(|u| u.parse::<tokio_postgres::Config>().ok())
    else {
        return;
    };
    let s = state.clone();
    let on = move |channel: &str, payload: &str| {
        if payload.is_empty() {
            // reconnected: whatever was missed, everyone checks again
            let waiting: Vec<_> = s
                .measured
                .lock()
                .unwrap_or_else(|p| p.into_inner())
                .values()
                .cloned()
                .collect();
            for n in waiting {
                n.notify_waiters();
            }
            s.rebalance.notify_one();
        } else if channel == store::CHANNEL_MEASURED {
            if let Ok(id) = payload.parse::<i64>() {
                s.measured(id).notify_waiters();
            }
        } else {
            s.rebalance.notify_one();
        }
    };
    let cancel = state.shutdown.clone();
    state
        .tracker
        .spawn(async move { replicas::listen(config, CHANNELS, on, cancel).await });
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

fn spawn_field(state: &Arc<AppState>, field: &Field, start: Start) {
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
        .spawn(async move { control_loop(s, id, t, start).await });
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
async fn control_loop(state: Arc<AppState>, id: i64, cancel: CancellationToken, start: Start) {
    if start == Start::Now
        && let Ok(Some(field)) = state.engine.store.field(id)
    {
        tokio::select! {
            _ = first_cycle(&state, &field) => {}
            _ = cancel.cancelled() => return,
        }
    }
    // the boundary this task last came to, to see one it slept through
    let mut last: Option<DateTime<Utc>> = None;
    if start == Start::CatchUp {
        // a boundary that passes while the catch-up looks (its store
        // reads take clock time, much of it on an accelerated clock) is
        // one it did not see: the loop's first turn sees it through `last`
        if let Ok(Some(field)) = state.engine.store.field(id) {
            last = Some(clock::boundary_at_or_before(
                state.clock.now(),
                field.spec.control_period_s,
            ));
        }
        tokio::select! {
            _ = catch_up(&state, id) => {}
            _ = cancel.cancelled() => return,
        }
    }
    loop {
        let Ok(Some(field)) = state.engine.store.field(id) else {
            return;
        };
        let period = field.spec.control_period_s;
        // a cycle that outlasted a period (an overloaded machine, a slow
        // database) left boundaries behind: run those no replica has run,
        // oldest first, as a gained field does, before waiting for the next
        if let Some(last) = last
            && clock::boundary_at_or_before(state.clock.now(), period) > last
            && state.holds(id)
        {
            tokio::select! {
                _ = catch_up(&state, id) => {}
                _ = cancel.cancelled() => return,
            }
        }
        let next = clock::next_boundary(state.clock.now(), period);
        tokio::select! {
            _ = state.clock.sleep_until(next) => {}
            _ = cancel.cancelled() => return,
        }
        last = Some(next);
        if field.spec.actuator != Actuator::Simulated {
            let wait =
                TimeDelta::milliseconds((field.spec.effective_measurement_wait() * 1000.0) as i64);
            tokio::select! {
                _ = measurement_at(&state, id, next, next + wait) => {}
                _ = cancel.cancelled() => return,
            }
        }
        if !state.holds(id) {
            // the lease lapsed (the database is lost) or moved: no cycle
            tracing::warn!(field = id, at = %next, "cycle skipped: this replica's lease has lapsed");
            continue;
        }
        if let Err(e) = run_cycle(&state, field, next, true).await {
            tracing::warn!(field = id, at = %next, error = %e, "control cycle failed");
        }
    }
}

/// Most boundaries a gained field catches up on (newest first, each one no
/// replica has run): a bound on the work a lease move can start.
const CATCH_UP_BOUNDARIES: usize = 12;

/// What a gained field has to catch up on.
enum Due {
    /// No setpoint yet: its first cycle.
    First(Field),
    /// The boundaries since its last cycle that no replica has run,
    /// oldest first (at most [`CATCH_UP_BOUNDARIES`]).
    Missed(Field, Vec<DateTime<Utc>>),
}

/// A gained field's first cycle, if it has had none; else every boundary
/// since its last cycle that no replica has run, oldest first (the replica
/// that held the field died before, or during, those cycles; boundaries
/// can pass while this one catches up, so it looks again until none is
/// left); a boundary before the field existed is not one of its cycles.
async fn catch_up(state: &Arc<AppState>, id: i64) {
    // a field created within the last lease gets its first cycle from the
    // replica that created it (in the request): this one waits that long
    // before it looks for one
    let lease = state.settings.replicas.lease_s;
    let created = state
        .engine
        .store
        .field(id)
        .ok()
        .flatten()
        .map(|f| f.created_at);
    if let Some(created) = created {
        let settled = clock::add_seconds(created, lease);
        if state.clock.now() < settled {
            state.clock.sleep_until(settled).await;
        }
    }
    // each round runs what it found; one more finds nothing (or what
    // passed meanwhile)
    for _ in 0..3 {
        let engine = state.engine.clone();
        let now = state.clock.now();
        let due = tokio::task::spawn_blocking(move || -> Result<Option<Due>, store::StoreError> {
            let Some(field) = engine.store.field(id)? else {
                return Ok(None);
            };
            if engine.store.recent_setpoints(id, 1)?.is_empty() {
                return Ok(Some(Due::First(field)));
            }
            let period = field.spec.control_period_s;
            let mut boundary = clock::boundary_at_or_before(now, period);
            let mut missed = Vec::new();
            while missed.len() < CATCH_UP_BOUNDARIES
                && boundary >= field.created_at
                && engine.store.cycle_runs(id, boundary, boundary)?.is_empty()
            {
                missed.push(boundary);
                boundary = clock::add_seconds(boundary, -period);
            }
            missed.reverse();
            Ok(Some(Due::Missed(field, missed)))
        })
        .await;
        if !state.holds(id) {
            return;
        }
        match due {
            Ok(Ok(Some(Due::First(field)))) => {
                first_cycle(state, &field).await;
                return;
            }
            Ok(Ok(Some(Due::Missed(field, missed)))) if !missed.is_empty() => {
                for boundary in missed {
                    if !state.holds(id) {
                        return;
                    }
                    tracing::info!(field = id, at = %boundary, "catching up a boundary no replica has run");
                    if let Err(e) = run_cycle(state, field.clone(), boundary, true).await {
                        tracing::warn!(field = id, at = %boundary, error = %e, "catch-up cycle failed");
                    }
                }
            }
            _ => return,
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
    let permit = state
        .permits
        .clone()
        .acquire_owned()
        .await
        .map_err(|e| e.to_string())?;
    let _busy = Busy::mark(state, field.id);
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
    // the permit bounds the cycles' computing, not their publishing
    drop(permit);
    let (setpoint, previous, theta) = match decided {
        Ok(Ok(Some(done))) => {
            if done.estimate_deferred {
                state.deferred.push(field.clone(), at);
            }
            (done.setpoint, done.previous, done.theta)
        }
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
    if scheduled {
        let late = (state.clock.now() - at).as_seconds_f64() / state.clock.speedup();
        state.metrics.cycle_lateness_seconds.observe(late.max(0.0));
    }
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
    if let Some(previous) = &previous {
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
    if let Some(theta) = theta {
        m.theta.with_label_values(&[label.as_str()]).set(theta);
    }
    save_clock(state).await;
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

/// Least wall time between two cycles' stores of the clock's time.
const CLOCK_SAVE_INTERVAL: std::time::Duration = std::time::Duration::from_secs(1);

/// Stores the clock's time after a cycle, so that an accelerated clock
/// resumes from about there after a crash (a clean stop stores it again).
/// At most once per [`CLOCK_SAVE_INTERVAL`]: the fields' cycles of a
/// boundary share one row, and one write per field would queue them all
/// on its lock.
async fn save_clock(state: &Arc<AppState>) {
    {
        let mut last = state.clock_saved.lock().unwrap_or_else(|e| e.into_inner());
        if last.is_some_and(|t| t.elapsed() < CLOCK_SAVE_INTERVAL) {
            return;
        }
        *last = Some(std::time::Instant::now());
    }
    let engine = state.engine.clone();
    let now = state.clock.now().to_rfc3339();
    let _ = tokio::task::spawn_blocking(move || engine.store.set_meta("clock", &now)).await;
}

/// Marks a field's cycle as running while it lives.
struct Busy<'a> {
    state: &'a AppState,
    id: i64,
}

impl<'a> Busy<'a> {
    fn mark(state: &'a AppState, id: i64) -> Busy<'a> {
        state
            .running
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .insert(id);
        Busy { state, id }
    }
}

impl Drop for Busy<'_> {
    fn drop(&mut self) {
        self.state
            .running
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .remove(&self.id);
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
