//! The embedded backend: SQLite (bundled) in WAL mode, schema migrations
//! versioned in the code (`PRAGMA user_version`). Every write is its own
//! transaction, committed before the caller acknowledges it.

use std::path::Path;
use std::sync::Mutex;

use chrono::{DateTime, Utc};
use rusqlite::{Connection, OptionalExtension, params};

use super::copy::{self, Cell, Kind, Table};
use super::{
    CYCLE_FORECASTS, CYCLE_SETPOINTS, CycleOutputs, CycleQuery, CycleRead, ReadingOutcome, Sensors,
    StoreError, millis, setpoint_of, time,
};
use crate::service::wire::{Field, FieldSpec, Forecast, Measurement, Setpoint};

/// The schema, one migration per entry; entry i brings the database to
/// version i + 1.
const MIGRATIONS: &[&str] = &[
    "CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
     CREATE TABLE fields (
         id INTEGER PRIMARY KEY AUTOINCREMENT,
         created_at INTEGER NOT NULL,
         spec TEXT NOT NULL);
     CREATE TABLE measurements (
         field_id INTEGER NOT NULL REFERENCES fields(id) ON DELETE CASCADE,
         time INTEGER NOT NULL,
         theta REAL NOT NULL,
         sensor TEXT);
     CREATE INDEX measurements_by_time ON measurements(field_id, time);
     CREATE TABLE forecasts (
         id INTEGER PRIMARY KEY AUTOINCREMENT,
         field_id INTEGER NOT NULL REFERENCES fields(id) ON DELETE CASCADE,
         issued_at INTEGER NOT NULL,
         body TEXT NOT NULL);
     CREATE INDEX forecasts_by_field ON forecasts(field_id, id);
     CREATE TABLE setpoints (
         id INTEGER PRIMARY KEY AUTOINCREMENT,
         field_id INTEGER NOT NULL REFERENCES fields(id) ON DELETE CASCADE,
         time INTEGER NOT NULL,
         body TEXT NOT NULL);
     CREATE INDEX setpoints_by_time ON setpoints(field_id, time);
     CREATE TABLE simulations (
         field_id INTEGER PRIMARY KEY REFERENCES fields(id) ON DELETE CASCADE,
         body TEXT NOT NULL);",
    // measurements are idempotent: a resent (time, sensor) is stored once
    "DELETE FROM measurements WHERE rowid NOT IN (
         SELECT MIN(rowid) FROM measurements GROUP BY field_id, time, COALESCE(sensor, ''));
     CREATE UNIQUE INDEX measurements_once ON measurements(field_id, time, COALESCE(sensor, ''));",
    // the noise-free θ of the built-in simulated fields, for the dashboard
    "ALTER TABLE measurements ADD COLUMN true_theta REAL;",
    // field names are unique: older duplicates get their id appended
    "UPDATE fields SET spec = json_set(spec, '$.name', json_extract(spec, '$.name') || ' #' || id)
         WHERE id NOT IN (SELECT MIN(id) FROM fields GROUP BY json_extract(spec, '$.name'));
     CREATE UNIQUE INDEX fields_by_name ON fields(json_extract(spec, '$.name'));",
    // a sensor's raw reading, when it sent one (θ is then its calibration);
    // fields had one sensor before: its readings become the primary
    // sensor's (stored with no id), any that would collide keep their id
    "ALTER TABLE measurements ADD COLUMN raw REAL;
     UPDATE OR IGNORE measurements SET sensor = NULL WHERE sensor IS NOT NULL;",
    // a field's state estimate (the estimator's snapshot and its clock time)
    "CREATE TABLE estimates (
         field_id INTEGER PRIMARY KEY REFERENCES fields(id) ON DELETE CASCADE,
         body TEXT NOT NULL);",
    // a polled forecast source's state (its last good forecast, validators,
    // backoff), shared by the fields at its location
    "CREATE TABLE forecast_sources (key TEXT PRIMARY KEY, body TEXT NOT NULL);",
    // each scheduled cycle (field, period boundary) runs once
    "CREATE TABLE cycle_runs (
         field_id INTEGER NOT NULL REFERENCES fields(id) ON DELETE CASCADE,
         boundary INTEGER NOT NULL,
         replica TEXT NOT NULL,
         done_at INTEGER NOT NULL,
         PRIMARY KEY (field_id, boundary));",
];

/// The schema version this binary brings a database to.
pub(super) const VERSION: usize = MIGRATIONS.len();

/// A unique-constraint violation as a conflict naming `what`.
fn conflict(e: rusqlite::Error, what: impl FnOnce() -> String) -> StoreError {
    match e {
        rusqlite::Error::SqliteFailure(f, _)
            if f.code == rusqlite::ErrorCode::ConstraintViolation =>
        {
            StoreError::Conflict(what())
        }
        e => e.into(),
    }
}

/// The database file.
pub(super) struct Sqlite {
    conn: Mutex<Connection>,
}

/// The files the daemon keeps in its data folder.
const OWN_FILES: &[&str] = &[
    "rootzone.sqlite3",
    "rootzone.sqlite3-wal",
    "rootzone.sqlite3-shm",
    "api-token",
];

#[cfg(unix)]
fn private(dir: &Path, file: &Path) -> std::io::Result<()> {
    use std::os::unix::fs::{OpenOptionsExt, PermissionsExt};
    // a folder of the daemon's own: 0700; a shared one (say ".") is left
    // as it is, with a warning
    let foreign = std::fs::read_dir(dir)?
        .filter_map(Result::ok)
        .any(|e| !OWN_FILES.contains(&e.file_name().to_string_lossy().as_ref()));
    let mode = std::fs::metadata(dir)?.permissions().mode() & 0o777;
    if !foreign {
        if mode != 0o700 {
            std::fs::set_permissions(dir, std::fs::Permissions::from_mode(0o700))?;
        }
    } else if mode & 0o077 != 0 {
        tracing::warn!(dir = %dir.display(), mode = format!("{mode:o}"),
            "the data folder holds other files and is open to other users; left as it is");
    }
    // the database (and the WAL files SQLite makes with its mode): 0600
    std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .mode(0o600)
        .open(file)?;
    for name in OWN_FILES.iter().take(3) {
        let path = dir.join(name);
        if path.exists() {
            std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o600))?;
        }
    }
    Ok(())
}

#[cfg(not(unix))]
fn private(_dir: &Path, _file: &Path) -> std::io::Result<()> {
    Ok(())
}

fn measurement_row(r: &rusqlite::Row<'_>) -> rusqlite::Result<Measurement> {
    Ok(Measurement {
        time: time(r.get(0)?),
        theta: r.get(1)?,
        sensor: r.get(2)?,
        true_theta: r.get(3)?,
        raw: r.get(4)?,
    })
}

impl Sqlite {
    /// Opens (creating) `dir/rootzone.sqlite3` and migrates it.
    /// The folder is made private (0700) when the daemon creates it or it
    /// holds only the daemon's files, and the database file is 0600.
    pub(super) fn open(dir: &Path) -> Result<Sqlite, StoreError> {
        std::fs::create_dir_all(dir)
            .map_err(|e| StoreError::Io(format!("cannot create {}: {e}", dir.display())))?;
        let file = dir.join("rootzone.sqlite3");
        private(dir, &file)
            .map_err(|e| StoreError::Io(format!("cannot restrict {}: {e}", dir.display())))?;
        let conn = Connection::open(&file)?;
        conn.pragma_update(None, "journal_mode", "WAL")?;
        // NORMAL in WAL mode: a committed write survives a crash of the
        // process (kill -9); only a power cut can lose the last commits
        conn.pragma_update(None, "synchronous", "NORMAL")?;
        conn.pragma_update(None, "foreign_keys", "ON")?;
        conn.busy_timeout(std::time::Duration::from_secs(5))?;
        let version: i64 = conn.pragma_query_value(None, "user_version", |r| r.get(0))?;
        if version > VERSION as i64 {
            return Err(StoreError::Schema(format!(
                "{}: the database's schema is version {version}, newer than this binary's \
                 version {VERSION}; run the rootzone release that wrote it (or a newer one)",
                file.display()
            )));
        }
        for (i, sql) in MIGRATIONS.iter().enumerate().skip(version.max(0) as usize) {
            let tx = conn.unchecked_transaction()?;
            tx.execute_batch(sql)?;
            tx.pragma_update(None, "user_version", (i + 1) as i64)?;
            tx.commit()?;
        }
        Ok(Sqlite {
            conn: Mutex::new(conn),
        })
    }

    fn with<T>(
        &self,
        f: impl FnOnce(&mut Connection) -> Result<T, StoreError>,
    ) -> Result<T, StoreError> {
        let mut conn = self.conn.lock().unwrap_or_else(|p| p.into_inner());
        f(&mut conn)
    }

    pub(super) fn ping(&self) -> Result<(), StoreError> {
        self.with(|c| Ok(c.query_row("SELECT 1", [], |_| Ok(()))?))
    }

    pub(super) fn meta(&self, key: &str) -> Result<Option<String>, StoreError> {
        self.with(|c| {
            Ok(
                c.query_row("SELECT value FROM meta WHERE key = ?1", [key], |r| r.get(0))
                    .optional()?,
            )
        })
    }

    pub(super) fn set_meta(&self, key: &str, value: &str) -> Result<(), StoreError> {
        self.with(|c| {
            c.execute(
                "INSERT INTO meta(key, value) VALUES (?1, ?2)
                 ON CONFLICT(key) DO UPDATE SET value = excluded.value",
                [key, value],
            )?;
            Ok(())
        })
    }

    pub(super) fn create_field(
        &self,
        spec: &FieldSpec,
        now: DateTime<Utc>,
    ) -> Result<Field, StoreError> {
        let body = serde_json::to_string(spec)?;
        self.with(|c| {
            c.execute(
                "INSERT INTO fields(created_at, spec) VALUES (?1, ?2)",
                params![millis(now), body],
            )
            .map_err(|e| conflict(e, || format!("a field named '{}' exists", spec.name)))?;
            Ok(Field {
                id: c.last_insert_rowid(),
                created_at: time(millis(now)),
                spec: spec.clone(),
            })
        })
    }

    pub(super) fn fields(&self) -> Result<Vec<Field>, StoreError> {
        self.with(|c| {
            let mut stmt = c.prepare("SELECT id, created_at, spec FROM fields ORDER BY id")?;
            let rows = stmt.query_map([], |r| {
                Ok((
                    r.get::<_, i64>(0)?,
                    r.get::<_, i64>(1)?,
                    r.get::<_, String>(2)?,
                ))
            })?;
            let mut out = Vec::new();
            for row in rows {
                let (id, created, spec) = row?;
                out.push(Field {
                    id,
                    created_at: time(created),
                    spec: serde_json::from_str(&spec)?,
                });
            }
            Ok(out)
        })
    }

    pub(super) fn field(&self, id: i64) -> Result<Option<Field>, StoreError> {
        let row = self.with(|c| {
            Ok(c.query_row(
                "SELECT created_at, spec FROM fields WHERE id = ?1",
                [id],
                |r| Ok((r.get::<_, i64>(0)?, r.get::<_, String>(1)?)),
            )
            .optional()?)
        })?;
        match row {
            None => Ok(None),
            Some((created, spec)) => Ok(Some(Field {
                id,
                created_at: time(created),
                spec: serde_json::from_str(&spec)?,
            })),
        }
    }

    pub(super) fn update_field(&self, id: i64, spec: &FieldSpec) -> Result<bool, StoreError> {
        let body = serde_json::to_string(spec)?;
        self.with(|c| {
            Ok(c.execute(
                "UPDATE fields SET spec = ?2 WHERE id = ?1",
                params![id, body],
            )
            .map_err(|e| conflict(e, || format!("a field named '{}' exists", spec.name)))?
                == 1)
        })
    }

    /// Deletes a field with all its data.
    pub(super) fn delete_field(&self, id: i64) -> Result<bool, StoreError> {
        self.with(|c| Ok(c.execute("DELETE FROM fields WHERE id = ?1", [id])? == 1))
    }

    /// Stores a batch of measurements in one transaction: all or nothing.
    /// A measurement whose (time, sensor) the field already has with the
    /// same θ is skipped (a client resending after a lost acknowledgement);
    /// with another θ the whole batch is refused with a [`StoreError::Conflict`]
    /// naming both values. Returns how many were new.
    pub(super) fn add_measurements(
        &self,
        field: i64,
        batch: &[Measurement],
    ) -> Result<usize, StoreError> {
        self.with(|c| {
            let tx = c.transaction()?;
            let mut new = 0;
            {
                let mut existing = tx.prepare_cached(
                    "SELECT theta FROM measurements
                     WHERE field_id = ?1 AND time = ?2 AND COALESCE(sensor, '') = COALESCE(?3, '')",
                )?;
                let mut insert = tx.prepare_cached(
                    "INSERT INTO measurements(field_id, time, theta, sensor, true_theta, raw)
                     VALUES (?1, ?2, ?3, ?4, ?5, ?6)",
                )?;
                for (i, m) in batch.iter().enumerate() {
                    let stored: Option<f64> = existing
                        .query_row(params![field, millis(m.time), m.sensor], |r| r.get(0))
                        .optional()?;
                    match stored {
                        Some(theta) if theta == m.theta => {}
                        Some(theta) => {
                            return Err(StoreError::Conflict(format!(
                                "measurements[{i}]: field {field} already has θ = {theta} at {} \
                                 from sensor '{}'; this one says θ = {}",
                                m.time.to_rfc3339(),
                                m.sensor.as_deref().unwrap_or(""),
                                m.theta
                            )));
                        }
                        None => {
                            new += insert.execute(params![
                                field,
                                millis(m.time),
                                m.theta,
                                m.sensor,
                                m.true_theta,
                                m.raw
                            ])?;
                        }
                    }
                }
            }
            tx.commit()?;
            Ok(new)
        })
    }

    /// Stores readings of many fields in one transaction (the MQTT ingest's
    /// batches), each on its own: a reading whose (time, sensor) its field
    /// already has with the same θ is a duplicate, with another θ a
    /// conflict, and one of a field that is gone is refused; none of these
    /// stops the others. Returns one outcome per reading, in order.
    pub(super) fn add_readings(
        &self,
        readings: &[(i64, Measurement)],
    ) -> Result<Vec<ReadingOutcome>, StoreError> {
        self.with(|c| {
            let tx = c.transaction()?;
            let mut outcomes = Vec::with_capacity(readings.len());
            {
                let mut existing = tx.prepare_cached(
                    "SELECT theta FROM measurements
                     WHERE field_id = ?1 AND time = ?2 AND COALESCE(sensor, '') = COALESCE(?3, '')",
                )?;
                let mut insert = tx.prepare_cached(
                    "INSERT INTO measurements(field_id, time, theta, sensor, true_theta, raw)
                     SELECT ?1, ?2, ?3, ?4, ?5, ?6 WHERE EXISTS (SELECT 1 FROM fields WHERE id = ?1)",
                )?;
                for (field, m) in readings {
                    let stored: Option<f64> = existing
                        .query_row(params![field, millis(m.time), m.sensor], |r| r.get(0))
                        .optional()?;
                    outcomes.push(match stored {
                        Some(theta) if theta == m.theta => ReadingOutcome::Duplicate,
                        Some(theta) => ReadingOutcome::Conflict(theta),
                        None => {
                            let n = insert.execute(params![
                                field,
                                millis(m.time),
                                m.theta,
                                m.sensor,
                                m.true_theta,
                                m.raw
                            ])?;
                            if n == 1 {
                                ReadingOutcome::Stored
                            } else {
                                ReadingOutcome::NoField
                            }
                        }
                    });
                }
            }
            tx.commit()?;
            Ok(outcomes)
        })
    }

    /// Measurements in [from, to], oldest first, at most `limit`; of every
    /// sensor, or of the primary one only (stored with no sensor id).
    pub(super) fn measurements(
        &self,
        field: i64,
        from: Option<DateTime<Utc>>,
        to: Option<DateTime<Utc>>,
        limit: usize,
        sensors: Sensors,
    ) -> Result<Vec<Measurement>, StoreError> {
        self.with(|c| read::measurements(c, field, from, to, limit, sensors))
    }

    /// The primary sensor's latest measurement at or before `at`.
    pub(super) fn measurement_before(
        &self,
        field: i64,
        at: DateTime<Utc>,
    ) -> Result<Option<Measurement>, StoreError> {
        self.with(|c| read::measurement_before(c, field, at))
    }

    pub(super) fn count_measurements(&self, field: i64) -> Result<u64, StoreError> {
        self.with(|c| {
            Ok(c.query_row(
                "SELECT COUNT(*) FROM measurements WHERE field_id = ?1",
                [field],
                |r| r.get::<_, i64>(0),
            )? as u64)
        })
    }

    pub(super) fn put_forecast(&self, field: i64, forecast: &Forecast) -> Result<(), StoreError> {
        let body = serde_json::to_string(forecast)?;
        self.with(|c| {
            c.execute(
                "INSERT INTO forecasts(field_id, issued_at, body) VALUES (?1, ?2, ?3)",
                params![field, millis(forecast.issued_at), body],
            )?;
            Ok(())
        })
    }

    /// The forecast put last.
    pub(super) fn latest_forecast(&self, field: i64) -> Result<Option<Forecast>, StoreError> {
        self.with(|c| read::latest_forecast(c, field))
    }

    /// The forecasts issued at or after `from`, oldest first; at most the
    /// newest `limit`.
    pub(super) fn forecasts_since(
        &self,
        field: i64,
        from: DateTime<Utc>,
        limit: usize,
    ) -> Result<Vec<Forecast>, StoreError> {
        self.with(|c| read::forecasts_since(c, field, from, limit))
    }

    /// Setpoints in [from, to], oldest first, at most `limit`.
    pub(super) fn setpoints(
        &self,
        field: i64,
        from: Option<DateTime<Utc>>,
        to: Option<DateTime<Utc>>,
        limit: usize,
    ) -> Result<Vec<Setpoint>, StoreError> {
        self.with(|c| read::setpoints(c, field, from, to, limit))
    }

    /// The latest `n` setpoints, newest first.
    pub(super) fn recent_setpoints(
        &self,
        field: i64,
        n: usize,
    ) -> Result<Vec<Setpoint>, StoreError> {
        self.with(|c| read::recent_setpoints(c, field, n))
    }

    /// One cycle's inputs in one read transaction, with the connection
    /// held throughout (every write waits for it).
    pub(super) fn cycle_read(&self, q: &CycleQuery) -> Result<CycleRead, StoreError> {
        self.with(|c| {
            let tx = c.transaction()?;
            let out = CycleRead {
                estimate: read::document(&tx, read::ESTIMATE, q.field)?,
                readings: read::measurements(
                    &tx,
                    q.field,
                    Some(q.readings_from),
                    Some(q.now),
                    q.readings_limit,
                    Sensors::All,
                )?,
                latest_primary: read::measurement_before(&tx, q.field, q.now)?,
                setpoints: read::setpoints(
                    &tx,
                    q.field,
                    Some(q.setpoints_from),
                    None,
                    CYCLE_SETPOINTS,
                )?,
                recent: read::recent_setpoints(&tx, q.field, q.recent)?,
                latest_forecast: read::latest_forecast(&tx, q.field)?,
                forecasts: match q.forecasts_from {
                    Some(from) => read::forecasts_since(&tx, q.field, from, CYCLE_FORECASTS)?,
                    None => Vec::new(),
                },
                forecast_source: match &q.forecast_source {
                    Some(key) => read::document(&tx, read::FORECAST_SOURCE, key)?,
                    None => None,
                },
            };
            tx.commit()?;
            Ok(out)
        })
    }

    pub(super) fn simulation(&self, field: i64) -> Result<Option<String>, StoreError> {
        self.with(|c| {
            Ok(c.query_row(
                "SELECT body FROM simulations WHERE field_id = ?1",
                [field],
                |r| r.get(0),
            )
            .optional()?)
        })
    }

    pub(super) fn put_simulation(&self, field: i64, body: &str) -> Result<(), StoreError> {
        self.with(|c| {
            c.execute(
                "INSERT INTO simulations(field_id, body) VALUES (?1, ?2)
                 ON CONFLICT(field_id) DO UPDATE SET body = excluded.body",
                params![field, body],
            )?;
            Ok(())
        })
    }

    /// Writes a cycle's outputs in one transaction: the run of its boundary
    /// (refused, and nothing written, when that boundary has run), the
    /// state estimate and the setpoint. Returns false when refused.
    pub(super) fn commit_cycle(&self, out: &CycleOutputs<'_>) -> Result<bool, StoreError> {
        let body = serde_json::to_string(out.setpoint)?;
        let field = out.setpoint.field_id;
        self.with(|c| {
            let tx = c.transaction()?;
            if let Some(run) = &out.run {
                let n = tx.execute(
                    "INSERT OR IGNORE INTO cycle_runs(field_id, boundary, replica, done_at)
                     VALUES (?1, ?2, ?3, ?4)",
                    params![field, millis(run.boundary), run.replica, millis(Utc::now())],
                )?;
                if n == 0 {
                    return Ok(false);
                }
            }
            if let Some(estimate) = out.estimate {
                tx.execute(
                    "INSERT INTO estimates(field_id, body) VALUES (?1, ?2)
                     ON CONFLICT(field_id) DO UPDATE SET body = excluded.body",
                    params![field, estimate],
                )?;
            }
            tx.execute(
                "INSERT INTO setpoints(field_id, time, body) VALUES (?1, ?2, ?3)",
                params![field, millis(out.setpoint.time), body],
            )?;
            tx.commit()?;
            Ok(true)
        })
    }

    /// The boundaries of field `field`'s scheduled cycles that have run, in
    /// [from, to], oldest first.
    pub(super) fn cycle_runs(
        &self,
        field: i64,
        from: DateTime<Utc>,
        to: DateTime<Utc>,
    ) -> Result<Vec<DateTime<Utc>>, StoreError> {
        self.with(|c| {
            let mut stmt = c.prepare_cached(
                "SELECT boundary FROM cycle_runs WHERE field_id = ?1 AND boundary >= ?2
                 AND boundary <= ?3 ORDER BY boundary",
            )?;
            let rows = stmt.query_map(params![field, millis(from), millis(to)], |r| {
                r.get::<_, i64>(0)
            })?;
            Ok(rows.map(|r| r.map(time)).collect::<Result<Vec<_>, _>>()?)
        })
    }

    /// A field's stored state estimate (JSON).
    pub(super) fn estimate(&self, field: i64) -> Result<Option<String>, StoreError> {
        self.with(|c| read::document(c, read::ESTIMATE, field))
    }

    /// The estimate replaced when the stored one is still `expected` (one
    /// process: no lease to check).
    pub(super) fn replace_estimate(
        &self,
        field: i64,
        expected: Option<&str>,
        body: &str,
        _replica: &str,
    ) -> Result<bool, StoreError> {
        self.with(|c| {
            let n = match expected {
                Some(old) => c.execute(
                    "UPDATE estimates SET body = ?2 WHERE field_id = ?1 AND body = ?3",
                    params![field, body, old],
                )?,
                None => c.execute(
                    "INSERT INTO estimates(field_id, body) SELECT ?1, ?2
                     WHERE EXISTS (SELECT 1 FROM fields WHERE id = ?1)
                     ON CONFLICT(field_id) DO NOTHING",
                    params![field, body],
                )?,
            };
            Ok(n == 1)
        })
    }

    pub(super) fn forecast_source(&self, key: &str) -> Result<Option<String>, StoreError> {
        self.with(|c| read::document(c, read::FORECAST_SOURCE, key))
    }

    pub(super) fn put_forecast_source(&self, key: &str, body: &str) -> Result<(), StoreError> {
        self.with(|c| {
            c.execute(
                "INSERT INTO forecast_sources(key, body) VALUES (?1, ?2)
                 ON CONFLICT(key) DO UPDATE SET body = excluded.body",
                params![key, body],
            )?;
            Ok(())
        })
    }

    pub(super) fn read_page(
        &self,
        table: &Table,
        offset: usize,
        limit: usize,
    ) -> Result<Vec<Vec<Cell>>, StoreError> {
        let sql = copy::select_sql(table, "?1", "?2");
        self.with(|c| {
            let mut stmt = c.prepare(&sql)?;
            let rows = stmt.query_map(params![limit as i64, offset as i64], |r| {
                table
                    .columns
                    .iter()
                    .enumerate()
                    .map(|(i, (_, kind))| {
                        use rusqlite::types::Value;
                        Ok(match (r.get::<_, Value>(i)?, kind) {
                            (Value::Null, _) => Cell::Null,
                            (Value::Integer(v), Kind::Real) => Cell::Real(v as f64),
                            (Value::Integer(v), _) => Cell::Int(v),
                            (Value::Real(v), _) => Cell::Real(v),
                            (Value::Text(v), _) => Cell::Text(v),
                            (Value::Blob(v), _) => Cell::Text(String::from_utf8_lossy(&v).into()),
                        })
                    })
                    .collect::<rusqlite::Result<Vec<Cell>>>()
            })?;
            Ok(rows.collect::<Result<Vec<_>, _>>()?)
        })
    }

    pub(super) fn write_rows(&self, table: &Table, rows: &[Vec<Cell>]) -> Result<(), StoreError> {
        let sql = copy::insert_sql(table, '?');
        self.with(|c| {
            let tx = c.transaction()?;
            {
                let mut stmt = tx.prepare(&sql)?;
                for row in rows {
                    let values = row.iter().map(|cell| match cell {
                        Cell::Null => rusqlite::types::Value::Null,
                        Cell::Int(v) => rusqlite::types::Value::Integer(*v),
                        Cell::Real(v) => rusqlite::types::Value::Real(*v),
                        Cell::Text(v) => rusqlite::types::Value::Text(v.clone()),
                    });
                    stmt.execute(rusqlite::params_from_iter(values))?;
                }
            }
            tx.commit()?;
            Ok(())
        })
    }
}

/// The reads, on a connection or within a transaction (both deref to
/// `Connection`).
mod read {
    use chrono::{DateTime, Utc};
    use rusqlite::{Connection, OptionalExtension, params};

    use super::{StoreError, measurement_row, millis, setpoint_of};
    use crate::service::wire::{Forecast, Measurement, Setpoint};
    use crate::store::Sensors;

    /// A field's stored state estimate.
    pub(super) const ESTIMATE: &str = "SELECT body FROM estimates WHERE field_id = ?1";
    /// A polled forecast source's state, by its key.
    pub(super) const FORECAST_SOURCE: &str = "SELECT body FROM forecast_sources WHERE key = ?1";

    pub(super) fn measurements(
        c: &Connection,
        field: i64,
        from: Option<DateTime<Utc>>,
        to: Option<DateTime<Utc>>,
        limit: usize,
        sensors: Sensors,
    ) -> Result<Vec<Measurement>, StoreError> {
        let sql = match sensors {
            Sensors::All => {
                "SELECT time, theta, sensor, true_theta, raw FROM measurements
                 WHERE field_id = ?1 AND time >= ?2 AND time <= ?3
                 ORDER BY time, rowid LIMIT ?4"
            }
            Sensors::Primary => {
                "SELECT time, theta, sensor, true_theta, raw FROM measurements
                 WHERE field_id = ?1 AND time >= ?2 AND time <= ?3 AND sensor IS NULL
                 ORDER BY time, rowid LIMIT ?4"
            }
        };
        let mut stmt = c.prepare_cached(sql)?;
        let rows = stmt.query_map(
            params![
                field,
                from.map_or(i64::MIN, millis),
                to.map_or(i64::MAX, millis),
                limit.min(i64::MAX as usize) as i64
            ],
            measurement_row,
        )?;
        Ok(rows.collect::<Result<Vec<_>, _>>()?)
    }

    pub(super) fn measurement_before(
        c: &Connection,
        field: i64,
        at: DateTime<Utc>,
    ) -> Result<Option<Measurement>, StoreError> {
        Ok(c.prepare_cached(
            "SELECT time, theta, sensor, true_theta, raw FROM measurements
                 WHERE field_id = ?1 AND time <= ?2 AND sensor IS NULL
                 ORDER BY time DESC, rowid DESC LIMIT 1",
        )?
        .query_row(params![field, millis(at)], measurement_row)
        .optional()?)
    }

    pub(super) fn latest_forecast(
        c: &Connection,
        field: i64,
    ) -> Result<Option<Forecast>, StoreError> {
        let body: Option<String> = c
            .prepare_cached(
                "SELECT body FROM forecasts WHERE field_id = ?1 ORDER BY id DESC LIMIT 1",
            )?
            .query_row([field], |r| r.get(0))
            .optional()?;
        Ok(body.map(|b| serde_json::from_str(&b)).transpose()?)
    }

    pub(super) fn forecasts_since(
        c: &Connection,
        field: i64,
        from: DateTime<Utc>,
        limit: usize,
    ) -> Result<Vec<Forecast>, StoreError> {
        let mut stmt = c.prepare_cached(
            "SELECT body FROM forecasts WHERE field_id = ?1 AND issued_at >= ?2
             ORDER BY id DESC LIMIT ?3",
        )?;
        let rows = stmt.query_map(
            params![field, millis(from), limit.min(i64::MAX as usize) as i64],
            |r| r.get::<_, String>(0),
        )?;
        let mut bodies = rows.collect::<Result<Vec<_>, _>>()?;
        bodies.reverse();
        Ok(bodies
            .iter()
            .map(|b| serde_json::from_str(b))
            .collect::<Result<_, _>>()?)
    }

    pub(super) fn setpoints(
        c: &Connection,
        field: i64,
        from: Option<DateTime<Utc>>,
        to: Option<DateTime<Utc>>,
        limit: usize,
    ) -> Result<Vec<Setpoint>, StoreError> {
        let mut stmt = c.prepare_cached(
            "SELECT body FROM setpoints WHERE field_id = ?1 AND time >= ?2 AND time <= ?3
             ORDER BY time, id LIMIT ?4",
        )?;
        let rows = stmt.query_map(
            params![
                field,
                from.map_or(i64::MIN, millis),
                to.map_or(i64::MAX, millis),
                limit.min(i64::MAX as usize) as i64
            ],
            |r| r.get::<_, String>(0),
        )?;
        setpoints_of(rows.collect::<Result<Vec<_>, _>>()?)
    }

    pub(super) fn recent_setpoints(
        c: &Connection,
        field: i64,
        n: usize,
    ) -> Result<Vec<Setpoint>, StoreError> {
        let mut stmt = c.prepare_cached(
            "SELECT body FROM setpoints WHERE field_id = ?1 ORDER BY time DESC, id DESC LIMIT ?2",
        )?;
        let rows = stmt.query_map(params![field, n.min(i64::MAX as usize) as i64], |r| {
            r.get::<_, String>(0)
        })?;
        setpoints_of(rows.collect::<Result<Vec<_>, _>>()?)
    }

    fn setpoints_of(bodies: Vec<String>) -> Result<Vec<Setpoint>, StoreError> {
        Ok(bodies
            .iter()
            .map(|b| setpoint_of(b))
            .collect::<Result<_, _>>()?)
    }

    /// One body column of one row, by its key.
    pub(super) fn document(
        c: &Connection,
        sql: &str,
        key: impl rusqlite::ToSql,
    ) -> Result<Option<String>, StoreError> {
        Ok(c.prepare_cached(sql)?
            .query_row([key], |r| r.get(0))
            .optional()?)
    }
}
