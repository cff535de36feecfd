//! A field's state estimate carried from cycle to cycle: a cycle goes on
//! from the stored estimate when no reading came in late, and replays from
//! the settled one when one did. Either way the estimate after a chain of
//! cycles is the one a single pass over the same readings gives (the
//! filter's random draws travel in its snapshot), to the last bit.

use std::path::Path;
use std::sync::Arc;

use chrono::{DateTime, TimeDelta, Utc};
use rootzone::service::engine::{Engine, Models, StoredEstimate};
use rootzone::service::wire::{Actuator, FieldSpec, Measurement};
use rootzone::store::Store;
use rootzone::surrogate::ModelFile;

fn engine(dir: &Path) -> (Arc<Store>, Engine) {
    let store = Arc::new(Store::open(dir).unwrap());
    let models = Path::new(env!("CARGO_MANIFEST_DIR")).join("models");
    let models = Models {
        two_layer: ModelFile::load(&models.join("two-layer.json")).unwrap(),
        lstm: ModelFile::load(&models.join("single-lstm.json")).unwrap(),
    };
    (store.clone(), Engine::new(store, models))
}

fn spec() -> FieldSpec {
    FieldSpec {
        name: "resume".into(),
        actuator: Actuator::None,
        simulation: None,
        ..FieldSpec::demo()
    }
}

fn reading(time: DateTime<Utc>, theta: f64) -> Measurement {
    Measurement {
        time,
        theta,
        sensor: None,
        raw: None,
        true_theta: None,
    }
}

/// A wet field drying down: above its zone, so no cycle irrigates and the
/// estimate's forcing is the same whenever it is computed.
fn readings(t0: DateTime<Utc>, n: usize) -> Vec<Measurement> {
    (0..n)
        .map(|k| reading(t0 + TimeDelta::hours(2 * k as i64), 0.33 - 0.002 * k as f64))
        .collect()
}

fn stored(store: &Store, field: i64) -> StoredEstimate {
    serde_json::from_str(&store.estimate(field).unwrap().expect("an estimate")).unwrap()
}

/// Field 1 of a fresh store given `all` at once and one cycle at `end`.
fn one_pass(all: &[Measurement], end: DateTime<Utc>) -> StoredEstimate {
    let dir = tempfile::tempdir().unwrap();
    let (store, engine) = engine(dir.path());
    let field = store.create_field(&spec(), all[0].time).unwrap();
    store.add_measurements(field.id, all).unwrap();
    engine.control_cycle(&field, end, None).unwrap();
    stored(&store, field.id)
}

#[test]
fn a_chain_of_cycles_estimates_as_one_pass_does_with_and_without_late_readings() {
    let t0: DateTime<Utc> = "2026-06-01T00:00:00Z".parse().unwrap();
    let n = 10;
    let on_time = readings(t0, n);
    // a reading half an hour before boundary 6, arriving 25 min after it
    let late = reading(t0 + TimeDelta::minutes(6 * 120 - 30), 0.3205);
    let end = on_time[n - 1].time;

    let dir = tempfile::tempdir().unwrap();
    let (store, engine) = engine(dir.path());
    let field = store.create_field(&spec(), t0).unwrap();
    for (k, m) in on_time.iter().enumerate() {
        store
            .add_measurements(field.id, std::slice::from_ref(m))
            .unwrap();
        let s = engine
            .control_cycle(&field, m.time, None)
            .unwrap()
            .unwrap()
            .setpoint;
        assert_eq!(s.rate, 0.0, "cycle {k} irrigated a field above its zone");
        if k == 6 {
            store
                .add_measurements(field.id, std::slice::from_ref(&late))
                .unwrap();
        }
        if k >= 2 {
            // in the steady state the estimate settles on the reading before
            let e = stored(&store, field.id);
            assert_eq!(e.time, m.time);
            assert_eq!(e.settled.as_ref().unwrap().time, on_time[k - 1].time);
        }
    }
    let chain = stored(&store, field.id);

    let mut with_late = on_time.clone();
    with_late.push(late.clone());
    with_late.sort_by_key(|m| m.time);
    let reference = one_pass(&with_late, end);
    let without = one_pass(&on_time, end);
    assert_eq!(chain.time, reference.time);
    assert_eq!(
        chain.snapshot.members, reference.snapshot.members,
        "the chain of cycles and the single pass over the same readings differ"
    );
    // and the late reading counted: without it the estimate is another
    assert_ne!(
        chain.snapshot.members, without.snapshot.members,
        "the late reading made no difference"
    );
}

/// A chain of scheduled cycles at the readings' times, on a daemon's
/// engine (`defer`: estimates deferred and brought up to date after each
/// cycle, except after the cycles of `skip`) or on one that brings them up
/// to date in the cycle. Returns the setpoints' rates, the cycles that
/// deferred, and the stored estimate at the end.
fn scheduled_chain(
    all: &[Measurement],
    defer: bool,
    skip: &[usize],
) -> (Vec<f64>, Vec<usize>, StoredEstimate) {
    use rootzone::store::CycleRun;
    let dir = tempfile::tempdir().unwrap();
    let (store, engine) = engine(dir.path());
    let engine = engine.defer_estimates(defer);
    let field = store.create_field(&spec(), all[0].time).unwrap();
    let (mut rates, mut deferred) = (Vec::new(), Vec::new());
    for (k, m) in all.iter().enumerate() {
        store
            .add_measurements(field.id, std::slice::from_ref(m))
            .unwrap();
        let run = CycleRun {
            boundary: m.time,
            replica: "r1",
        };
        let done = engine
            .control_cycle(&field, m.time, Some(run))
            .unwrap()
            .expect("the boundary's first run");
        rates.push(done.setpoint.rate);
        if done.estimate_deferred {
            deferred.push(k);
            if !skip.contains(&k) {
                assert!(engine.update_estimate(&field, m.time, "r1").unwrap());
                assert_eq!(stored(&store, field.id).time, m.time);
            }
        }
        if k > 0 && skip.contains(&(k - 1)) {
            // the update of the cycle before, run after this cycle brought
            // the estimate up to date itself: it changes nothing
            let before = store.estimate(field.id).unwrap();
            assert!(
                !engine
                    .update_estimate(&field, all[k - 1].time, "r1")
                    .unwrap()
            );
            assert_eq!(store.estimate(field.id).unwrap(), before);
        }
    }
    (rates, deferred, stored(&store, field.id))
}

#[test]
fn estimates_deferred_past_their_cycles_end_where_the_cycles_own_do() {
    let t0: DateTime<Utc> = "2026-06-01T00:00:00Z".parse().unwrap();
    let all = readings(t0, 30);
    let (rates, none, inline) = scheduled_chain(&all, false, &[]);
    assert!(
        none.is_empty(),
        "an engine that does not defer deferred {none:?}"
    );
    // the window is all measured from the 20th reading on: those defer,
    // except the one after a skipped update (its stored estimate is two
    // periods behind, so it brings it up to date itself)
    let (deferred_rates, deferred, after) = scheduled_chain(&all, true, &[]);
    assert_eq!(deferred, (19..30).collect::<Vec<_>>());
    assert_eq!(rates, deferred_rates, "deferring changed a setpoint");
    assert_eq!(after.time, inline.time);
    assert_eq!(
        after.snapshot.members, inline.snapshot.members,
        "the deferred estimates end elsewhere than the cycles' own"
    );
    let (skipped_rates, deferred, skipped) = scheduled_chain(&all, true, &[23]);
    assert_eq!(
        deferred,
        (19..30).filter(|&k| k != 24).collect::<Vec<_>>(),
        "the cycle after a missing update deferred again"
    );
    assert_eq!(rates, skipped_rates);
    assert_eq!(skipped.snapshot.members, inline.snapshot.members);
}
