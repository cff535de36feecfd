//! Field leases shared by several `rootzone serve` replicas over one
//! PostgreSQL database.
//!
//! # Invariants
//!
//! * **Who may run a field.** A replica may run a field's control cycle (or
//!   actuate its valves) only while [`Leases::holds`] returns true for it. The
//!   table `leases` has one row per field (its primary key), so at most one
//!   replica is the recorded holder at any time; a row whose `expires_at` lies
//!   in the past belongs to nobody and may be taken by any replica.
//! * **One clock for expiry.** Every `expires_at` and `heartbeat_at` is
//!   computed and compared by the database (`clock_timestamp()`); the
//!   replicas' wall clocks never enter the tables, so replicas with skewed
//!   clocks agree on who holds what.
//! * **The local deadline ends before the database's.** A replica cannot ask
//!   the database before every valve command, so it keeps a local deadline
//!   `valid_until = sent + lease − margin`, where `sent` is the [`Instant`]
//!   at which the renewing statement was *sent*. The database computed the
//!   row's `expires_at` when it *executed* that statement, which is later
//!   than `sent`, so `expires_at ≥ sent + lease` (in the database's time).
//!   The margin (a fifth of the lease) absorbs a difference in clock *rates*
//!   between this host and the database host and the time it takes a cycle
//!   to notice. (It cannot absorb a *step* of the database's clock: the
//!   database host's time must be slewed, not stepped, while replicas run.) Another replica can take the field only after `expires_at`,
//!   hence only after this replica's [`Leases::holds`] has already turned
//!   false: no two replicas ever both believe they hold a field. The other
//!   way a field changes hands, a release, is safe for the same reason: the
//!   field leaves the local set before the `DELETE` is sent.
//! * **Check before acting.** A cycle that started while `holds` was true
//!   may outlive the deadline (the database went away mid-cycle): callers
//!   check [`Leases::holds`] again right before each valve command or
//!   stored output, not only when the cycle starts. Fields with a cycle
//!   under way are passed as `busy` to [`Leases::tick`], which renews them
//!   instead of handing them over mid-cycle.
//! * **A failed tick extends nothing.** When the database is unreachable,
//!   [`Leases::tick`] fails (quickly: every step is bounded by timeouts) and
//!   `valid_until` stays where the last successful renewal put it, so the
//!   replica stops running its fields before anyone else may start them. The
//!   next successful tick renews what is still ours or re-acquires it.
//!
//! # Distribution
//!
//! Each replica computes the same assignment of fields to the live replicas
//! (heartbeat within one lease) by rendezvous (highest-random-weight)
//! hashing with a hash spelled out here ([`weight`]), so every process, of
//! every build, agrees. A replica releases the fields it holds outside its
//! share (unless they are busy: a cycle is running) and acquires the fields
//! of its share that are free or expired. When a replica joins, the others
//! release its share on their next tick and it acquires them on its tick
//! after that; when one dies, its heartbeat and its leases age out after one
//! lease and the survivors take its fields on their next tick.

use std::collections::{BTreeSet, HashSet};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use deadpool_postgres::{Manager, ManagerConfig, Pool, RecyclingMethod, Runtime};
use futures_util::StreamExt;
use serde::{Deserialize, Serialize};
use tokio_postgres::{AsyncMessage, NoTls};
use tokio_util::sync::CancellationToken;

/// The tables of the lease manager, as one migration (after `fields`).
///
/// `replicas` has one row per running replica with its heartbeat; `leases`
/// one row per held (or formerly held, expired) field. A field's lease goes
/// with the field (`ON DELETE CASCADE`).
pub const SCHEMA: &str = "\
CREATE TABLE IF NOT EXISTS replicas (
    id TEXT PRIMARY KEY,
    started_at TIMESTAMPTZ NOT NULL,
    heartbeat_at TIMESTAMPTZ NOT NULL
);
CREATE TABLE IF NOT EXISTS leases (
    field_id BIGINT PRIMARY KEY REFERENCES fields(id) ON DELETE CASCADE,
    holder TEXT NOT NULL,
    expires_at TIMESTAMPTZ NOT NULL,
    acquired_at TIMESTAMPTZ NOT NULL
);
CREATE INDEX IF NOT EXISTS leases_holder ON leases (holder);
";

/// Shortest wall-clock lease, whatever the clock speedup.
pub const MIN_WALL_LEASE: Duration = Duration::from_millis(200);

/// Longest a connection attempt to the database may take.
const CONNECT_TIMEOUT: Duration = Duration::from_secs(2);

/// Stale replica rows older than this are deleted by any replica's tick.
const FORGET_REPLICAS_AFTER_S: f64 = 86_400.0;

/// The `[replicas]` settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ReplicaSettings {
    /// This replica's name in the tables (`ROOTZONE_REPLICAS__ID`); none: a
    /// new `hostname-pid-random` at every start ([`ReplicaSettings::replica_id`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub id: Option<String>,
    /// How long a lease lasts, in seconds of the daemon's clock (which runs
    /// `clock.speedup` times faster than the wall clock); in [1, 3600].
    #[serde(deserialize_with = "super::settings::lenient_f64")]
    pub lease_s: f64,
}

impl Default for ReplicaSettings {
    /// A generated id and a 60 s lease.
    fn default() -> Self {
        ReplicaSettings {
            id: None,
            lease_s: 60.0,
        }
    }
}

/// Longest replica id.
pub const MAX_ID_LEN: usize = 64;

/// Whether `id` is 1 … 64 characters of `A-Za-z0-9._-`.
pub fn valid_id(id: &str) -> bool {
    !id.is_empty()
        && id.len() <= MAX_ID_LEN
        && id
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || matches!(b, b'.' | b'_' | b'-'))
}

impl ReplicaSettings {
    /// `lease_s` in [1, 3600]; the id, if given, 1 … 64 characters of
    /// `A-Za-z0-9._-`. The error names the key.
    pub fn validate(&self) -> Result<(), String> {
        let l = self.lease_s;
        if !(l.is_finite() && (1.0..=3600.0).contains(&l)) {
            return Err(format!("replicas.lease_s = {l} must lie in [1, 3600]"));
        }
        if let Some(id) = &self.id
            && !valid_id(id)
        {
            return Err(format!(
                "replicas.id = '{id}' must be 1 to {MAX_ID_LEN} characters of A-Z a-z 0-9 . _ -"
            ));
        }
        Ok(())
    }

    /// The configured id, or a new `hostname-pid-random` one.
    pub fn replica_id(&self) -> String {
        self.id.clone().unwrap_or_else(generated_id)
    }

    /// The lease in wall-clock time: `lease_s / speedup` seconds, at least
    /// [`MIN_WALL_LEASE`] (a speedup that is not a positive number counts
    /// as 1).
    pub fn wall_lease(&self, speedup: f64) -> Duration {
        let speedup = if speedup.is_finite() && speedup > 0.0 {
            speedup
        } else {
            1.0
        };
        let s = self.lease_s / speedup;
        if s.is_finite() {
            Duration::from_secs_f64(s).max(MIN_WALL_LEASE)
        } else {
            MIN_WALL_LEASE
        }
    }
}

/// `hostname-pid-random`, with the host name cut to 40 characters and any
/// character outside `A-Za-z0-9._-` replaced by `-`.
pub fn generated_id() -> String {
    let host = ["/proc/sys/kernel/hostname", "/etc/hostname"]
        .iter()
        .find_map(|p| {
            let h = std::fs::read_to_string(p).ok()?;
            let h = h.trim();
            (!h.is_empty()).then(|| h.to_string())
        })
        .unwrap_or_else(|| "replica".into());
    let host: String = host
        .chars()
        .take(40)
        .map(|c| {
            if c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-') {
                c
            } else {
                '-'
            }
        })
        .collect();
    let random = uuid::Uuid::new_v4().simple().to_string();
    format!("{host}-{}-{}", std::process::id(), &random[..8])
}

/// The lease database failed.
#[derive(Debug, thiserror::Error)]
pub enum LeaseError {
    /// No connection could be had from the pool (database down, pool
    /// exhausted, connection attempt timed out).
    #[error("lease database: no connection: {}", describe_pool(.0))]
    Pool(#[from] deadpool_postgres::PoolError),
    /// A statement failed.
    #[error("lease database: {}", describe(.0))]
    Postgres(#[from] tokio_postgres::Error),
    /// The database did not answer in time.
    #[error("lease database: no answer within {0:.1?}")]
    Timeout(Duration),
    /// The connection settings are not usable.
    #[error("lease database settings: {0}")]
    Config(String),
}

/// A pool error with the connection's cause, if any.
fn describe_pool(e: &deadpool_postgres::PoolError) -> String {
    match e {
        deadpool_postgres::PoolError::Backend(e) => describe(e),
        other => other.to_string(),
    }
}

/// A postgres error with the server's message and its cause, if any.
fn describe(e: &tokio_postgres::Error) -> String {
    if let Some(db) = e.as_db_error() {
        return format!("{} ({})", db.message(), db.code().code());
    }
    match std::error::Error::source(e) {
        Some(cause) => format!("{e}: {cause}"),
        None => e.to_string(),
    }
}

/// A connection pool for the lease manager that fails fast when the
/// database is gone: connection attempts time out after at most 2 s (less
/// for shorter leases), waiting for a pooled connection likewise,
/// statements are cancelled by the server after one lease
/// (`statement_timeout`), and TCP keepalives / `tcp_user_timeout` notice a
/// silently dead peer. [`Leases::tick`] bounds itself by the lease on top.
pub fn pool(url: &str, lease: Duration) -> Result<Pool, LeaseError> {
    let mut cfg: tokio_postgres::Config = url
        .parse()
        .map_err(|e| LeaseError::Config(format!("database URL: {e}")))?;
    let step = lease.clamp(MIN_WALL_LEASE, CONNECT_TIMEOUT);
    cfg.connect_timeout(step)
        .keepalives(true)
        .keepalives_idle(Duration::from_secs(5))
        .keepalives_interval(Duration::from_secs(2))
        .keepalives_retries(3)
        .tcp_user_timeout(lease.max(CONNECT_TIMEOUT));
    if cfg.get_application_name().is_none() {
        cfg.application_name("rootzone-leases");
    }
    if cfg.get_options().is_none() {
        cfg.options(format!(
            "-c statement_timeout={}",
            lease.as_millis().max(100)
        ));
    }
    let manager = Manager::from_config(
        cfg,
        NoTls,
        ManagerConfig {
            recycling_method: RecyclingMethod::Fast,
        },
    );
    Pool::builder(manager)
        .max_size(4)
        .runtime(Runtime::Tokio1)
        .wait_timeout(Some(step))
        .create_timeout(Some(step))
        .recycle_timeout(Some(step))
        .build()
        .map_err(|e| LeaseError::Config(format!("pool: {e}")))
}

/// 64-bit FNV-1a.
fn fnv1a(bytes: &[u8]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for &b in bytes {
        h ^= u64::from(b);
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    h
}

/// The splitmix64 finaliser.
fn splitmix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// The rendezvous weight of `field` at `replica`: the same in every process
/// and build (FNV-1a of the id, mixed with the field by splitmix64). Changing
/// it reshuffles every field during a rolling upgrade: don't.
pub fn weight(replica: &str, field: i64) -> u64 {
    splitmix(fnv1a(replica.as_bytes()) ^ splitmix(field as u64))
}

/// The replica of `replicas` that should run `field`: the highest weight,
/// ties (practically never) to the smallest id. None for no replicas.
pub fn owner<S: AsRef<str>>(replicas: &[S], field: i64) -> Option<&str> {
    replicas.iter().map(|r| r.as_ref()).max_by(|a, b| {
        weight(a, field)
            .cmp(&weight(b, field))
            .then_with(|| b.cmp(a))
    })
}

/// What a tick changed, relative to the previous successful tick. Sorted.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize)]
pub struct Change {
    /// Fields held now and not before.
    pub gained: Vec<i64>,
    /// Fields held before and not now: released (outside the share), or
    /// found with another holder on renewal.
    pub lost: Vec<i64>,
    /// Every field held now.
    pub held: Vec<i64>,
}

/// The lease manager's state, for `/healthz` and `/metrics`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LeaseStatus {
    /// This replica's id.
    pub replica: String,
    /// Fields [`Leases::holds`] is true for (none once the deadline lapsed).
    pub held: usize,
    /// Live replicas (this one included) seen by the last successful tick.
    pub live_replicas: usize,
    /// Seconds since the last successful renewal was sent; none before the
    /// first.
    pub last_renewal_age_s: Option<f64>,
    /// Whether the local deadline has not passed ([`Leases::holds`] can be
    /// true).
    pub valid: bool,
}

#[derive(Debug, Default)]
struct State {
    /// What [`Leases::holds`] answers from (with `valid_until`).
    held: BTreeSet<i64>,
    /// The held fields as told by the last [`Change`] (a tick shrinks
    /// `held` before it releases; this stays until the tick succeeds).
    reported: BTreeSet<i64>,
    /// The local deadline of every held lease.
    valid_until: Option<Instant>,
    /// When the last successful renewal was sent.
    renewed: Option<Instant>,
    live_replicas: usize,
}

/// Heartbeat, then the live replicas (this one included: the upserted row
/// is not visible to the statement's own snapshot, hence the union). Also
/// forgets replica rows not seen for a day.
const BEAT: &str = "\
WITH beat AS (
    INSERT INTO replicas (id, started_at, heartbeat_at)
    VALUES ($1, clock_timestamp(), clock_timestamp())
    ON CONFLICT (id) DO UPDATE SET heartbeat_at = excluded.heartbeat_at
    RETURNING id
), forgotten AS (
    DELETE FROM replicas
    WHERE heartbeat_at < clock_timestamp() - make_interval(secs => $3)
)
SELECT id FROM beat
UNION
SELECT id FROM replicas
WHERE heartbeat_at > clock_timestamp() - make_interval(secs => $2)";

/// Release, keep and renew/acquire in one statement. `$1` holder, `$2` the
/// share, `$3` the busy fields, `$4` the lease in seconds. The three parts
/// touch disjoint rows (outside the share and not busy / outside the share
/// and busy / the share), as data-modifying CTEs must.
///
/// Acquisition is `INSERT … ON CONFLICT DO UPDATE … WHERE` rather than
/// `SELECT … FOR UPDATE SKIP LOCKED` and a second statement: the upsert is
/// atomic per row under READ COMMITTED: when two replicas race for an
/// expired row, the second waits for the first's row lock and re-checks the
/// `WHERE` against the row the first wrote (no longer expired), so it takes
/// nothing; and free rows, renewals and takeovers are one round trip. Rows
/// are fed in field order so that two replicas upserting overlapping shares
/// (for a moment after a membership change) lock in the same order.
const RENEW: &str = "\
WITH released AS (
    DELETE FROM leases
    WHERE holder = $1 AND field_id <> ALL($2) AND field_id <> ALL($3)
    RETURNING field_id
), kept AS (
    UPDATE leases SET expires_at = clock_timestamp() + make_interval(secs => $4)
    WHERE holder = $1 AND field_id = ANY($3) AND field_id <> ALL($2)
    RETURNING field_id
), taken AS (
    INSERT INTO leases (field_id, holder, expires_at, acquired_at)
    SELECT f.id, $1, clock_timestamp() + make_interval(secs => $4), clock_timestamp()
    FROM fields f WHERE f.id = ANY($2)
    ORDER BY f.id
    ON CONFLICT (field_id) DO UPDATE
        SET holder = excluded.holder,
            expires_at = excluded.expires_at,
            acquired_at = CASE WHEN leases.holder = excluded.holder
                               THEN leases.acquired_at ELSE excluded.acquired_at END
        WHERE leases.holder = excluded.holder OR leases.expires_at < clock_timestamp()
    RETURNING field_id
)
SELECT field_id FROM kept
UNION ALL
SELECT field_id FROM taken";

/// Graceful exit: drop own leases and own replica row.
const RELEASE_ALL: &str = "\
WITH gone AS (DELETE FROM leases WHERE holder = $1)
DELETE FROM replicas WHERE id = $1";

/// The lease manager of one replica. See the module documentation for the
/// invariants.
///
/// Every replica must have its own id (generated ids are) and the same
/// lease (the same `replicas.lease_s` and `clock.speedup`): liveness is
/// judged with the judge's lease. A process restarted with a configured id
/// takes over the leases its predecessor still had.
pub struct Leases {
    pool: Pool,
    id: String,
    lease: Duration,
    margin: Duration,
    state: Mutex<State>,
    /// One tick (or release) at a time.
    turn: tokio::sync::Mutex<()>,
}

impl Leases {
    /// The manager of replica `id` with leases of `lease` (wall clock; see
    /// [`ReplicaSettings::wall_lease`]). `pool` should fail fast (see
    /// [`pool`]). Holds nothing until the first [`Leases::tick`].
    pub fn new(pool: Pool, id: String, lease: Duration) -> Leases {
        let lease = lease.max(MIN_WALL_LEASE);
        Leases {
            pool,
            id,
            lease,
            margin: lease / 5,
            state: Mutex::new(State::default()),
            turn: tokio::sync::Mutex::new(()),
        }
    }

    /// This replica's id.
    pub fn id(&self) -> &str {
        &self.id
    }

    /// The wall-clock lease.
    pub fn lease(&self) -> Duration {
        self.lease
    }

    /// A good interval between ticks: a quarter of the lease, so that a
    /// tick or two may fail (or be late) before the local deadline, at
    /// four-fifths of the lease, lapses.
    pub fn tick_interval(&self) -> Duration {
        self.lease / 4
    }

    fn state(&self) -> std::sync::MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Whether this replica may run `field` now: it held the field after the
    /// last successful tick and the local deadline (which ends before the
    /// database lets another replica take it) has not passed.
    pub fn holds(&self, field: i64) -> bool {
        let s = self.state();
        s.held.contains(&field) && s.valid_until.is_some_and(|v| Instant::now() < v)
    }

    /// The fields [`Leases::holds`] is true for, sorted.
    pub fn held(&self) -> Vec<i64> {
        let s = self.state();
        if s.valid_until.is_some_and(|v| Instant::now() < v) {
            s.held.iter().copied().collect()
        } else {
            Vec::new()
        }
    }

    /// The lease manager's state.
    pub fn status(&self) -> LeaseStatus {
        let s = self.state();
        let now = Instant::now();
        LeaseStatus {
            replica: self.id.clone(),
            held: if now < s.valid_until.unwrap_or(now) {
                s.held.len()
            } else {
                0
            },
            live_replicas: s.live_replicas,
            last_renewal_age_s: s.renewed.map(|r| now.duration_since(r).as_secs_f64()),
            valid: s.valid_until.is_some_and(|v| now < v),
        }
    }

    /// One round: heartbeat, read the live replicas, compute this replica's
    /// share of `fields` by rendezvous hashing, release held fields outside
    /// the share unless `busy` (busy ones are renewed instead), renew held
    /// fields in the share and acquire the free or expired ones. Two
    /// statements in all. Fields without a row in `fields` are ignored.
    ///
    /// Acquisition is one `INSERT … ON CONFLICT (field_id) DO UPDATE … WHERE
    /// leases.holder = me OR leases.expires_at < clock_timestamp()`, not
    /// `SELECT … FOR UPDATE SKIP LOCKED`: under READ COMMITTED a second
    /// replica racing for the same expired row waits for the first's row
    /// lock and re-checks the `WHERE` against the row the first wrote, so
    /// exactly one wins, and renewals, free rows and takeovers all go in one
    /// round trip with the expiry judged by the database clock.
    ///
    /// Fields to be released stop being held locally *before* the release
    /// is sent, so there is no moment at which this replica still believes
    /// it holds a field that another could already have taken.
    ///
    /// The [`Change`] is relative to the last successful tick; if the local
    /// deadline had lapsed in between (ticks failed for a lease), every
    /// field held now counts as gained: it was nobody's, or someone else's,
    /// for a while, and its state must be re-read.
    ///
    /// Call it well within the lease (e.g. every lease / 4). It returns
    /// within about one lease whatever the database does (pool, connect and
    /// statement timeouts, and the whole tick bounded by the lease); on an
    /// error nothing is extended and [`Leases::holds`] lapses at the old
    /// deadline. A deadlock between two replicas' statements, possible only
    /// for a moment after a membership change, is broken by the server and
    /// fails one of the ticks; the next one is normal.
    pub async fn tick(&self, fields: &[i64], busy: &HashSet<i64>) -> Result<Change, LeaseError> {
        let _turn = self.turn.lock().await;
        let started = Instant::now();
        let budget = self.lease;
        let client = tokio::time::timeout(budget, self.pool.get())
            .await
            .map_err(|_| LeaseError::Timeout(budget))??;
        let left = budget.saturating_sub(started.elapsed());
        let (live, held, sent) =
            match tokio::time::timeout(left, self.exchange(&client, fields, busy)).await {
                Ok(Ok(r)) => r,
                Ok(Err(e)) => {
                    if client.is_closed() {
                        drop(deadpool_postgres::Object::take(client));
                    }
                    return Err(e);
                }
                Err(_) => {
                    // the connection may hang with a half-read answer: don't
                    // hand it to the next tick
                    drop(deadpool_postgres::Object::take(client));
                    return Err(LeaseError::Timeout(budget));
                }
            };
        let mut s = self.state();
        // after a lapse the fields were nobody's for a while (another
        // replica may have run them): they count as gained anew
        let lapsed = s.valid_until.is_none_or(|v| sent >= v);
        let change = Change {
            gained: if lapsed {
                held.iter().copied().collect()
            } else {
                held.difference(&s.reported).copied().collect()
            },
            lost: s.reported.difference(&held).copied().collect(),
            held: held.iter().copied().collect(),
        };
        s.reported = held.clone();
        s.held = held;
        s.valid_until = Some(sent + self.lease - self.margin);
        s.renewed = Some(sent);
        s.live_replicas = live;
        drop(s);
        if !change.gained.is_empty() || !change.lost.is_empty() {
            tracing::info!(
                replica = %self.id,
                gained = change.gained.len(),
                lost = change.lost.len(),
                held = change.held.len(),
                live,
                "leases changed"
            );
        }
        Ok(change)
    }

    /// The two statements of a tick: (live replicas, held fields, when the
    /// renewal was sent).
    async fn exchange(
        &self,
        client: &deadpool_postgres::Client,
        fields: &[i64],
        busy: &HashSet<i64>,
    ) -> Result<(usize, BTreeSet<i64>, Instant), LeaseError> {
        let lease_s = self.lease.as_secs_f64();
        let beat = client.prepare_cached(BEAT).await?;
        let rows = client
            .query(&beat, &[&self.id, &lease_s, &FORGET_REPLICAS_AFTER_S])
            .await?;
        let live: Vec<String> = rows.iter().map(|r| r.get(0)).collect();
        let fields: BTreeSet<i64> = fields.iter().copied().collect();
        let share: Vec<i64> = fields
            .iter()
            .copied()
            .filter(|&f| owner(&live, f) == Some(self.id.as_str()))
            .collect();
        let renew = client.prepare_cached(RENEW).await?;
        {
            // stop holding what is about to be released *before* the
            // release reaches the database: once it has, another replica
            // may take the field at once
            let mut s = self.state();
            s.held
                .retain(|f| share.binary_search(f).is_ok() || busy.contains(f));
        }
        let busy: Vec<i64> = busy.iter().copied().collect();
        let sent = Instant::now();
        let rows = client
            .query(&renew, &[&self.id, &share, &busy, &lease_s])
            .await?;
        let held = rows.iter().map(|r| r.get::<_, i64>(0)).collect();
        Ok((live.len(), held, sent))
    }

    /// Graceful shutdown: stop holding anything at once, then delete this
    /// replica's leases and its replica row, so the others take its fields
    /// on their next tick instead of after a lease.
    pub async fn release_all(&self) -> Result<(), LeaseError> {
        let forget = || {
            let mut s = self.state();
            s.held.clear();
            s.reported.clear();
            s.valid_until = None;
        };
        forget();
        let _turn = self.turn.lock().await;
        // a tick that was under way has stored what it renewed: forget it
        // too, before the leases go
        forget();
        let budget = self.lease;
        let work = async {
            let client = self.pool.get().await?;
            client.execute(RELEASE_ALL, &[&self.id]).await?;
            Ok::<_, LeaseError>(())
        };
        tokio::time::timeout(budget, work)
            .await
            .map_err(|_| LeaseError::Timeout(budget))?
    }
}

/// First wait before reconnecting [`listen`]'s connection.
const BACKOFF_MIN: Duration = Duration::from_millis(200);
/// Longest wait between reconnection attempts.
const BACKOFF_MAX: Duration = Duration::from_secs(5);

/// Longest a connection of [`listen`] may take to be ready.
const LISTEN_CONNECT_TIMEOUT: Duration = Duration::from_secs(5);

/// `name` as a quoted SQL identifier.
fn quote_ident(name: &str) -> String {
    format!("\"{}\"", name.replace('"', "\"\""))
}

/// Listens on `channels` over a dedicated connection until `cancel`,
/// calling `on(channel, payload)` for every notification. On any connection
/// error it reconnects, waiting 0.2 s doubling to 5 s between attempts; after
/// each reconnect (not the first connection) it calls `on(channel, "")` once
/// per channel, since notifications sent while it was away are lost: the
/// callers then re-check their state. `on` runs on the listening task: keep
/// it short (e.g. send on a channel or wake a `Notify`).
///
/// Without a connect timeout in `config`, 2 s; TCP keepalives notice a
/// silently dead server on an idle connection.
pub async fn listen(
    mut config: tokio_postgres::Config,
    channels: &[&str],
    on: impl Fn(&str, &str) + Send + Sync + 'static,
    cancel: CancellationToken,
) {
    if config.get_connect_timeout().is_none() {
        config.connect_timeout(CONNECT_TIMEOUT);
    }
    config
        .keepalives(true)
        .keepalives_idle(Duration::from_secs(5))
        .keepalives_interval(Duration::from_secs(2))
        .keepalives_retries(3);
    let sql: String = channels
        .iter()
        .map(|c| format!("LISTEN {};", quote_ident(c)))
        .collect();
    let mut backoff = BACKOFF_MIN;
    let mut connected_before = false;
    loop {
        let outcome = tokio::select! {
            _ = cancel.cancelled() => return,
            r = listen_once(&config, &sql, channels, &on, &cancel, connected_before) => r,
        };
        match outcome {
            Ok(()) => return, // cancelled while listening
            Err((listened, e)) => {
                if listened {
                    connected_before = true;
                    backoff = BACKOFF_MIN;
                }
                tracing::warn!(error = %e, retry_in = ?backoff, "notification listener lost its connection");
            }
        }
        tokio::select! {
            _ = cancel.cancelled() => return,
            _ = tokio::time::sleep(backoff) => {}
        }
        backoff = (backoff * 2).min(BACKOFF_MAX);
    }
}

/// One connection of [`listen`]: connect, LISTEN, forward until an error
/// (with whether LISTEN had succeeded, and why) or `cancel` (Ok).
async fn listen_once(
    config: &tokio_postgres::Config,
    sql: &str,
    channels: &[&str],
    on: &(impl Fn(&str, &str) + Send + Sync),
    cancel: &CancellationToken,
    reconnect: bool,
) -> Result<(), (bool, String)> {
    // the connect timeout covers the TCP connection only: bound the
    // start-up exchange too (a server that accepts and never answers)
    let (client, mut connection) =
        tokio::time::timeout(LISTEN_CONNECT_TIMEOUT, config.connect(NoTls))
            .await
            .map_err(|_| {
                (
                    false,
                    format!("no answer within {LISTEN_CONNECT_TIMEOUT:?}"),
                )
            })?
            .map_err(|e| (false, describe(&e)))?;
    let messages = futures_util::stream::poll_fn(move |cx| connection.poll_message(cx));
    tokio::pin!(messages);
    // LISTEN while driving the connection
    {
        let subscribe = client.batch_execute(sql);
        tokio::pin!(subscribe);
        loop {
            tokio::select! {
                r = &mut subscribe => {
                    r.map_err(|e| (false, describe(&e)))?;
                    break;
                }
                m = messages.next() => match m {
                    Some(Ok(AsyncMessage::Notification(n))) => on(n.channel(), n.payload()),
                    Some(Ok(_)) => {}
                    Some(Err(e)) => return Err((false, describe(&e))),
                    None => return Err((false, "connection closed".into())),
                },
            }
        }
    }
    if reconnect {
        tracing::info!("notification listener reconnected");
        for c in channels {
            on(c, "");
        }
    }
    loop {
        tokio::select! {
            _ = cancel.cancelled() => return Ok(()),
            m = messages.next() => match m {
                Some(Ok(AsyncMessage::Notification(n))) => on(n.channel(), n.payload()),
                Some(Ok(_)) => {}
                Some(Err(e)) => return Err((true, describe(&e))),
                None => return Err((true, "connection closed".into())),
            },
        }
    }
}
