//! The shared backend: PostgreSQL through tokio-postgres with a
//! deadpool pool. The same tables as the SQLite file (times as BIGINT
//! milliseconds, documents as JSON text), plus the replicas' leases.
//!
//! The store's interface is synchronous; this backend runs its queries on a
//! two-thread tokio runtime of its own and waits for them, so it can be
//! called from the daemon's blocking pool, the CLI and the tests alike.
//! Every operation is bounded: the pool's wait and connect timeouts and an
//! overall deadline turn a dead or unreachable server into
//! [`StoreError::Unavailable`] within seconds, never a hang.
//!
//! Stored measurements and changed fields are announced with `NOTIFY`
//! (channels [`CHANNEL_MEASURED`] and [`CHANNEL_FIELDS`], the field id as
//! payload), delivered at commit to every replica that listens.

use std::collections::HashMap;
use std::future::Future;
use std::pin::Pin;
use std::time::Duration;

use chrono::{DateTime, Utc};
use deadpool_postgres::{Manager, ManagerConfig, Pool, RecyclingMethod, Runtime};
use tokio_postgres::NoTls;
use tokio_postgres::error::SqlState;

use super::copy::{self, Cell, Kind, Table};
use super::{
    CYCLE_FORECASTS, CYCLE_SETPOINTS, CycleOutputs, CycleQuery, CycleRead, ReadingOutcome, Sensors,
    StoreError, millis, setpoint_of, time,
};
use crate::service::wire::{Field, FieldSpec, Forecast, Measurement, Setpoint};

/// Notified with a field's id when measurements of it are stored.
pub const CHANNEL_MEASURED: &str = "rootzone_measured";
/// Notified with a field's id when it is created, changed or deleted.
pub const CHANNEL_FIELDS: &str = "rootzone_fields";

/// The schema, one migration per entry; entry i brings the database to
/// version i + 1 (recorded in `schema_version`).
const MIGRATIONS: &[&str] = &[
    "CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
     CREATE TABLE fields (
         id BIGSERIAL PRIMARY KEY,
         created_at BIGINT NOT NULL,
         spec TEXT NOT NULL);
     CREATE UNIQUE INDEX fields_by_name ON fields (((spec::jsonb) ->> 'name'));
     CREATE TABLE measurements (
         id BIGSERIAL PRIMARY KEY,
         field_id BIGINT NOT NULL REFERENCES fields(id) ON DELETE CASCADE,
         time BIGINT NOT NULL,
         theta DOUBLE PRECISION NOT NULL,
         sensor TEXT,
         true_theta DOUBLE PRECISION,
         raw DOUBLE PRECISION);
     CREATE UNIQUE INDEX measurements_once ON measurements (field_id, time, COALESCE(sensor, ''));
     CREATE TABLE forecasts (
         id BIGSERIAL PRIMARY KEY,
         field_id BIGINT NOT NULL REFERENCES fields(id) ON DELETE CASCADE,
         issued_at BIGINT NOT NULL,
         body TEXT NOT NULL);
     CREATE INDEX forecasts_by_field ON forecasts(field_id, id);
     CREATE TABLE setpoints (
         id BIGSERIAL PRIMARY KEY,
         field_id BIGINT NOT NULL REFERENCES fields(id) ON DELETE CASCADE,
         time BIGINT NOT NULL,
         body TEXT NOT NULL);
     CREATE INDEX setpoints_by_time ON setpoints(field_id, time);
     CREATE TABLE simulations (
         field_id BIGINT PRIMARY KEY REFERENCES fields(id) ON DELETE CASCADE,
         body TEXT NOT NULL);
     CREATE TABLE estimates (
         field_id BIGINT PRIMARY KEY REFERENCES fields(id) ON DELETE CASCADE,
         body TEXT NOT NULL);
     CREATE TABLE forecast_sources (key TEXT PRIMARY KEY, body TEXT NOT NULL);
     CREATE TABLE cycle_runs (
         field_id BIGINT NOT NULL REFERENCES fields(id) ON DELETE CASCADE,
         boundary BIGINT NOT NULL,
         replica TEXT NOT NULL,
         done_at TIMESTAMPTZ NOT NULL DEFAULT clock_timestamp(),
         PRIMARY KEY (field_id, boundary));",
    // the replicas and their leases of fields
    crate::service::replicas::SCHEMA,
];

/// The schema version this binary brings a database to.
pub(super) const VERSION: usize = MIGRATIONS.len();

/// The longest any one operation may take, waiting for a connection
/// included.
const DEADLINE: Duration = Duration::from_secs(20);

/// Any one migration's advisory lock key (replicas starting together
/// migrate one after the other).
const MIGRATION_LOCK: i64 = 0x726f_6f74_7a6f_6e65;

type BoxFuture<'a, T> = Pin<Box<dyn Future<Output = T> + Send + 'a>>;

pub(super) struct Postgres {
    rt: Option<tokio::runtime::Runtime>,
    pool: Pool,
}

/// A driver error: one the server answered (a statement failed) or one of
/// the connection (the server cannot be reached).
fn pg(e: tokio_postgres::Error) -> StoreError {
    match e.as_db_error() {
        Some(db) => StoreError::Postgres(format!("{} ({})", db.message(), db.code().code())),
        None if e.is_closed() || e.code().is_none() => StoreError::Unavailable(e.to_string()),
        None => StoreError::Postgres(e.to_string()),
    }
}

fn pool_err(e: deadpool_postgres::PoolError) -> StoreError {
    match e {
        deadpool_postgres::PoolError::Backend(e) => match pg(e) {
            StoreError::Postgres(m) => StoreError::Unavailable(m),
            other => other,
        },
        e => StoreError::Unavailable(e.to_string()),
    }
}

fn is_unique_violation(e: &tokio_postgres::Error) -> bool {
    e.code() == Some(&SqlState::UNIQUE_VIOLATION)
}

fn measurement_of(r: &tokio_postgres::Row) -> Measurement {
    Measurement {
        time: time(r.get(0)),
        theta: r.get(1),
        sensor: r.get(2),
        true_theta: r.get(3),
        raw: r.get(4),
    }
}

impl Postgres {
    /// Connects to `url`, checks the schema's version and migrates.
    pub(super) fn connect(url: &str) -> Result<Postgres, StoreError> {
        let shown = super::redact(url);
        let mut config: tokio_postgres::Config = url
            .parse()
            .map_err(|e| StoreError::Io(format!("storage.url '{shown}': {e}")))?;
        config
            .connect_timeout(Duration::from_secs(3))
            .keepalives(true)
            .keepalives_idle(Duration::from_secs(10))
            .tcp_user_timeout(Duration::from_secs(10));
        if config.get_application_name().is_none() {
            config.application_name("rootzone");
        }
        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .thread_name("rootzone-postgres")
            .enable_all()
            .build()
            .map_err(|e| StoreError::Io(format!("cannot start the database runtime: {e}")))?;
        let manager = Manager::from_config(
            config,
            NoTls,
            ManagerConfig {
                recycling_method: RecyclingMethod::Fast,
            },
        );
        let pool = {
            let _guard = rt.enter();
            Pool::builder(manager)
                .max_size(16)
                .runtime(Runtime::Tokio1)
                .wait_timeout(Some(Duration::from_secs(5)))
                .create_timeout(Some(Duration::from_secs(5)))
                .recycle_timeout(Some(Duration::from_secs(3)))
                .build()
                .map_err(|e| StoreError::Io(format!("storage.url '{shown}': {e}")))?
        };
        let store = Postgres { rt: Some(rt), pool };
        store.migrate().map_err(|e| match e {
            StoreError::Unavailable(m) => {
                StoreError::Unavailable(format!("cannot connect to {shown}: {m}"))
            }
            e => e,
        })?;
        Ok(store)
    }

    /// Runs `f` with a pooled connection on the backend's runtime and waits
    /// for it, at most [`DEADLINE`].
    fn run<T, F>(&self, f: F) -> Result<T, StoreError>
    where
        T: Send + 'static,
        F: for<'c> FnOnce(
                &'c mut deadpool_postgres::Client,
            ) -> BoxFuture<'c, Result<T, StoreError>>
            + Send
            + 'static,
    {
        let pool = self.pool.clone();
        let (tx, rx) = std::sync::mpsc::sync_channel(1);
        let rt = self
            .rt
            .as_ref()
            .expect("the runtime lives as long as the store");
        rt.spawn(async move {
            let work = async {
                let mut client = pool.get().await.map_err(pool_err)?;
                f(&mut client).await
            };
            let result = match tokio::time::timeout(DEADLINE, work).await {
                Ok(r) => r,
                Err(_) => Err(StoreError::Unavailable(format!(
                    "no answer within {} s",
                    DEADLINE.as_secs()
                ))),
            };
            let _ = tx.send(result);
        });
        rx.recv()
            .unwrap_or_else(|_| Err(StoreError::Unavailable("the database task ended".into())))
    }

    fn migrate(&self) -> Result<(), StoreError> {
        self.run(|c| {
            Box::pin(async move {
                let tx = c.transaction().await.map_err(pg)?;
                tx.execute("SELECT pg_advisory_xact_lock($1)", &[&MIGRATION_LOCK])
                    .await
                    .map_err(pg)?;
                tx.batch_execute(
                    "CREATE TABLE IF NOT EXISTS schema_version (version INTEGER NOT NULL)",
                )
                .await
                .map_err(pg)?;
                let row = tx
                    .query_opt("SELECT max(version) FROM schema_version", &[])
                    .await
                    .map_err(pg)?;
                let version = row.and_then(|r| r.get::<_, Option<i32>>(0)).unwrap_or(0);
                if version as usize > VERSION {
                    return Err(StoreError::Schema(format!(
                        "the database's schema is version {version}, newer than this binary's \
                         version {VERSION}; run the rootzone release that wrote it (or a newer one)"
                    )));
                }
                for (i, sql) in MIGRATIONS.iter().enumerate().skip(version.max(0) as usize) {
                    tx.batch_execute(sql).await.map_err(pg)?;
                    tx.execute("DELETE FROM schema_version", &[])
                        .await
                        .map_err(pg)?;
                    tx.execute(
                        "INSERT INTO schema_version(version) VALUES ($1)",
                        &[&((i + 1) as i32)],
                    )
                    .await
                    .map_err(pg)?;
                }
                tx.commit().await.map_err(pg)?;
                Ok(())
            })
        })
    }

    pub(super) fn ping(&self) -> Result<(), StoreError> {
        self.run(|c| {
            Box::pin(async move {
                c.simple_query("SELECT 1").await.map_err(pg)?;
                Ok(())
            })
        })
    }

    pub(super) fn meta(&self, key: &str) -> Result<Option<String>, StoreError> {
        let key = key.to_string();
        self.run(move |c| {
            Box::pin(async move {
                let row = c
                    .query_opt("SELECT value FROM meta WHERE key = $1", &[&key])
                    .await
                    .map_err(pg)?;
                Ok(row.map(|r| r.get(0)))
            })
        })
    }

    pub(super) fn set_meta(&self, key: &str, value: &str) -> Result<(), StoreError> {
        let (key, value) = (key.to_string(), value.to_string());
        self.run(move |c| {
            Box::pin(async move {
                c.execute(
                    "INSERT INTO meta(key, value) VALUES ($1, $2)
                     ON CONFLICT(key) DO UPDATE SET value = excluded.value",
                    &[&key, &value],
                )
                .await
                .map_err(pg)?;
                Ok(())
            })
        })
    }

    pub(super) fn create_field(
        &self,
        spec: &FieldSpec,
        now: DateTime<Utc>,
    ) -> Result<Field, StoreError> {
        let body = serde_json::to_string(spec)?;
        let spec = spec.clone();
        self.run(move |c| {
            Box::pin(async move {
                let tx = c.transaction().await.map_err(pg)?;
                let row = tx
                    .query_one(
                        "INSERT INTO fields(created_at, spec) VALUES ($1, $2) RETURNING id",
                        &[&millis(now), &body],
                    )
                    .await
                    .map_err(|e| {
                        if is_unique_violation(&e) {
                            StoreError::Conflict(format!("a field named '{}' exists", spec.name))
                        } else {
                            pg(e)
                        }
                    })?;
                let id: i64 = row.get(0);
                notify(&tx, CHANNEL_FIELDS, id).await?;
                tx.commit().await.map_err(pg)?;
                Ok(Field {
                    id,
                    created_at: time(millis(now)),
                    spec,
                })
            })
        })
    }

    pub(super) fn fields(&self) -> Result<Vec<Field>, StoreError> {
        self.run(|c| {
            Box::pin(async move {
                let rows = c
                    .query("SELECT id, created_at, spec FROM fields ORDER BY id", &[])
                    .await
                    .map_err(pg)?;
                rows.iter()
                    .map(|r| {
                        Ok(Field {
                            id: r.get(0),
                            created_at: time(r.get(1)),
                            spec: serde_json::from_str(r.get::<_, &str>(2))?,
                        })
                    })
                    .collect()
            })
        })
    }

    pub(super) fn field(&self, id: i64) -> Result<Option<Field>, StoreError> {
        self.run(move |c| {
            Box::pin(async move {
                let row = c
                    .query_opt("SELECT created_at, spec FROM fields WHERE id = $1", &[&id])
                    .await
                    .map_err(pg)?;
                match row {
                    None => Ok(None),
                    Some(r) => Ok(Some(Field {
                        id,
                        created_at: time(r.get(0)),
                        spec: serde_json::from_str(r.get::<_, &str>(1))?,
                    })),
                }
            })
        })
    }

    pub(super) fn update_field(&self, id: i64, spec: &FieldSpec) -> Result<bool, StoreError> {
        let body = serde_json::to_string(spec)?;
        let name = spec.name.clone();
        self.run(move |c| {
            Box::pin(async move {
                let tx = c.transaction().await.map_err(pg)?;
                let n = tx
                    .execute("UPDATE fields SET spec = $2 WHERE id = $1", &[&id, &body])
                    .await
                    .map_err(|e| {
                        if is_unique_violation(&e) {
                            StoreError::Conflict(format!("a field named '{name}' exists"))
                        } else {
                            pg(e)
                        }
                    })?;
                notify(&tx, CHANNEL_FIELDS, id).await?;
                tx.commit().await.map_err(pg)?;
                Ok(n == 1)
            })
        })
    }

    pub(super) fn delete_field(&self, id: i64) -> Result<bool, StoreError> {
        self.run(move |c| {
            Box::pin(async move {
                let tx = c.transaction().await.map_err(pg)?;
                let n = tx
                    .execute("DELETE FROM fields WHERE id = $1", &[&id])
                    .await
                    .map_err(pg)?;
                notify(&tx, CHANNEL_FIELDS, id).await?;
                tx.commit().await.map_err(pg)?;
                Ok(n == 1)
            })
        })
    }

    pub(super) fn add_measurements(
        &self,
        field: i64,
        batch: &[Measurement],
    ) -> Result<usize, StoreError> {
        // a (time, sensor) twice in the batch: once with the same θ, a
        // conflict with another (as the SQLite backend, row by row)
        let mut first: HashMap<(i64, Option<&str>), f64> = HashMap::new();
        let mut rows: Vec<(usize, &Measurement)> = Vec::with_capacity(batch.len());
        for (i, m) in batch.iter().enumerate() {
            match first.get(&(millis(m.time), m.sensor.as_deref())) {
                Some(&theta) if theta == m.theta => {}
                Some(&theta) => return Err(conflict_at(i, field, theta, m)),
                None => {
                    first.insert((millis(m.time), m.sensor.as_deref()), m.theta);
                    rows.push((i, m));
                }
            }
        }
        let index: Vec<i64> = (0..rows.len() as i64).collect();
        let times: Vec<i64> = rows.iter().map(|(_, m)| millis(m.time)).collect();
        let thetas: Vec<f64> = rows.iter().map(|(_, m)| m.theta).collect();
        let sensors: Vec<Option<String>> = rows.iter().map(|(_, m)| m.sensor.clone()).collect();
        let truths: Vec<Option<f64>> = rows.iter().map(|(_, m)| m.true_theta).collect();
        let raws: Vec<Option<f64>> = rows.iter().map(|(_, m)| m.raw).collect();
        let positions: Vec<usize> = rows.iter().map(|(i, _)| *i).collect();
        let owned: Vec<Measurement> = rows.iter().map(|(_, m)| (*m).clone()).collect();
        self.run(move |c| {
            Box::pin(async move {
                let tx = c.transaction().await.map_err(pg)?;
                let new = tx
                    .execute(
                        "INSERT INTO measurements(field_id, time, theta, sensor, true_theta, raw)
                         SELECT $1, b.time, b.theta, b.sensor, b.true_theta, b.raw
                         FROM unnest($2::bigint[], $3::float8[], $4::text[], $5::float8[], $6::float8[])
                              AS b(time, theta, sensor, true_theta, raw)
                         ON CONFLICT DO NOTHING",
                        &[&field, &times, &thetas, &sensors, &truths, &raws],
                    )
                    .await
                    .map_err(pg)?;
                // what was there already, with another θ, refuses the batch
                let clash = tx
                    .query_opt(
                        "SELECT b.i, m.theta FROM unnest($2::bigint[], $3::float8[], $4::text[], $5::bigint[])
                              AS b(time, theta, sensor, i)
                         JOIN measurements m ON m.field_id = $1 AND m.time = b.time
                              AND COALESCE(m.sensor, '') = COALESCE(b.sensor, '')
                         WHERE m.theta <> b.theta ORDER BY b.i LIMIT 1",
                        &[&field, &times, &thetas, &sensors, &index],
                    )
                    .await
                    .map_err(pg)?;
                if let Some(r) = clash {
                    let i = r.get::<_, i64>(0) as usize;
                    return Err(conflict_at(positions[i], field, r.get(1), &owned[i]));
                }
                if new > 0 {
                    notify(&tx, CHANNEL_MEASURED, field).await?;
                }
                tx.commit().await.map_err(pg)?;
                Ok(new as usize)
            })
        })
    }

    pub(super) fn add_readings(
        &self,
        readings: &[(i64, Measurement)],
    ) -> Result<Vec<ReadingOutcome>, StoreError> {
        let readings = readings.to_vec();
        self.run(move |c| {
            Box::pin(async move {
                let tx = c.transaction().await.map_err(pg)?;
                let existing = tx
                    .prepare_cached(
                        "SELECT theta FROM measurements
                         WHERE field_id = $1 AND time = $2 AND COALESCE(sensor, '') = COALESCE($3, '')",
                    )
                    .await
                    .map_err(pg)?;
                let insert = tx
                    .prepare_cached(
                        "INSERT INTO measurements(field_id, time, theta, sensor, true_theta, raw)
                         SELECT $1, $2, $3, $4, $5, $6 WHERE EXISTS (SELECT 1 FROM fields WHERE id = $1)",
                    )
                    .await
                    .map_err(pg)?;
                let mut outcomes = Vec::with_capacity(readings.len());
                let mut touched = std::collections::BTreeSet::new();
                for (field, m) in &readings {
                    let t = millis(m.time);
                    let stored = tx
                        .query_opt(&existing, &[field, &t, &m.sensor])
                        .await
                        .map_err(pg)?;
                    outcomes.push(match stored {
                        Some(r) if r.get::<_, f64>(0) == m.theta => ReadingOutcome::Duplicate,
                        Some(r) => ReadingOutcome::Conflict(r.get(0)),
                        None => {
                            let n = tx
                                .execute(
                                    &insert,
                                    &[field, &t, &m.theta, &m.sensor, &m.true_theta, &m.raw],
                                )
                                .await
                                .map_err(pg)?;
                            if n == 1 {
                                touched.insert(*field);
                                ReadingOutcome::Stored
                            } else {
                                ReadingOutcome::NoField
                            }
                        }
                    });
                }
                for field in touched {
                    notify(&tx, CHANNEL_MEASURED, field).await?;
                }
                tx.commit().await.map_err(pg)?;
                Ok(outcomes)
            })
        })
    }

    pub(super) fn measurements(
        &self,
        field: i64,
        from: Option<DateTime<Utc>>,
        to: Option<DateTime<Utc>>,
        limit: usize,
        sensors: Sensors,
    ) -> Result<Vec<Measurement>, StoreError> {
        self.run(move |c| {
            Box::pin(async move { read::measurements(&*c, field, from, to, limit, sensors).await })
        })
    }

    pub(super) fn measurement_before(
        &self,
        field: i64,
        at: DateTime<Utc>,
    ) -> Result<Option<Measurement>, StoreError> {
        self.run(move |c| Box::pin(async move { read::measurement_before(&*c, field, at).await }))
    }

    pub(super) fn count_measurements(&self, field: i64) -> Result<u64, StoreError> {
        self.run(move |c| {
            Box::pin(async move {
                let row = c
                    .query_one(
                        "SELECT COUNT(*) FROM measurements WHERE field_id = $1",
                        &[&field],
                    )
                    .await
                    .map_err(pg)?;
                Ok(row.get::<_, i64>(0) as u64)
            })
        })
    }

    pub(super) fn put_forecast(&self, field: i64, forecast: &Forecast) -> Result<(), StoreError> {
        let body = serde_json::to_string(forecast)?;
        let issued = millis(forecast.issued_at);
        self.run(move |c| {
            Box::pin(async move {
                c.execute(
                    "INSERT INTO forecasts(field_id, issued_at, body) VALUES ($1, $2, $3)",
                    &[&field, &issued, &body],
                )
                .await
                .map_err(pg)?;
                Ok(())
            })
        })
    }

    pub(super) fn latest_forecast(&self, field: i64) -> Result<Option<Forecast>, StoreError> {
        self.run(move |c| Box::pin(async move { read::latest_forecast(&*c, field).await }))
    }

    pub(super) fn forecasts_since(
        &self,
        field: i64,
        from: DateTime<Utc>,
        limit: usize,
    ) -> Result<Vec<Forecast>, StoreError> {
        self.run(move |c| {
            Box::pin(async move { read::forecasts_since(&*c, field, from, limit).await })
        })
    }

    pub(super) fn commit_cycle(&self, out: &CycleOutputs<'_>) -> Result<bool, StoreError> {
        let body = serde_json::to_string(out.setpoint)?;
        let field = out.setpoint.field_id;
        let at = millis(out.setpoint.time);
        let estimate = out.estimate.map(str::to_string);
        let run = out.run.map(|r| (millis(r.boundary), r.replica.to_string()));
        self.run(move |c| {
            Box::pin(async move {
                let tx = c.transaction().await.map_err(pg)?;
                if let Some((boundary, replica)) = &run {
                    // only the holder of a live lease, and only once
                    let n = tx
                        .execute(
                            "INSERT INTO cycle_runs(field_id, boundary, replica)
                             SELECT $1, $2, $3 WHERE EXISTS (
                                 SELECT 1 FROM leases WHERE field_id = $1 AND holder = $3
                                 AND expires_at > clock_timestamp())
                             ON CONFLICT DO NOTHING",
                            &[&field, boundary, replica],
                        )
                        .await
                        .map_err(pg)?;
                    if n == 0 {
                        return Ok(false);
                    }
                }
                if let Some(estimate) = &estimate {
                    tx.execute(
                        "INSERT INTO estimates(field_id, body) VALUES ($1, $2)
                         ON CONFLICT(field_id) DO UPDATE SET body = excluded.body",
                        &[&field, estimate],
                    )
                    .await
                    .map_err(pg)?;
                }
                tx.execute(
                    "INSERT INTO setpoints(field_id, time, body) VALUES ($1, $2, $3)",
                    &[&field, &at, &body],
                )
                .await
                .map_err(pg)?;
                tx.commit().await.map_err(pg)?;
                Ok(true)
            })
        })
    }

    pub(super) fn cycle_runs(
        &self,
        field: i64,
        from: DateTime<Utc>,
        to: DateTime<Utc>,
    ) -> Result<Vec<DateTime<Utc>>, StoreError> {
        let (from, to) = (millis(from), millis(to));
        self.run(move |c| {
            Box::pin(async move {
                let rows = c
                    .query(
                        "SELECT boundary FROM cycle_runs WHERE field_id = $1 AND boundary >= $2
                         AND boundary <= $3 ORDER BY boundary",
                        &[&field, &from, &to],
                    )
                    .await
                    .map_err(pg)?;
                Ok(rows.iter().map(|r| time(r.get(0))).collect())
            })
        })
    }

    pub(super) fn setpoints(
        &self,
        field: i64,
        from: Option<DateTime<Utc>>,
        to: Option<DateTime<Utc>>,
        limit: usize,
    ) -> Result<Vec<Setpoint>, StoreError> {
        self.run(move |c| {
            Box::pin(async move { read::setpoints(&*c, field, from, to, limit).await })
        })
    }

    pub(super) fn recent_setpoints(
        &self,
        field: i64,
        n: usize,
    ) -> Result<Vec<Setpoint>, StoreError> {
        self.run(move |c| Box::pin(async move { read::recent_setpoints(&*c, field, n).await }))
    }

    /// One cycle's inputs: one read-only repeatable-read transaction, its
    /// statements sent together (pipelined) on its connection.
    pub(super) fn cycle_read(&self, q: &CycleQuery) -> Result<CycleRead, StoreError> {
        let q = q.clone();
        self.run(move |c| {
            Box::pin(async move {
                let tx = c
                    .build_transaction()
                    .isolation_level(tokio_postgres::IsolationLevel::RepeatableRead)
                    .read_only(true)
                    .start()
                    .await
                    .map_err(pg)?;
                let t = &tx;
                let forecasts = async {
                    match q.forecasts_from {
                        Some(from) => {
                            read::forecasts_since(t, q.field, from, CYCLE_FORECASTS).await
                        }
                        None => Ok(Vec::new()),
                    }
                };
                let source = async {
                    match &q.forecast_source {
                        Some(key) => read::document(t, read::FORECAST_SOURCE, key).await,
                        None => Ok(None),
                    }
                };
                let (
                    estimate,
                    readings,
                    latest_primary,
                    setpoints,
                    recent,
                    latest_forecast,
                    forecasts,
                    forecast_source,
                ) = futures_util::try_join!(
                    read::document(t, read::ESTIMATE, &q.field),
                    read::measurements(
                        t,
                        q.field,
                        Some(q.readings_from),
                        Some(q.now),
                        q.readings_limit,
                        Sensors::All
                    ),
                    read::measurement_before(t, q.field, q.now),
                    read::setpoints(t, q.field, Some(q.setpoints_from), None, CYCLE_SETPOINTS),
                    read::recent_setpoints(t, q.field, q.recent),
                    read::latest_forecast(t, q.field),
                    forecasts,
                    source,
                )?;
                tx.commit().await.map_err(pg)?;
                Ok(CycleRead {
                    estimate,
                    readings,
                    latest_primary,
                    setpoints,
                    recent,
                    latest_forecast,
                    forecasts,
                    forecast_source,
                })
            })
        })
    }

    fn document(&self, sql: &'static str, key: Key) -> Result<Option<String>, StoreError> {
        self.run(move |c| {
            Box::pin(async move {
                let key: &(dyn tokio_postgres::types::ToSql + Sync) = match &key {
                    Key::Field(id) => id,
                    Key::Text(k) => k,
                };
                read::document(&*c, sql, key).await
            })
        })
    }

    fn put_document(&self, sql: &'static str, key: Key, body: &str) -> Result<(), StoreError> {
        let body = body.to_string();
        self.run(move |c| {
            Box::pin(async move {
                match &key {
                    Key::Field(id) => c.execute(sql, &[id, &body]).await,
                    Key::Text(k) => c.execute(sql, &[k, &body]).await,
                }
                .map_err(pg)?;
                Ok(())
            })
        })
    }

    pub(super) fn simulation(&self, field: i64) -> Result<Option<String>, StoreError> {
        self.document(
            "SELECT body FROM simulations WHERE field_id = $1",
            Key::Field(field),
        )
    }

    pub(super) fn put_simulation(&self, field: i64, body: &str) -> Result<(), StoreError> {
        self.put_document(
            "INSERT INTO simulations(field_id, body) VALUES ($1, $2)
             ON CONFLICT(field_id) DO UPDATE SET body = excluded.body",
            Key::Field(field),
            body,
        )
    }

    pub(super) fn estimate(&self, field: i64) -> Result<Option<String>, StoreError> {
        self.document(read::ESTIMATE, Key::Field(field))
    }

    /// The estimate replaced when the stored one is still `expected` and
    /// `replica` holds a live lease of the field.
    pub(super) fn replace_estimate(
        &self,
        field: i64,
        expected: Option<&str>,
        body: &str,
        replica: &str,
    ) -> Result<bool, StoreError> {
        let (expected, body, replica) = (
            expected.map(str::to_string),
            body.to_string(),
            replica.to_string(),
        );
        self.run(move |c| {
            Box::pin(async move {
                let leased = "EXISTS (SELECT 1 FROM leases WHERE field_id = $1 AND holder = $3
                              AND expires_at > clock_timestamp())";
                let n = match &expected {
                    Some(old) => {
                        c.execute(
                            &format!(
                                "UPDATE estimates SET body = $2
                                 WHERE field_id = $1 AND body = $4 AND {leased}"
                            ),
                            &[&field, &body, &replica, old],
                        )
                        .await
                    }
                    None => {
                        c.execute(
                            &format!(
                                "INSERT INTO estimates(field_id, body) SELECT $1, $2
                                 WHERE {leased} ON CONFLICT(field_id) DO NOTHING"
                            ),
                            &[&field, &body, &replica],
                        )
                        .await
                    }
                }
                .map_err(pg)?;
                Ok(n == 1)
            })
        })
    }

    pub(super) fn forecast_source(&self, key: &str) -> Result<Option<String>, StoreError> {
        self.document(read::FORECAST_SOURCE, Key::Text(key.to_string()))
    }

    pub(super) fn put_forecast_source(&self, key: &str, body: &str) -> Result<(), StoreError> {
        self.put_document(
            "INSERT INTO forecast_sources(key, body) VALUES ($1, $2)
             ON CONFLICT(key) DO UPDATE SET body = excluded.body",
            Key::Text(key.to_string()),
            body,
        )
    }
}

impl Postgres {
    pub(super) fn read_page(
        &self,
        table: &'static Table,
        offset: usize,
        limit: usize,
    ) -> Result<Vec<Vec<Cell>>, StoreError> {
        let sql = copy::select_sql(table, "$1", "$2");
        let (offset, limit) = (offset as i64, limit as i64);
        self.run(move |c| {
            Box::pin(async move {
                let rows = c.query(&sql, &[&limit, &offset]).await.map_err(pg)?;
                Ok(rows
                    .iter()
                    .map(|r| {
                        table
                            .columns
                            .iter()
                            .enumerate()
                            .map(|(i, (_, kind))| match kind {
                                Kind::Int => {
                                    r.get::<_, Option<i64>>(i).map_or(Cell::Null, Cell::Int)
                                }
                                Kind::Real => {
                                    r.get::<_, Option<f64>>(i).map_or(Cell::Null, Cell::Real)
                                }
                                Kind::Text => {
                                    r.get::<_, Option<String>>(i).map_or(Cell::Null, Cell::Text)
                                }
                            })
                            .collect()
                    })
                    .collect())
            })
        })
    }

    pub(super) fn write_rows(
        &self,
        table: &'static Table,
        rows: Vec<Vec<Cell>>,
    ) -> Result<(), StoreError> {
        let sql = copy::insert_sql(table, '$');
        self.run(move |c| {
            Box::pin(async move {
                let tx = c.transaction().await.map_err(pg)?;
                let stmt = tx.prepare(&sql).await.map_err(pg)?;
                for row in &rows {
                    let values: Vec<Box<dyn tokio_postgres::types::ToSql + Sync + Send>> = row
                        .iter()
                        .zip(table.columns)
                        .map(|(cell, (_, kind))| -> Box<dyn tokio_postgres::types::ToSql + Sync + Send> {
                            match (cell, kind) {
                                (Cell::Int(v), _) => Box::new(*v),
                                (Cell::Real(v), _) => Box::new(*v),
                                (Cell::Text(v), _) => Box::new(v.clone()),
                                (Cell::Null, Kind::Int) => Box::new(None::<i64>),
                                (Cell::Null, Kind::Real) => Box::new(None::<f64>),
                                (Cell::Null, Kind::Text) => Box::new(None::<String>),
                            }
                        })
                        .collect();
                    let refs: Vec<&(dyn tokio_postgres::types::ToSql + Sync)> = values
                        .iter()
                        .map(|v| v.as_ref() as &(dyn tokio_postgres::types::ToSql + Sync))
                        .collect();
                    tx.execute(&stmt, &refs).await.map_err(pg)?;
                }
                tx.commit().await.map_err(pg)?;
                Ok(())
            })
        })
    }

    /// After rows came in with their ids: the id sequences continue past
    /// them.
    pub(super) fn reset_sequences(&self) -> Result<(), StoreError> {
        self.run(|c| {
            Box::pin(async move {
                for table in ["fields", "measurements", "forecasts", "setpoints"] {
                    c.execute(
                        &format!(
                            "SELECT setval(pg_get_serial_sequence('{table}', 'id'),
                                 GREATEST((SELECT max(id) FROM {table}), 1),
                                 (SELECT max(id) FROM {table}) IS NOT NULL)"
                        ),
                        &[],
                    )
                    .await
                    .map_err(pg)?;
                }
                Ok(())
            })
        })
    }
}

/// The key of a one-document-per-key table.
enum Key {
    Field(i64),
    Text(String),
}

fn conflict_at(i: usize, field: i64, stored: f64, m: &Measurement) -> StoreError {
    StoreError::Conflict(format!(
        "measurements[{i}]: field {field} already has θ = {stored} at {} \
         from sensor '{}'; this one says θ = {}",
        m.time.to_rfc3339(),
        m.sensor.as_deref().unwrap_or(""),
        m.theta
    ))
}

/// Announces field `id` on `channel` when the transaction commits.
async fn notify(
    tx: &deadpool_postgres::Transaction<'_>,
    channel: &str,
    id: i64,
) -> Result<(), StoreError> {
    tx.execute("SELECT pg_notify($1, $2)", &[&channel, &id.to_string()])
        .await
        .map_err(pg)?;
    Ok(())
}

impl Drop for Postgres {
    fn drop(&mut self) {
        // may run inside another runtime (the daemon's): no blocking drop
        if let Some(rt) = self.rt.take() {
            rt.shutdown_background();
        }
    }
}

/// The reads, on a pooled connection or within a transaction.
mod read {
    use chrono::{DateTime, Utc};
    use deadpool_postgres::GenericClient;
    use tokio_postgres::types::ToSql;

    use super::{StoreError, measurement_of, millis, pg, setpoint_of};
    use crate::service::wire::{Forecast, Measurement, Setpoint};
    use crate::store::Sensors;

    /// A field's stored state estimate.
    pub(super) const ESTIMATE: &str = "SELECT body FROM estimates WHERE field_id = $1";
    /// A polled forecast source's state, by its key.
    pub(super) const FORECAST_SOURCE: &str = "SELECT body FROM forecast_sources WHERE key = $1";

    fn count(n: usize) -> i64 {
        n.min(i64::MAX as usize) as i64
    }

    pub(super) async fn measurements(
        c: &impl GenericClient,
        field: i64,
        from: Option<DateTime<Utc>>,
        to: Option<DateTime<Utc>>,
        limit: usize,
        sensors: Sensors,
    ) -> Result<Vec<Measurement>, StoreError> {
        let sql = match sensors {
            Sensors::All => {
                "SELECT time, theta, sensor, true_theta, raw FROM measurements
                 WHERE field_id = $1 AND time >= $2 AND time <= $3
                 ORDER BY time, id LIMIT $4"
            }
            Sensors::Primary => {
                "SELECT time, theta, sensor, true_theta, raw FROM measurements
                 WHERE field_id = $1 AND time >= $2 AND time <= $3 AND sensor IS NULL
                 ORDER BY time, id LIMIT $4"
            }
        };
        let (from, to) = (from.map_or(i64::MIN, millis), to.map_or(i64::MAX, millis));
        let stmt = c.prepare_cached(sql).await.map_err(pg)?;
        let rows = c
            .query(&stmt, &[&field, &from, &to, &count(limit)])
            .await
            .map_err(pg)?;
        Ok(rows.iter().map(measurement_of).collect())
    }

    pub(super) async fn measurement_before(
        c: &impl GenericClient,
        field: i64,
        at: DateTime<Utc>,
    ) -> Result<Option<Measurement>, StoreError> {
        let stmt = c
            .prepare_cached(
                "SELECT time, theta, sensor, true_theta, raw FROM measurements
                 WHERE field_id = $1 AND time <= $2 AND sensor IS NULL
                 ORDER BY time DESC, id DESC LIMIT 1",
            )
            .await
            .map_err(pg)?;
        let row = c
            .query_opt(&stmt, &[&field, &millis(at)])
            .await
            .map_err(pg)?;
        Ok(row.as_ref().map(measurement_of))
    }

    pub(super) async fn latest_forecast(
        c: &impl GenericClient,
        field: i64,
    ) -> Result<Option<Forecast>, StoreError> {
        let stmt = c
            .prepare_cached(
                "SELECT body FROM forecasts WHERE field_id = $1 ORDER BY id DESC LIMIT 1",
            )
            .await
            .map_err(pg)?;
        let row = c.query_opt(&stmt, &[&field]).await.map_err(pg)?;
        Ok(row
            .map(|r| serde_json::from_str(r.get::<_, &str>(0)))
            .transpose()?)
    }

    pub(super) async fn forecasts_since(
        c: &impl GenericClient,
        field: i64,
        from: DateTime<Utc>,
        limit: usize,
    ) -> Result<Vec<Forecast>, StoreError> {
        let stmt = c
            .prepare_cached(
                "SELECT body FROM forecasts WHERE field_id = $1 AND issued_at >= $2
                 ORDER BY id DESC LIMIT $3",
            )
            .await
            .map_err(pg)?;
        let rows = c
            .query(&stmt, &[&field, &millis(from), &count(limit)])
            .await
            .map_err(pg)?;
        let mut out: Vec<Forecast> = rows
            .iter()
            .map(|r| serde_json::from_str(r.get::<_, &str>(0)))
            .collect::<Result<_, _>>()?;
        out.reverse();
        Ok(out)
    }

    pub(super) async fn setpoints(
        c: &impl GenericClient,
        field: i64,
        from: Option<DateTime<Utc>>,
        to: Option<DateTime<Utc>>,
        limit: usize,
    ) -> Result<Vec<Setpoint>, StoreError> {
        let (from, to) = (from.map_or(i64::MIN, millis), to.map_or(i64::MAX, millis));
        let stmt = c
            .prepare_cached(
                "SELECT body FROM setpoints WHERE field_id = $1 AND time >= $2 AND time <= $3
                 ORDER BY time, id LIMIT $4",
            )
            .await
            .map_err(pg)?;
        let rows = c
            .query(&stmt, &[&field, &from, &to, &count(limit)])
            .await
            .map_err(pg)?;
        Ok(rows
            .iter()
            .map(|r| setpoint_of(r.get::<_, &str>(0)))
            .collect::<Result<_, _>>()?)
    }

    pub(super) async fn recent_setpoints(
        c: &impl GenericClient,
        field: i64,
        n: usize,
    ) -> Result<Vec<Setpoint>, StoreError> {
        let stmt = c
            .prepare_cached(
                "SELECT body FROM setpoints WHERE field_id = $1
                 ORDER BY time DESC, id DESC LIMIT $2",
            )
            .await
            .map_err(pg)?;
        let rows = c.query(&stmt, &[&field, &count(n)]).await.map_err(pg)?;
        Ok(rows
            .iter()
            .map(|r| setpoint_of(r.get::<_, &str>(0)))
            .collect::<Result<_, _>>()?)
    }

    /// One body column of one row, by its key.
    pub(super) async fn document(
        c: &impl GenericClient,
        sql: &str,
        key: &(dyn ToSql + Sync),
    ) -> Result<Option<String>, StoreError> {
        let stmt = c.prepare_cached(sql).await.map_err(pg)?;
        let row = c.query_opt(&stmt, &[key]).await.map_err(pg)?;
        Ok(row.map(|r| r.get(0)))
    }
}
