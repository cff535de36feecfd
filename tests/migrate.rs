//! `rootzone migrate --from sqlite:… --to postgres:…`, the real binary
//! against a real PostgreSQL server: every row arrives with its id, the
//! new ids continue after them, a second copy into live data is refused.

mod common;

use std::process::Command;

use chrono::{DateTime, TimeDelta, Utc};
use common::postgres::Postgres;
use rootzone::service::wire::{Actuator, FieldSpec, Measurement, Setpoint};
use rootzone::store::{CycleOutputs, CycleRun, Location, Sensors, Store};

fn spec(name: &str) -> FieldSpec {
    FieldSpec {
        name: name.into(),
        actuator: Actuator::None,
        simulation: None,
        ..FieldSpec::demo()
    }
}

fn setpoint(field: i64, time: DateTime<Utc>, amount: f64) -> Setpoint {
    serde_json::from_value(serde_json::json!({
        "field_id": field, "time": time, "valid_from": time,
        "valid_until": time + TimeDelta::hours(2), "rate": 0.0, "amount_mm": amount,
        "plan": [0.0], "predicted_theta": [0.2], "zone": [[0.18, 0.23]],
        "model": "two-layer", "status": "converged", "iterations": 1, "solve_ms": 1.0,
        "degraded": [], "bias": 0.0
    }))
    .unwrap()
}

fn migrate(from: &str, to: &str) -> (i32, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_rootzone"))
        .args(["migrate", "--from", from, "--to", to])
        .output()
        .unwrap();
    (
        out.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&out.stdout).into(),
        String::from_utf8_lossy(&out.stderr).into(),
    )
}

#[test]
fn a_sqlite_store_moves_to_postgres_whole_with_its_ids() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let t0: DateTime<Utc> = "2026-05-01T00:00:00Z".parse().unwrap();
    let (ids, n_measurements) = {
        let store = Store::open(&data).unwrap();
        // a deleted field leaves a gap in the ids, which must survive
        let gone = store.create_field(&spec("gone"), t0).unwrap();
        let a = store.create_field(&spec("a"), t0).unwrap().id;
        let b = store.create_field(&spec("b"), t0).unwrap().id;
        store.delete_field(gone.id).unwrap();
        let mut n = 0;
        for (k, f) in [a, b].into_iter().enumerate() {
            let batch: Vec<Measurement> = (0..7000)
                .map(|i| Measurement {
                    time: t0 + TimeDelta::minutes(i),
                    theta: 0.2 + (i % 100) as f64 * 1e-4 + k as f64 * 0.01,
                    sensor: if i % 3 == 0 {
                        Some("deep".into())
                    } else {
                        None
                    },
                    raw: (i % 5 == 0).then_some(1234.5),
                    true_theta: None,
                })
                .collect();
            n += store.add_measurements(f, &batch).unwrap();
            store
                .commit_cycle(&CycleOutputs {
                    setpoint: &setpoint(f, t0, 1.5 + k as f64),
                    estimate: Some("{\"e\":1}"),
                    run: Some(CycleRun {
                        boundary: t0,
                        replica: "one",
                    }),
                })
                .unwrap();
            store.put_simulation(f, "{\"s\":2}").unwrap();
        }
        store.set_meta("clock", "2026-05-02T00:00:00Z").unwrap();
        (vec![a, b], n)
    };
    let pg = Postgres::shared();
    let url = pg.fresh_database();
    let from = format!("sqlite:{}", data.display());
    let (code, stdout, stderr) = migrate(&from, &url);
    assert_eq!(code, 0, "{stderr}");
    assert!(
        stdout.contains("fields 2") && stdout.contains(&format!("measurements {n_measurements}")),
        "{stdout}"
    );

    let source = Store::open(&data).unwrap();
    let target = Store::connect(&Location::parse(&url).unwrap()).unwrap();
    let names = |s: &Store| {
        s.fields()
            .unwrap()
            .into_iter()
            .map(|f| (f.id, f.spec, f.created_at))
            .collect::<Vec<_>>()
    };
    assert_eq!(names(&source), names(&target));
    assert_eq!(
        target
            .fields()
            .unwrap()
            .iter()
            .map(|f| f.id)
            .collect::<Vec<_>>(),
        ids
    );
    for &f in &ids {
        let all = |s: &Store| {
            s.measurements(f, None, None, 100_000, Sensors::All)
                .unwrap()
        };
        let (m1, m2) = (all(&source), all(&target));
        assert_eq!(m1.len(), 7000);
        assert_eq!(m1, m2);
        assert_eq!(
            source.recent_setpoints(f, 5).unwrap().len(),
            target.recent_setpoints(f, 5).unwrap().len()
        );
        assert_eq!(
            target.recent_setpoints(f, 1).unwrap()[0].amount_mm,
            source.recent_setpoints(f, 1).unwrap()[0].amount_mm
        );
        assert_eq!(target.estimate(f).unwrap().as_deref(), Some("{\"e\":1}"));
        assert_eq!(target.simulation(f).unwrap().as_deref(), Some("{\"s\":2}"));
        assert_eq!(
            target.cycle_runs(f, t0, t0).unwrap(),
            [t0],
            "the boundary's run moves with it"
        );
    }
    assert_eq!(
        target.meta("clock").unwrap().as_deref(),
        Some("2026-05-02T00:00:00Z")
    );
    // new rows continue after the copied ids
    let c = target.create_field(&spec("c"), t0).unwrap();
    assert!(c.id > *ids.last().unwrap(), "{}", c.id);

    // a second copy would merge into live data: refused, exit 2
    let (code, _, stderr) = migrate(&from, &url);
    assert_eq!(code, 2, "{stderr}");
    assert!(stderr.contains("empty database"), "{stderr}");
}

#[test]
fn bad_migrate_arguments_exit_2_with_the_reason() {
    let dir = tempfile::tempdir().unwrap();
    let empty = format!("sqlite:{}", dir.path().display());
    for (from, to, needle) in [
        ("mysql://x/y", "sqlite:/tmp/x", "--from"),
        (
            empty.as_str(),
            "sqlite:/tmp/elsewhere",
            "no rootzone.sqlite3",
        ),
        (empty.as_str(), empty.as_str(), "same store"),
    ] {
        let (code, _, stderr) = migrate(from, to);
        assert_eq!(code, 2, "{from} → {to}: {stderr}");
        assert!(stderr.contains(needle), "{stderr}");
    }
}
