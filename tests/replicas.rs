//! Failover with real processes: three `rootzone serve` replicas on one
//! real PostgreSQL server, 300 fields on an accelerated clock, one replica
//! killed with SIGKILL. Its fields' cycles resume on the others; over the
//! run no (field, boundary) runs twice or is skipped, and every
//! acknowledged measurement is stored. A replica whose database is lost
//! stops running cycles before its leases expire and resumes after.

mod common;

use std::collections::{BTreeMap, HashSet};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use chrono::{DateTime, Utc};
use common::postgres::Postgres;
use common::*;
use serde_json::{Value, json};

/// Clock seconds per wall second.
const SPEEDUP: f64 = 60.0;
/// A field's control period [clock s]: 10 s of wall time.
const PERIOD_S: f64 = 600.0;
/// The lease [clock s]: 1 s of wall time.
const LEASE_S: f64 = 60.0;

fn replica(dir: &std::path::Path, url: &str, id: &str, epoch: &str) -> Daemon {
    std::fs::create_dir_all(dir).unwrap();
    start_with(
        dir,
        &config(""),
        &[
            ("ROOTZONE_STORAGE__URL", url),
            ("ROOTZONE_REPLICAS__ID", id),
            ("ROOTZONE_REPLICAS__LEASE_S", &LEASE_S.to_string()),
            ("ROOTZONE_CLOCK__SPEEDUP", &SPEEDUP.to_string()),
            ("ROOTZONE_CLOCK__EPOCH", epoch),
        ],
    )
}

fn health(d: &Daemon) -> Value {
    json_of(&curl(d, "GET", "/healthz", None, None).2)
}

fn db(url: &str) -> &str {
    url.rsplit('/').next().unwrap()
}

/// Rows of a psql query, each split on `|`.
fn rows(pg: &Postgres, url: &str, sql: &str) -> Vec<Vec<String>> {
    pg.psql(db(url), sql)
        .lines()
        .filter(|l| !l.is_empty())
        .map(|l| l.split('|').map(str::to_string).collect())
        .collect()
}

fn wait_for(what: &str, limit: Duration, mut ok: impl FnMut() -> bool) {
    let deadline = Instant::now() + limit;
    while !ok() {
        assert!(Instant::now() < deadline, "{what}: not within {limit:?}");
        std::thread::sleep(Duration::from_millis(200));
    }
}

#[test]
fn a_killed_replica_s_fields_resume_on_the_others_with_no_cycle_doubled_or_skipped() {
    let pg = Postgres::shared();
    let url = pg.fresh_database();
    let dir = tempfile::tempdir().unwrap();
    let epoch = Utc::now().to_rfc3339();
    let mut daemons: Vec<Option<Daemon>> = ["r1", "r2", "r3"]
        .iter()
        .map(|id| Some(replica(&dir.path().join(id), &url, id, &epoch)))
        .collect();
    let d = |i: usize, ds: &[Option<Daemon>]| ds[i].as_ref().map(|d| d.base.clone());
    // 300 fields: 294 with sensors of their own, 6 simulated plants
    for k in 0..300 {
        let spec = if k % 50 == 0 {
            json!({"name": format!("sim-{k}"), "model": "two-layer",
                   "control_period_s": PERIOD_S, "actuator": {"kind": "simulated"},
                   "simulation": {"scenario": "dry", "measurement_noise": 0.0,
                       "process_noise": 0.0, "forecast_error": 0.0, "seed": k,
                       "measurement_interval_s": 300.0, "initial_head": -0.3}})
        } else {
            json!({"name": format!("f-{k}"), "model": "two-layer",
                   "control_period_s": PERIOD_S, "measurement_wait_s": 60.0})
        };
        let target = daemons[k % 3].as_ref().unwrap();
        let r = curl(
            target,
            "POST",
            "/v1/fields",
            Some(&spec.to_string()),
            Some(TOKEN),
        );
        assert_eq!(r.0, 201, "{}", r.2);
    }
    // every field leased by exactly one replica, spread across the three
    wait_for("all 300 fields leased", Duration::from_secs(30), || {
        let held: i64 = (0..3)
            .map(|i| {
                health(daemons[i].as_ref().unwrap())["leases"]["held"]
                    .as_i64()
                    .unwrap_or(0)
            })
            .sum();
        held == 300
    });
    for daemon in daemons.iter().flatten() {
        let h = health(daemon);
        let held = h["leases"]["held"].as_i64().unwrap();
        assert!((60..=140).contains(&held), "{h}");
        assert_eq!(h["storage"], "postgres");
        assert_eq!(h["database"], "up");
    }

    // measurements posted to every replica throughout; the acknowledged ones
    let acked: Arc<Mutex<Vec<(i64, String)>>> = Arc::default();
    let stop = Arc::new(AtomicBool::new(false));
    let bases: Arc<Mutex<Vec<Option<String>>>> =
        Arc::new(Mutex::new((0..3).map(|i| d(i, &daemons)).collect()));
    let poster = {
        let (acked, stop, bases) = (acked.clone(), stop.clone(), bases.clone());
        std::thread::spawn(move || {
            let mut k = 0i64;
            while !stop.load(Ordering::Relaxed) {
                k += 1;
                let field = 1 + (k * 7) % 300;
                let target = bases.lock().unwrap()[(k % 3) as usize].clone();
                let Some(base) = target else { continue };
                let time = (Utc::now() - chrono::TimeDelta::seconds(k)).to_rfc3339();
                let body = json!([{"time": time, "theta": 0.25}]).to_string();
                let r = curl_at(
                    &base,
                    "POST",
                    &format!("/v1/fields/{field}/measurements"),
                    Some(&body),
                    Some(TOKEN),
                );
                if r.0 == 201 {
                    acked.lock().unwrap().push((field, time));
                }
                std::thread::sleep(Duration::from_millis(20));
            }
        })
    };

    // two periods on three replicas, then r3 dies
    std::thread::sleep(Duration::from_secs_f64(2.0 * PERIOD_S / SPEEDUP));
    let r3_fields: HashSet<i64> = rows(pg, &url, "SELECT field_id FROM leases WHERE holder = 'r3'")
        .iter()
        .map(|r| r[0].parse().unwrap())
        .collect();
    assert!(!r3_fields.is_empty());
    bases.lock().unwrap()[2] = None;
    let mut r3 = daemons[2].take().unwrap();
    let killed_at = Utc::now();
    r3.child.kill().unwrap(); // SIGKILL
    let _ = r3.child.wait();
    drop(r3);

    // r3's fields are leased by the survivors
    wait_for("r3's fields taken over", Duration::from_secs(20), || {
        rows(
            pg,
            &url,
            "SELECT count(*) FROM leases WHERE holder IN ('r1', 'r2') AND expires_at > clock_timestamp()",
        )[0][0]
            == "300"
    });
    let takeover: Vec<f64> = rows(
        pg,
        &url,
        &format!(
            "SELECT extract(epoch FROM acquired_at - '{}'::timestamptz) FROM leases WHERE field_id IN ({})",
            killed_at.to_rfc3339(),
            r3_fields.iter().map(i64::to_string).collect::<Vec<_>>().join(",")
        ),
    )
    .iter()
    .map(|r| r[0].parse().unwrap())
    .collect();
    let lease_wall = LEASE_S / SPEEDUP;
    let worst = takeover.iter().cloned().fold(f64::MIN, f64::max);
    assert!(
        worst <= lease_wall,
        "takeover after {worst} s (lease {lease_wall} s)"
    );
    // three more periods on two replicas
    std::thread::sleep(Duration::from_secs_f64(3.0 * PERIOD_S / SPEEDUP));
    stop.store(true, Ordering::Relaxed);
    poster.join().unwrap();

    // every field ran every boundary once, from its first to its last,
    // and the last lies after the kill by more than a period
    let runs = rows(
        pg,
        &url,
        "SELECT field_id, boundary, replica FROM cycle_runs ORDER BY field_id, boundary",
    );
    let mut by_field: BTreeMap<i64, Vec<(i64, String)>> = BTreeMap::new();
    for r in &runs {
        by_field
            .entry(r[0].parse().unwrap())
            .or_default()
            .push((r[1].parse().unwrap(), r[2].clone()));
    }
    assert_eq!(by_field.len(), 300, "every field ran scheduled cycles");
    let period_ms = (PERIOD_S * 1000.0) as i64;
    let kill_ms = clock_ms(&epoch, killed_at);
    for (field, list) in &by_field {
        for w in list.windows(2) {
            assert_eq!(
                w[1].0 - w[0].0,
                period_ms,
                "field {field}: a boundary skipped: {list:?}"
            );
        }
        let last = list.last().unwrap().0;
        assert!(
            last > kill_ms + period_ms,
            "field {field}: no cycle after the kill: {list:?}"
        );
        if r3_fields.contains(field) {
            assert!(
                list.iter().any(|(b, r)| r != "r3" && *b > kill_ms),
                "{field}: {list:?}"
            );
        }
    }
    // a scheduled setpoint per boundary: none stored twice
    let doubled = rows(
        pg,
        &url,
        "SELECT s.field_id, s.time, count(*) FROM setpoints s JOIN cycle_runs c
             ON c.field_id = s.field_id AND c.boundary = s.time
         GROUP BY s.field_id, s.time HAVING count(*) > 1",
    );
    assert!(doubled.is_empty(), "doubled: {doubled:?}");
    // every acknowledged measurement is stored
    let acked = acked.lock().unwrap().clone();
    assert!(acked.len() > 100, "{} acknowledged", acked.len());
    let stored: HashSet<(i64, i64)> = rows(
        pg,
        &url,
        "SELECT field_id, time FROM measurements WHERE sensor IS NULL",
    )
    .iter()
    .map(|r| (r[0].parse().unwrap(), r[1].parse().unwrap()))
    .collect();
    for (field, time) in &acked {
        let t: DateTime<Utc> = time.parse().unwrap();
        assert!(
            stored.contains(&(*field, t.timestamp_millis())),
            "lost: field {field} at {time}"
        );
    }
    // simulated plants moved with their lease: r3's kept being measured
    let sims: Vec<i64> = rows(
        pg,
        &url,
        "SELECT id FROM fields WHERE spec LIKE '%\"simulated\"%'",
    )
    .iter()
    .map(|r| r[0].parse().unwrap())
    .collect();
    for id in sims {
        let after = rows(
            pg,
            &url,
            &format!("SELECT count(*) FROM measurements WHERE field_id = {id} AND true_theta IS NOT NULL AND time > {}", kill_ms + period_ms),
        )[0][0]
            .parse::<i64>()
            .unwrap();
        assert!(
            after >= 2,
            "simulated field {id}: {after} readings after the kill"
        );
    }
    // the first cycle of r3's fields after the kill: how long after its
    // boundary (or after the kill, for a boundary r3 left unrun) it ran
    let late: Vec<f64> = rows(
        pg,
        &url,
        &format!(
            "SELECT boundary, extract(epoch FROM done_at) FROM cycle_runs c WHERE field_id IN ({}) \
             AND replica <> 'r3' AND boundary = (SELECT min(boundary) FROM cycle_runs d \
             WHERE d.field_id = c.field_id AND d.replica <> 'r3' AND d.boundary > {})",
            r3_fields
                .iter()
                .map(i64::to_string)
                .collect::<Vec<_>>()
                .join(","),
            kill_ms - period_ms
        ),
    )
    .iter()
    .map(|r| {
        let boundary: i64 = r[0].parse().unwrap();
        let done: f64 = r[1].parse().unwrap();
        let e: DateTime<Utc> = epoch.parse().unwrap();
        let due_wall = e.timestamp_millis() as f64 / 1e3
            + (boundary - e.timestamp_millis()) as f64 / 1e3 / SPEEDUP;
        done - due_wall.max(killed_at.timestamp_millis() as f64 / 1e3)
    })
    .collect();
    let mut late = late;
    late.sort_by(f64::total_cmp);
    eprintln!(
        "failover: r3's fields' next cycle ran [wall s after due or kill]: min {:.2}, median {:.2}, max {:.2} ({} fields)",
        late[0],
        late[late.len() / 2],
        late[late.len() - 1],
        late.len()
    );
    let mut takeover = takeover;
    takeover.sort_by(f64::total_cmp);
    eprintln!(
        "failover: {} fields of r3; lease takeover after the kill [wall s]: min {:.2}, median {:.2}, max {:.2}; \
         {} acknowledged measurements, all stored; {} cycle runs",
        r3_fields.len(),
        takeover[0],
        takeover[takeover.len() / 2],
        takeover[takeover.len() - 1],
        acked.len(),
        runs.len()
    );
    for d in daemons.iter().flatten() {
        d.sigterm();
    }
}

/// Clock time (ms) at wall time `t` on the shared accelerated clock.
fn clock_ms(epoch: &str, t: DateTime<Utc>) -> i64 {
    let e: DateTime<Utc> = epoch.parse().unwrap();
    e.timestamp_millis() + (((t - e).num_milliseconds() as f64) * SPEEDUP) as i64
}

#[test]
fn a_replica_that_loses_its_database_pauses_its_cycles_and_resumes() {
    let pg = Postgres::start();
    let url = pg.url("postgres");
    let dir = tempfile::tempdir().unwrap();
    let epoch = Utc::now().to_rfc3339();
    let d = replica(dir.path(), &url, "alone", &epoch);
    let spec = json!({"name": "f", "model": "two-layer", "control_period_s": PERIOD_S,
                      "measurement_wait_s": 60.0});
    let r = curl(
        &d,
        "POST",
        "/v1/fields",
        Some(&spec.to_string()),
        Some(TOKEN),
    );
    assert_eq!(r.0, 201, "{}", r.2);
    wait_for("the lease", Duration::from_secs(10), || {
        health(&d)["leases"]["held"] == 1
    });
    pg.kill();
    // before the lease could pass to anyone: no longer valid here
    let lost = Instant::now();
    wait_for("the lease lapses", Duration::from_secs(5), || {
        health(&d)["leases"]["valid"] == false
    });
    assert!(lost.elapsed() <= Duration::from_secs_f64(LEASE_S / SPEEDUP + 0.5));
    let h = health(&d);
    assert_eq!(h["database"], "unavailable", "{h}");
    // writes: 503 problem+json, nothing stored
    let m = json!([{"time": now_minus(1), "theta": 0.25}]).to_string();
    let r = curl(
        &d,
        "POST",
        "/v1/fields/1/measurements",
        Some(&m),
        Some(TOKEN),
    );
    problem(r, 503, "database is unavailable");
    let metrics = curl(&d, "GET", "/metrics", None, None).2;
    assert!(metrics.contains("rootzone_database_up 0"), "{metrics}");
    pg.resume();
    wait_for("the database is back", Duration::from_secs(20), || {
        let h = health(&d);
        h["database"] == "up" && h["leases"]["valid"] == true
    });
    let r = curl(
        &d,
        "POST",
        "/v1/fields/1/measurements",
        Some(&m),
        Some(TOKEN),
    );
    assert_eq!(r.0, 201, "{}", r.2);
    // and the next boundary's cycle runs
    let before = pg.psql("postgres", "SELECT count(*) FROM cycle_runs");
    wait_for(
        "a cycle after the return",
        Duration::from_secs_f64(2.0 * PERIOD_S / SPEEDUP + 5.0),
        || pg.psql("postgres", "SELECT count(*) FROM cycle_runs") != before,
    );
}
