//! Durable storage behind one interface, two backends: the embedded SQLite
//! file (the default: nothing to run) and PostgreSQL (`storage.url =
//! "postgres://…"`), which several replicas share.
//!
//! Both keep the same tables, brought to their version by migrations
//! versioned in the code and run at start; a database whose schema is newer
//! than the binary is refused, naming both versions. Every write is one
//! transaction, committed before the caller acknowledges it. A control
//! cycle writes its outputs in one transaction ([`Store::commit_cycle`]),
//! which a second run of the same (field, boundary) cannot repeat.
//!
//! The interface is synchronous: the daemon calls it on tokio's blocking
//! pool, the CLI and the tests from plain threads. The PostgreSQL backend
//! runs tokio-postgres on a small runtime of its own (see `postgres.rs`).

mod copy;
mod postgres;
mod sqlite;

pub use copy::CopyReport;

use std::path::{Path, PathBuf};

use chrono::{DateTime, TimeZone, Utc};

use crate::service::wire::{Field, FieldSpec, Forecast, Measurement, Setpoint};

pub use postgres::CHANNEL_FIELDS;
pub use postgres::CHANNEL_MEASURED;

/// The words every [`StoreError::Unavailable`] message carries, however it
/// is wrapped (the API answers such a failure with 503).
pub const UNAVAILABLE: &str = "database unavailable";

/// A storage operation failed.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error("database: {0}")]
    Sqlite(#[from] rusqlite::Error),
    #[error("database: {0}")]
    Postgres(String),
    /// The database cannot be reached (connection refused or lost, pool
    /// timeout): the caller may try again later.
    #[error("database unavailable: {0}")]
    Unavailable(String),
    /// The database's schema is not one this binary can use.
    #[error("{0}")]
    Schema(String),
    #[error("stored JSON: {0}")]
    Json(#[from] serde_json::Error),
    #[error("{0}")]
    Io(String),
    /// The write contradicts what is stored (the message names both).
    #[error("{0}")]
    Conflict(String),
}

impl StoreError {
    /// The database could not be reached: the same operation may succeed
    /// later.
    pub fn is_unavailable(&self) -> bool {
        matches!(self, StoreError::Unavailable(_))
    }
}

/// Which sensors' measurements a query returns.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Sensors {
    All,
    /// The field's first sensor (the one the surrogate controllers read),
    /// stored with no sensor id.
    Primary,
}

/// What became of one reading of [`Store::add_readings`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ReadingOutcome {
    Stored,
    /// Already stored with the same θ.
    Duplicate,
    /// Already stored with this other θ: refused.
    Conflict(f64),
    /// The field is gone: refused.
    NoField,
}

/// The run of a scheduled cycle: its period boundary and the replica that
/// ran it.
#[derive(Debug, Clone, Copy)]
pub struct CycleRun<'a> {
    pub boundary: DateTime<Utc>,
    pub replica: &'a str,
}

/// What one control cycle writes, in one transaction.
#[derive(Debug, Clone, Copy)]
pub struct CycleOutputs<'a> {
    pub setpoint: &'a Setpoint,
    /// The field's state estimate after the cycle (JSON).
    pub estimate: Option<&'a str>,
    /// A scheduled cycle's boundary (None: a cycle asked for by a client).
    pub run: Option<CycleRun<'a>>,
}

/// Where the data lives: `storage.url`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Location {
    /// The SQLite file `rootzone.sqlite3` in this folder.
    Sqlite(PathBuf),
    /// A PostgreSQL connection URL.
    Postgres(String),
}

impl Location {
    /// `sqlite:<folder>` (or `sqlite:<folder>/rootzone.sqlite3`),
    /// `postgres://…` or `postgresql://…`.
    pub fn parse(url: &str) -> Result<Location, String> {
        let url = url.trim();
        if url.starts_with("postgres://") || url.starts_with("postgresql://") {
            url.parse::<tokio_postgres::Config>()
                .map_err(|e| format!("'{}': {e}", redact(url)))?;
            return Ok(Location::Postgres(url.to_string()));
        }
        if let Some(path) = url.strip_prefix("sqlite:") {
            let path = path.strip_prefix("//").unwrap_or(path);
            if path.is_empty() {
                return Err("sqlite: needs a folder (sqlite:/var/lib/rootzone)".into());
            }
            let p = PathBuf::from(path);
            let dir = if p.extension().is_some_and(|e| e == "sqlite3") {
                p.parent().map(Path::to_path_buf).unwrap_or_default()
            } else {
                p
            };
            return Ok(Location::Sqlite(dir));
        }
        Err(format!(
            "'{}': not a storage URL (sqlite:<folder>, postgres://user@host/db)",
            redact(url)
        ))
    }
}

/// A URL with its password replaced by `***`, for messages and logs
/// (also one that does not parse).
pub fn redact(url: &str) -> String {
    let Some(start) = url.find("://").map(|i| i + 3) else {
        return url.to_string();
    };
    let rest = &url[start..];
    let Some(at) = rest.rfind('@') else {
        return url.to_string();
    };
    match rest[..at].find(':') {
        Some(colon) => format!("{}{}:***{}", &url[..start], &rest[..colon], &rest[at..]),
        None => url.to_string(),
    }
}

/// What one control cycle of a field reads: [`Store::cycle_read`].
#[derive(Debug, Clone)]
pub struct CycleQuery {
    pub field: i64,
    pub now: DateTime<Utc>,
    /// Readings of every sensor in [readings_from, now], oldest first.
    pub readings_from: DateTime<Utc>,
    /// At most this many of them (the oldest).
    pub readings_limit: usize,
    /// Setpoints from this time on (the irrigation the estimate replays).
    pub setpoints_from: DateTime<Utc>,
    /// The latest this many setpoints (the controller's warm start, bias).
    pub recent: usize,
    /// Stored forecasts issued from this time on (the observed weather
    /// of a field with no scenario); None reads none.
    pub forecasts_from: Option<DateTime<Utc>>,
    /// The polled forecast source the field uses, by its key.
    pub forecast_source: Option<String>,
}

/// A cycle's inputs, read in one consistent snapshot (one transaction).
#[derive(Debug, Clone, Default)]
pub struct CycleRead {
    /// The stored state estimate (JSON).
    pub estimate: Option<String>,
    /// Every sensor's readings in the query's span, oldest first.
    pub readings: Vec<Measurement>,
    /// The primary sensor's latest reading at or before `now`, however old.
    pub latest_primary: Option<Measurement>,
    /// Setpoints from the query's `setpoints_from`, oldest first (at most
    /// [`CYCLE_SETPOINTS`]).
    pub setpoints: Vec<Setpoint>,
    /// The latest `recent` setpoints, newest first.
    pub recent: Vec<Setpoint>,
    /// The forecast put last.
    pub latest_forecast: Option<Forecast>,
    /// Forecasts issued from `forecasts_from`, oldest first (at most the
    /// newest [`CYCLE_FORECASTS`]).
    pub forecasts: Vec<Forecast>,
    /// The state of the field's polled forecast source (JSON).
    pub forecast_source: Option<String>,
}

/// Most setpoints a cycle reads for its state estimate.
pub const CYCLE_SETPOINTS: usize = 10_000;
/// Most stored forecasts a cycle reads for its observed weather.
pub const CYCLE_FORECASTS: usize = 500;

enum Backend {
    Sqlite(sqlite::Sqlite),
    Postgres(postgres::Postgres),
}

/// The database.
pub struct Store {
    backend: Backend,
}

macro_rules! dispatch {
    ($self:ident, $b:ident => $e:expr) => {
        match &$self.backend {
            Backend::Sqlite($b) => $e,
            Backend::Postgres($b) => $e,
        }
    };
}

pub(crate) fn millis(t: DateTime<Utc>) -> i64 {
    t.timestamp_millis()
}

pub(crate) fn time(ms: i64) -> DateTime<Utc> {
    Utc.timestamp_millis_opt(ms).single().unwrap_or_default()
}

/// A stored setpoint; one stored before setpoints carried their
/// explanation gets it here, from what it recorded (without the field's
/// rate limit, so it cannot say that the limit bound).
pub(crate) fn setpoint_of(body: &str) -> Result<Setpoint, serde_json::Error> {
    let mut s: Setpoint = serde_json::from_str(body)?;
    if s.explanation.is_empty() {
        s.explanation = crate::service::explain::explain(&s, f64::INFINITY);
    }
    Ok(s)
}

impl Store {
    /// Opens (creating) `dir/rootzone.sqlite3` and migrates it.
    /// The folder is made private (0700) when the daemon creates it or it
    /// holds only the daemon's files, and the database file is 0600.
    pub fn open(dir: &Path) -> Result<Store, StoreError> {
        Ok(Store {
            backend: Backend::Sqlite(sqlite::Sqlite::open(dir)?),
        })
    }

    /// Opens the database at `location` and migrates it.
    pub fn connect(location: &Location) -> Result<Store, StoreError> {
        match location {
            Location::Sqlite(dir) => Store::open(dir),
            Location::Postgres(url) => Ok(Store {
                backend: Backend::Postgres(postgres::Postgres::connect(url)?),
            }),
        }
    }

    /// Which backend this is: `sqlite` or `postgres`.
    pub fn kind(&self) -> &'static str {
        match self.backend {
            Backend::Sqlite(_) => "sqlite",
            Backend::Postgres(_) => "postgres",
        }
    }

    /// Whether the database answers now (a trivial query).
    pub fn ping(&self) -> Result<(), StoreError> {
        dispatch!(self, b => b.ping())
    }

    pub fn meta(&self, key: &str) -> Result<Option<String>, StoreError> {
        dispatch!(self, b => b.meta(key))
    }

    pub fn set_meta(&self, key: &str, value: &str) -> Result<(), StoreError> {
        dispatch!(self, b => b.set_meta(key, value))
    }

    pub fn create_field(&self, spec: &FieldSpec, now: DateTime<Utc>) -> Result<Field, StoreError> {
        dispatch!(self, b => b.create_field(spec, now))
    }

    pub fn fields(&self) -> Result<Vec<Field>, StoreError> {
        dispatch!(self, b => b.fields())
    }

    pub fn field(&self, id: i64) -> Result<Option<Field>, StoreError> {
        dispatch!(self, b => b.field(id))
    }

    pub fn update_field(&self, id: i64, spec: &FieldSpec) -> Result<bool, StoreError> {
        dispatch!(self, b => b.update_field(id, spec))
    }

    /// Deletes a field with all its data.
    pub fn delete_field(&self, id: i64) -> Result<bool, StoreError> {
        dispatch!(self, b => b.delete_field(id))
    }

    /// Stores a batch of measurements in one transaction: all or nothing.
    /// A measurement whose (time, sensor) the field already has with the
    /// same θ is skipped (a client resending after a lost acknowledgement);
    /// with another θ the whole batch is refused with a [`StoreError::Conflict`]
    /// naming both values. Returns how many were new.
    pub fn add_measurements(&self, field: i64, batch: &[Measurement]) -> Result<usize, StoreError> {
        dispatch!(self, b => b.add_measurements(field, batch))
    }

    /// Stores readings of many fields in one transaction (the MQTT ingest's
    /// batches), each on its own: a reading whose (time, sensor) its field
    /// already has with the same θ is a duplicate, with another θ a
    /// conflict, and one of a field that is gone is refused; none of these
    /// stops the others. Returns one outcome per reading, in order.
    pub fn add_readings(
        &self,
        readings: &[(i64, Measurement)],
    ) -> Result<Vec<ReadingOutcome>, StoreError> {
        dispatch!(self, b => b.add_readings(readings))
    }

    /// Measurements in [from, to], oldest first, at most `limit`; of every
    /// sensor, or of the primary one only (stored with no sensor id).
    pub fn measurements(
        &self,
        field: i64,
        from: Option<DateTime<Utc>>,
        to: Option<DateTime<Utc>>,
        limit: usize,
        sensors: Sensors,
    ) -> Result<Vec<Measurement>, StoreError> {
        dispatch!(self, b => b.measurements(field, from, to, limit, sensors))
    }

    /// The primary sensor's latest measurement at or before `at`.
    pub fn measurement_before(
        &self,
        field: i64,
        at: DateTime<Utc>,
    ) -> Result<Option<Measurement>, StoreError> {
        dispatch!(self, b => b.measurement_before(field, at))
    }

    pub fn count_measurements(&self, field: i64) -> Result<u64, StoreError> {
        dispatch!(self, b => b.count_measurements(field))
    }

    pub fn put_forecast(&self, field: i64, forecast: &Forecast) -> Result<(), StoreError> {
        dispatch!(self, b => b.put_forecast(field, forecast))
    }

    /// The forecast put last.
    pub fn latest_forecast(&self, field: i64) -> Result<Option<Forecast>, StoreError> {
        dispatch!(self, b => b.latest_forecast(field))
    }

    /// The forecasts issued at or after `from`, oldest first; at most the
    /// newest `limit`.
    pub fn forecasts_since(
        &self,
        field: i64,
        from: DateTime<Utc>,
        limit: usize,
    ) -> Result<Vec<Forecast>, StoreError> {
        dispatch!(self, b => b.forecasts_since(field, from, limit))
    }

    /// A setpoint asked for outside the schedule (no boundary, no estimate).
    pub fn add_setpoint(&self, setpoint: &Setpoint) -> Result<(), StoreError> {
        self.commit_cycle(&CycleOutputs {
            setpoint,
            estimate: None,
            run: None,
        })
        .map(|_| ())
    }

    /// Writes a cycle's outputs in one transaction: the run of its boundary,
    /// its state estimate and its setpoint. A boundary that has run already
    /// (on this replica or another), or, on PostgreSQL, one whose field's
    /// lease this replica does not hold, writes nothing: returns false.
    pub fn commit_cycle(&self, out: &CycleOutputs<'_>) -> Result<bool, StoreError> {
        dispatch!(self, b => b.commit_cycle(out))
    }

    /// Everything one cycle of a field reads, in one consistent read: one
    /// transaction (a read-only repeatable-read snapshot on PostgreSQL,
    /// whose statements go out pipelined on one connection; the one
    /// connection held throughout on SQLite).
    pub fn cycle_read(&self, query: &CycleQuery) -> Result<CycleRead, StoreError> {
        dispatch!(self, b => b.cycle_read(query))
    }

    /// The boundaries of a field's scheduled cycles that have run, in
    /// [from, to], oldest first.
    pub fn cycle_runs(
        &self,
        field: i64,
        from: DateTime<Utc>,
        to: DateTime<Utc>,
    ) -> Result<Vec<DateTime<Utc>>, StoreError> {
        dispatch!(self, b => b.cycle_runs(field, from, to))
    }

    /// Setpoints in [from, to], oldest first, at most `limit`.
    pub fn setpoints(
        &self,
        field: i64,
        from: Option<DateTime<Utc>>,
        to: Option<DateTime<Utc>>,
        limit: usize,
    ) -> Result<Vec<Setpoint>, StoreError> {
        dispatch!(self, b => b.setpoints(field, from, to, limit))
    }

    /// The latest `n` setpoints, newest first.
    pub fn recent_setpoints(&self, field: i64, n: usize) -> Result<Vec<Setpoint>, StoreError> {
        dispatch!(self, b => b.recent_setpoints(field, n))
    }

    pub fn simulation(&self, field: i64) -> Result<Option<String>, StoreError> {
        dispatch!(self, b => b.simulation(field))
    }

    pub fn put_simulation(&self, field: i64, body: &str) -> Result<(), StoreError> {
        dispatch!(self, b => b.put_simulation(field, body))
    }

    /// A field's stored state estimate (JSON).
    pub fn estimate(&self, field: i64) -> Result<Option<String>, StoreError> {
        dispatch!(self, b => b.estimate(field))
    }

    /// Replaces a field's state estimate with `body` only if the stored one
    /// is still `expected` (None: none stored), and, on PostgreSQL, only
    /// while `replica` holds the field's lease: an estimate brought up to
    /// date after its cycle ([`crate::service`]'s deferred estimates) never
    /// overwrites one a later cycle wrote meanwhile. Returns whether it was
    /// written.
    pub fn replace_estimate(
        &self,
        field: i64,
        expected: Option<&str>,
        body: &str,
        replica: &str,
    ) -> Result<bool, StoreError> {
        dispatch!(self, b => b.replace_estimate(field, expected, body, replica))
    }

    /// A polled forecast source's state (JSON), by its key.
    pub fn forecast_source(&self, key: &str) -> Result<Option<String>, StoreError> {
        dispatch!(self, b => b.forecast_source(key))
    }

    pub fn put_forecast_source(&self, key: &str, body: &str) -> Result<(), StoreError> {
        dispatch!(self, b => b.put_forecast_source(key, body))
    }
}
#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_setpoint_stored_before_explanations_is_read_with_one() {
        let old = r#"{"field_id":1,"time":"2026-06-02T12:00:00Z","valid_from":"2026-06-02T12:00:00Z",
            "valid_until":"2026-06-02T14:00:00Z","rate":0.0,"amount_mm":0.0,"plan":[0.0,0.0],
            "predicted_theta":[0.21,0.2],"zone":[[0.18,0.23],[0.18,0.23]],"model":"richards",
            "status":"converged","iterations":3,"solve_ms":5.0,"degraded":["stale-measurement"],
            "bias":0.0}"#;
        let s = setpoint_of(old).unwrap();
        assert!(
            s.explanation
                .starts_with("Irrigate 0.00 mm this period; no irrigation needed"),
            "{}",
            s.explanation
        );
        assert!(
            s.explanation.contains("the last reading is old"),
            "{}",
            s.explanation
        );
        // a stored explanation is kept as it is
        let mut kept = s.clone();
        kept.explanation = "as decided".into();
        let body = serde_json::to_string(&kept).unwrap();
        assert_eq!(setpoint_of(&body).unwrap().explanation, "as decided");
    }
}
