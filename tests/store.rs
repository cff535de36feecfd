//! The store's contract, on both backends: the embedded SQLite file and a
//! real PostgreSQL server (tests/common/postgres.rs). Each check runs once
//! per backend with the same expectations.

mod common;

use std::time::{Duration, Instant};

use chrono::{DateTime, TimeDelta, Utc};
use common::postgres::Postgres;
use rootzone::service::wire::{Actuator, FieldSpec, Forecast, Measurement, Setpoint};
use rootzone::store::{
    CycleOutputs, CycleQuery, CycleRun, Location, ReadingOutcome, Sensors, Store, StoreError,
};

/// A fresh store of each backend (the folder keeps SQLite's file alive).
fn backends() -> Vec<(Store, Option<String>, tempfile::TempDir)> {
    let dir = tempfile::tempdir().unwrap();
    let sqlite = Store::open(dir.path()).unwrap();
    let url = Postgres::shared().fresh_database();
    let pg = Store::connect(&Location::parse(&url).unwrap()).unwrap();
    vec![
        (sqlite, None, dir),
        (pg, Some(url), tempfile::tempdir().unwrap()),
    ]
}

fn spec(name: &str) -> FieldSpec {
    FieldSpec {
        name: name.into(),
        actuator: Actuator::None,
        simulation: None,
        ..FieldSpec::demo()
    }
}

fn at(s: &str) -> DateTime<Utc> {
    s.parse().unwrap()
}

fn reading(time: &str, theta: f64) -> Measurement {
    Measurement {
        time: at(time),
        theta,
        sensor: None,
        raw: None,
        true_theta: None,
    }
}

const NOW: &str = "2026-05-01T12:00:00Z";

#[test]
fn fields_are_created_read_renamed_and_deleted_with_unique_names() {
    for (store, _, _dir) in backends() {
        let kind = store.kind();
        let a = store.create_field(&spec("a"), at(NOW)).unwrap();
        let b = store.create_field(&spec("b"), at(NOW)).unwrap();
        assert!(b.id > a.id, "{kind}");
        let again = store.create_field(&spec("a"), at(NOW));
        assert!(
            matches!(&again, Err(StoreError::Conflict(m)) if m.contains("'a'")),
            "{kind}: {again:?}"
        );
        assert!(
            matches!(
                store.update_field(b.id, &spec("a")),
                Err(StoreError::Conflict(_))
            ),
            "{kind}"
        );
        assert!(store.update_field(b.id, &spec("c")).unwrap(), "{kind}");
        let names: Vec<String> = store
            .fields()
            .unwrap()
            .into_iter()
            .map(|f| f.spec.name)
            .collect();
        assert_eq!(names, ["a", "c"], "{kind}");
        assert_eq!(store.field(a.id).unwrap().unwrap().created_at, at(NOW));
        assert!(store.delete_field(a.id).unwrap(), "{kind}");
        assert!(!store.delete_field(a.id).unwrap(), "{kind}");
        assert!(store.field(a.id).unwrap().is_none(), "{kind}");
    }
}

#[test]
fn a_batch_is_stored_once_and_a_contradicting_one_is_refused_whole() {
    for (store, _, _dir) in backends() {
        let kind = store.kind();
        let f = store.create_field(&spec("m"), at(NOW)).unwrap().id;
        let t = |h: u32| format!("2026-05-01T{h:02}:00:00Z");
        let batch: Vec<Measurement> = (0..10)
            .map(|h| reading(&t(h), 0.2 + h as f64 * 0.001))
            .collect();
        assert_eq!(store.add_measurements(f, &batch).unwrap(), 10, "{kind}");
        // resent after a lost acknowledgement: nothing new
        assert_eq!(store.add_measurements(f, &batch).unwrap(), 0, "{kind}");
        // one new, one contradicting an old one: all refused, naming both θ
        let bad = [reading(&t(11), 0.3), reading(&t(3), 0.25)];
        match store.add_measurements(f, &bad) {
            Err(StoreError::Conflict(m)) => {
                assert!(m.starts_with("measurements[1]"), "{kind}: {m}");
                assert!(m.contains("0.203") && m.contains("0.25"), "{kind}: {m}");
            }
            other => panic!("{kind}: {other:?}"),
        }
        // within one batch as well
        let inner = [reading(&t(12), 0.3), reading(&t(12), 0.31)];
        assert!(
            matches!(store.add_measurements(f, &inner), Err(StoreError::Conflict(m)) if m.starts_with("measurements[1]")),
            "{kind}"
        );
        assert_eq!(store.count_measurements(f).unwrap(), 10, "{kind}");
        // a second sensor at the same time is another reading
        let other = Measurement {
            sensor: Some("deep".into()),
            ..reading(&t(3), 0.4)
        };
        assert_eq!(store.add_measurements(f, &[other]).unwrap(), 1, "{kind}");
        let primary = store
            .measurements(f, Some(at(&t(2))), Some(at(&t(4))), 100, Sensors::Primary)
            .unwrap();
        assert_eq!(
            primary.iter().map(|m| m.theta).collect::<Vec<_>>(),
            [2, 3, 4].map(|h| 0.2 + h as f64 * 0.001),
            "{kind}"
        );
        let all = store
            .measurements(f, Some(at(&t(3))), Some(at(&t(3))), 100, Sensors::All)
            .unwrap();
        assert_eq!(all.len(), 2, "{kind}");
        let before = store
            .measurement_before(f, at("2026-05-01T05:30:00Z"))
            .unwrap();
        assert_eq!(before.map(|m| m.theta), Some(0.2 + 5.0 * 0.001), "{kind}");
        let limited = store.measurements(f, None, None, 3, Sensors::All).unwrap();
        assert_eq!(limited.len(), 3, "{kind}");
    }
}

#[test]
fn readings_of_many_fields_are_stored_each_on_its_own() {
    for (store, _, _dir) in backends() {
        let kind = store.kind();
        let a = store.create_field(&spec("a"), at(NOW)).unwrap().id;
        let b = store.create_field(&spec("b"), at(NOW)).unwrap().id;
        let (t1, t2) = ("2026-05-01T10:00:00Z", "2026-05-01T11:00:00Z");
        store.add_measurements(a, &[reading(t1, 0.2)]).unwrap();
        let outcomes = store
            .add_readings(&[
                (a, reading(t1, 0.2)),
                (a, reading(t1, 0.25)),
                (a, reading(t2, 0.21)),
                (b, reading(t1, 0.3)),
                (b + 10, reading(t1, 0.3)),
            ])
            .unwrap();
        assert_eq!(
            outcomes,
            [
                ReadingOutcome::Duplicate,
                ReadingOutcome::Conflict(0.2),
                ReadingOutcome::Stored,
                ReadingOutcome::Stored,
                ReadingOutcome::NoField,
            ],
            "{kind}"
        );
        assert_eq!(store.count_measurements(a).unwrap(), 2, "{kind}");
        assert_eq!(store.count_measurements(b).unwrap(), 1, "{kind}");
    }
}

fn setpoint(field: i64, time: DateTime<Utc>, amount: f64) -> Setpoint {
    let body = serde_json::json!({
        "field_id": field, "time": time, "valid_from": time,
        "valid_until": time + TimeDelta::hours(2), "rate": 0.0, "amount_mm": amount,
        "plan": [0.0], "predicted_theta": [0.2], "zone": [[0.18, 0.23]],
        "model": "two-layer", "status": "converged", "iterations": 1, "solve_ms": 1.0,
        "degraded": [], "bias": 0.0
    });
    serde_json::from_value(body).unwrap()
}

#[test]
fn a_boundary_is_committed_once_with_its_estimate_and_setpoint() {
    for (store, url, _dir) in backends() {
        let kind = store.kind();
        let f = store.create_field(&spec("c"), at(NOW)).unwrap().id;
        let boundary = at("2026-05-01T12:00:00Z");
        if let Some(url) = &url {
            // on PostgreSQL only the holder of a live lease may commit
            let run = CycleRun {
                boundary,
                replica: "r1",
            };
            let refused = store
                .commit_cycle(&CycleOutputs {
                    setpoint: &setpoint(f, boundary, 1.0),
                    estimate: Some("{\"x\":1}"),
                    run: Some(run),
                })
                .unwrap();
            assert!(!refused, "no lease, no commit");
            let db = url.rsplit('/').next().unwrap();
            Postgres::shared().psql(
                db,
                &format!(
                    "INSERT INTO leases VALUES ({f}, 'r1', clock_timestamp() + interval '1 hour', clock_timestamp())"
                ),
            );
        }
        let run = CycleRun {
            boundary,
            replica: "r1",
        };
        let first = store
            .commit_cycle(&CycleOutputs {
                setpoint: &setpoint(f, boundary, 1.0),
                estimate: Some("{\"x\":1}"),
                run: Some(run),
            })
            .unwrap();
        assert!(first, "{kind}");
        let second = store
            .commit_cycle(&CycleOutputs {
                setpoint: &setpoint(f, boundary, 2.0),
                estimate: Some("{\"x\":2}"),
                run: Some(CycleRun {
                    boundary,
                    replica: "r1",
                }),
            })
            .unwrap();
        assert!(!second, "{kind}: the same boundary twice");
        let stored = store.recent_setpoints(f, 10).unwrap();
        assert_eq!(stored.len(), 1, "{kind}");
        assert_eq!(stored[0].amount_mm, 1.0, "{kind}");
        assert_eq!(
            store.estimate(f).unwrap().as_deref(),
            Some("{\"x\":1}"),
            "{kind}"
        );
        // a cycle asked for by a client is not a boundary's run
        store.add_setpoint(&setpoint(f, boundary, 3.0)).unwrap();
        assert_eq!(store.recent_setpoints(f, 10).unwrap().len(), 2, "{kind}");
        assert_eq!(
            store
                .cycle_runs(
                    f,
                    boundary - TimeDelta::days(1),
                    boundary + TimeDelta::days(1)
                )
                .unwrap(),
            [boundary],
            "{kind}"
        );
    }
}

#[test]
fn a_deferred_estimate_replaces_only_the_one_it_started_from() {
    for (store, url, _dir) in backends() {
        let kind = store.kind();
        let f = store.create_field(&spec("d"), at(NOW)).unwrap().id;
        let lease = |holder: &str| {
            if let Some(url) = &url {
                let db = url.rsplit('/').next().unwrap();
                Postgres::shared().psql(
                    db,
                    &format!(
                        "DELETE FROM leases WHERE field_id = {f};
                         INSERT INTO leases VALUES ({f}, '{holder}', clock_timestamp() + interval '1 hour', clock_timestamp())"
                    ),
                );
            }
        };
        lease("r1");
        // none stored: written only when none is expected
        assert!(
            !store
                .replace_estimate(f, Some("{}"), "{\"e\":1}", "r1")
                .unwrap(),
            "{kind}"
        );
        assert!(
            store.replace_estimate(f, None, "{\"e\":1}", "r1").unwrap(),
            "{kind}"
        );
        assert!(
            !store.replace_estimate(f, None, "{\"e\":9}", "r1").unwrap(),
            "{kind}"
        );
        assert_eq!(
            store.estimate(f).unwrap().as_deref(),
            Some("{\"e\":1}"),
            "{kind}"
        );
        // over the one it started from, not over another written meanwhile
        assert!(
            store
                .replace_estimate(f, Some("{\"e\":1}"), "{\"e\":2}", "r1")
                .unwrap(),
            "{kind}"
        );
        assert!(
            !store
                .replace_estimate(f, Some("{\"e\":1}"), "{\"e\":3}", "r1")
                .unwrap(),
            "{kind}"
        );
        assert_eq!(
            store.estimate(f).unwrap().as_deref(),
            Some("{\"e\":2}"),
            "{kind}"
        );
        if url.is_some() {
            // on PostgreSQL, only while the replica holds the field
            lease("r2");
            assert!(
                !store
                    .replace_estimate(f, Some("{\"e\":2}"), "{\"e\":4}", "r1")
                    .unwrap()
            );
            assert_eq!(store.estimate(f).unwrap().as_deref(), Some("{\"e\":2}"));
            assert!(
                store
                    .replace_estimate(f, Some("{\"e\":2}"), "{\"e\":4}", "r2")
                    .unwrap()
            );
        }
        // a deleted field takes none
        store.delete_field(f).unwrap();
        assert!(
            !store.replace_estimate(f, None, "{\"e\":5}", "r2").unwrap(),
            "{kind}"
        );
    }
}

fn forecast(issued: DateTime<Utc>, et0: f64) -> Forecast {
    Forecast {
        issued_at: issued,
        start: issued,
        step_s: 7200.0,
        et0_mm: vec![et0; 3],
        precip_mm: vec![0.0; 3],
    }
}

#[test]
fn a_cycle_reads_what_the_separate_reads_give_in_one_read() {
    for (store, _, _dir) in backends() {
        let kind = store.kind();
        let f = store.create_field(&spec("r"), at(NOW)).unwrap().id;
        let other = store.create_field(&spec("other"), at(NOW)).unwrap().id;
        let now = at(NOW);
        // readings every 2 h over 4 days, of two sensors; one after `now`
        let mut batch = Vec::new();
        for k in -48..=1 {
            let t = now + TimeDelta::hours(2 * k);
            batch.push(Measurement {
                time: t,
                ..reading(NOW, 0.2 + 0.001 * k as f64)
            });
            batch.push(Measurement {
                time: t,
                sensor: Some("deep".into()),
                ..reading(NOW, 0.25)
            });
        }
        store.add_measurements(f, &batch).unwrap();
        store.add_measurements(other, &[reading(NOW, 0.3)]).unwrap();
        for k in -30..=0 {
            store
                .add_setpoint(&setpoint(f, now + TimeDelta::hours(2 * k), k as f64))
                .unwrap();
            store
                .put_forecast(f, &forecast(now + TimeDelta::hours(2 * k), 1.0 + k as f64))
                .unwrap();
        }
        store
            .commit_cycle(&CycleOutputs {
                setpoint: &setpoint(f, now, 9.0),
                estimate: Some("{\"e\":1}"),
                run: None,
            })
            .unwrap();
        store.put_forecast_source("src", "{\"s\":2}").unwrap();
        let from = now - TimeDelta::hours(36);
        let before = now - TimeDelta::hours(60);
        let q = CycleQuery {
            field: f,
            now,
            readings_from: from,
            readings_limit: 1000,
            setpoints_from: before,
            recent: 3,
            forecasts_from: Some(before),
            forecast_source: Some("src".into()),
        };
        let read = store.cycle_read(&q).unwrap();
        let readings = store
            .measurements(f, Some(from), Some(now), 1000, Sensors::All)
            .unwrap();
        assert_eq!(read.readings.len(), 2 * 19, "{kind}: 36 h of two sensors");
        assert_eq!(read.readings, readings, "{kind}");
        assert_eq!(
            read.latest_primary,
            store.measurement_before(f, now).unwrap(),
            "{kind}"
        );
        assert_eq!(read.latest_primary.as_ref().unwrap().time, now, "{kind}");
        let setpoints = store.setpoints(f, Some(before), None, 10_000).unwrap();
        assert_eq!(read.setpoints.len(), setpoints.len(), "{kind}");
        assert_eq!(read.setpoints.len(), 32, "{kind}: 31 cycles and one more");
        for (a, b) in read.setpoints.iter().zip(&setpoints) {
            assert_eq!((a.time, a.amount_mm), (b.time, b.amount_mm), "{kind}");
        }
        let recent: Vec<f64> = read.recent.iter().map(|s| s.amount_mm).collect();
        let expected: Vec<f64> = store
            .recent_setpoints(f, 3)
            .unwrap()
            .iter()
            .map(|s| s.amount_mm)
            .collect();
        assert_eq!(recent, expected, "{kind}");
        assert_eq!(recent.len(), 3, "{kind}");
        assert_eq!(
            read.latest_forecast.as_ref().map(|f| f.et0_mm[0]),
            Some(1.0),
            "{kind}: the forecast put last"
        );
        let forecasts = store.forecasts_since(f, before, 500).unwrap();
        assert_eq!(read.forecasts.len(), 31, "{kind}");
        assert_eq!(
            read.forecasts
                .iter()
                .map(|f| f.issued_at)
                .collect::<Vec<_>>(),
            forecasts.iter().map(|f| f.issued_at).collect::<Vec<_>>(),
            "{kind}"
        );
        assert_eq!(read.estimate.as_deref(), Some("{\"e\":1}"), "{kind}");
        assert_eq!(read.forecast_source.as_deref(), Some("{\"s\":2}"), "{kind}");
        // nothing asked, nothing read; another field's rows are not read
        let bare = store
            .cycle_read(&CycleQuery {
                field: other,
                forecasts_from: None,
                forecast_source: None,
                ..q.clone()
            })
            .unwrap();
        assert_eq!(bare.readings.len(), 1, "{kind}");
        assert!(
            bare.setpoints.is_empty() && bare.recent.is_empty(),
            "{kind}"
        );
        assert!(
            bare.forecasts.is_empty() && bare.latest_forecast.is_none(),
            "{kind}"
        );
        assert!(
            bare.estimate.is_none() && bare.forecast_source.is_none(),
            "{kind}"
        );
    }
}

#[test]
fn documents_and_forecasts_round_trip() {
    for (store, _, _dir) in backends() {
        let kind = store.kind();
        let f = store.create_field(&spec("d"), at(NOW)).unwrap().id;
        assert_eq!(store.simulation(f).unwrap(), None, "{kind}");
        store.put_simulation(f, "one").unwrap();
        store.put_simulation(f, "two").unwrap();
        assert_eq!(
            store.simulation(f).unwrap().as_deref(),
            Some("two"),
            "{kind}"
        );
        store.put_forecast_source("k", "{}").unwrap();
        assert_eq!(
            store.forecast_source("k").unwrap().as_deref(),
            Some("{}"),
            "{kind}"
        );
        store.set_meta("clock", "x").unwrap();
        store.set_meta("clock", "y").unwrap();
        assert_eq!(store.meta("clock").unwrap().as_deref(), Some("y"), "{kind}");
        assert_eq!(store.meta("none").unwrap(), None, "{kind}");
    }
}

#[test]
fn a_schema_newer_than_the_binary_is_refused_naming_both_versions() {
    let dir = tempfile::tempdir().unwrap();
    drop(Store::open(dir.path()).unwrap());
    let file = dir.path().join("rootzone.sqlite3");
    let conn = rusqlite::Connection::open(&file).unwrap();
    let ours: i64 = conn
        .pragma_query_value(None, "user_version", |r| r.get(0))
        .unwrap();
    conn.pragma_update(None, "user_version", 99).unwrap();
    drop(conn);
    let e = Store::open(dir.path()).err().expect("refused").to_string();
    assert!(
        e.contains("version 99") && e.contains(&format!("version {ours}")),
        "{e}"
    );

    let pg = Postgres::shared();
    let url = pg.fresh_database();
    drop(Store::connect(&Location::parse(&url).unwrap()).unwrap());
    let db = url.rsplit('/').next().unwrap();
    let ours = pg.psql(db, "SELECT version FROM schema_version");
    pg.psql(db, "UPDATE schema_version SET version = 42");
    let e = Store::connect(&Location::parse(&url).unwrap())
        .err()
        .expect("refused")
        .to_string();
    assert!(
        e.contains("version 42") && e.contains(&format!("version {ours}")),
        "{e}"
    );
}

#[test]
fn an_unreachable_server_is_reported_within_seconds() {
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let url = format!("postgres://rootzone:secret@127.0.0.1:{port}/none");
    let started = Instant::now();
    let e = Store::connect(&Location::parse(&url).unwrap())
        .err()
        .expect("nothing listens there");
    assert!(
        started.elapsed() < Duration::from_secs(15),
        "{:?}",
        started.elapsed()
    );
    let text = e.to_string();
    assert!(matches!(e, StoreError::Unavailable(_)), "{text}");
    assert!(
        text.contains(&port.to_string()) && !text.contains("secret"),
        "{text}"
    );
}

#[test]
fn a_lost_server_is_unavailable_and_the_store_recovers_when_it_returns() {
    let pg = Postgres::start();
    let url = pg.url("postgres");
    let store = Store::connect(&Location::parse(&url).unwrap()).unwrap();
    let f = store.create_field(&spec("lost"), at(NOW)).unwrap().id;
    pg.kill();
    let started = Instant::now();
    let e = store
        .add_measurements(f, &[reading("2026-05-01T10:00:00Z", 0.2)])
        .expect_err("the server is gone");
    assert!(matches!(e, StoreError::Unavailable(_)), "{e}");
    assert!(
        started.elapsed() < Duration::from_secs(25),
        "{:?}",
        started.elapsed()
    );
    pg.resume();
    // the pool makes new connections: the write goes through
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        match store.add_measurements(f, &[reading("2026-05-01T10:00:00Z", 0.2)]) {
            Ok(n) => {
                assert_eq!(n, 1);
                break;
            }
            Err(e) => assert!(Instant::now() < deadline, "not back: {e}"),
        }
        std::thread::sleep(Duration::from_millis(200));
    }
    assert_eq!(store.count_measurements(f).unwrap(), 1);
}

#[test]
fn storage_urls_are_parsed_or_refused_with_a_reason() {
    assert_eq!(
        Location::parse("sqlite:/var/lib/rootzone").unwrap(),
        Location::Sqlite("/var/lib/rootzone".into())
    );
    assert_eq!(
        Location::parse("sqlite:/var/lib/rootzone/rootzone.sqlite3").unwrap(),
        Location::Sqlite("/var/lib/rootzone".into())
    );
    assert!(matches!(
        Location::parse("postgres://u@db:5432/rootzone").unwrap(),
        Location::Postgres(_)
    ));
    for bad in [
        "mysql://x",
        "sqlite:",
        "",
        "postgres://u:pw@host:notaport/db",
    ] {
        let e = Location::parse(bad)
            .err()
            .unwrap_or_else(|| panic!("{bad} accepted"));
        assert!(!e.contains("pw@"), "{e}");
    }
}
