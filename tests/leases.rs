//! The lease manager of `rootzone serve` replicas against a real PostgreSQL
//! server: sharing, takeover, joining, busy fields, database loss, and the
//! notification listener.

mod common;

use std::collections::{BTreeSet, HashSet};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use common::postgres::Postgres;
use rootzone::service::replicas::{self, Leases, ReplicaSettings, SCHEMA};
use tokio_util::sync::CancellationToken;

/// A fresh database on `pg` with `n` fields (ids 1 … n) and the lease
/// tables; returns (database name, URL).
fn database(pg: &Postgres, n: i64) -> (String, String) {
    let url = pg.fresh_database();
    let db = url.rsplit('/').next().unwrap().to_string();
    pg.psql(
        &db,
        &format!(
            "CREATE TABLE fields (id BIGSERIAL PRIMARY KEY);\n{SCHEMA}\n\
             INSERT INTO fields (id) SELECT generate_series(1, {n});"
        ),
    );
    (db, url)
}

fn manager(url: &str, id: &str, lease: Duration) -> Leases {
    Leases::new(replicas::pool(url, lease).unwrap(), id.into(), lease)
}

fn assert_send<T: Send>(_: &T) {}

fn ids(n: i64) -> Vec<i64> {
    (1..=n).collect()
}

fn none() -> HashSet<i64> {
    HashSet::new()
}

/// Asserts that no field is believed held by two of `all` at this instant.
fn no_split_brain(all: &[&Leases], fields: &[i64]) {
    for &f in fields {
        let holders: Vec<&str> = all.iter().filter(|l| l.holds(f)).map(|l| l.id()).collect();
        assert!(holders.len() <= 1, "field {f} held by {holders:?}");
    }
}

#[tokio::test]
async fn one_replica_acquires_all_and_renews() {
    let pg = Postgres::shared();
    let (db, url) = database(pg, 50);
    let a = manager(&url, "solo", Duration::from_secs(10));
    assert!(!a.holds(1), "nothing held before the first tick");
    let mut wanted = ids(50);
    wanted.push(9999); // not a row of `fields`: ignored
    let busy = none();
    let first = a.tick(&wanted, &busy);
    assert_send(&first); // the daemon ticks on a spawned task
    let first = first.await.unwrap();
    assert_eq!(first.gained, ids(50));
    assert!(first.lost.is_empty());
    assert_eq!(first.held, ids(50));
    let second = a.tick(&wanted, &none()).await.unwrap();
    assert!(second.gained.is_empty(), "{second:?}");
    assert!(second.lost.is_empty(), "{second:?}");
    assert_eq!(second.held, ids(50));
    assert!((1..=50).all(|f| a.holds(f)));
    assert!(!a.holds(9999));
    assert_eq!(
        pg.psql(
            &db,
            "SELECT count(*) FROM leases WHERE holder = 'solo' AND expires_at > clock_timestamp()"
        ),
        "50"
    );
    let st = a.status();
    assert_eq!(st.replica, "solo");
    assert_eq!(st.held, 50);
    assert_eq!(st.live_replicas, 1);
    assert_eq!(a.tick_interval(), Duration::from_millis(2500));
    let json = serde_json::to_value(&st).unwrap();
    assert_eq!(json["replica"], "solo");
    assert_eq!(json["valid"], true);
    assert!(st.valid);
    assert!(st.last_renewal_age_s.is_some_and(|s| s < 5.0));
    // fields no longer asked for are released
    let fewer = a.tick(&ids(40), &none()).await.unwrap();
    assert_eq!(fewer.lost, (41..=50).collect::<Vec<_>>());
    assert!(!a.holds(41) && a.holds(40));
    assert_eq!(pg.psql(&db, "SELECT count(*) FROM leases"), "40");
    // graceful exit gives everything back at once
    a.release_all().await.unwrap();
    assert!(!a.holds(1));
    assert_eq!(pg.psql(&db, "SELECT count(*) FROM leases"), "0");
    assert_eq!(pg.psql(&db, "SELECT count(*) FROM replicas"), "0");
}

#[tokio::test]
async fn three_replicas_share_fields_exactly_once() {
    let pg = Postgres::shared();
    let (db, url) = database(pg, 300);
    let lease = Duration::from_secs(20);
    let all = [
        manager(&url, "replica-a", lease),
        manager(&url, "replica-b", lease),
        manager(&url, "replica-c", lease),
    ];
    let fields = ids(300);
    for _round in 0..3 {
        for r in &all {
            r.tick(&fields, &none()).await.unwrap();
            no_split_brain(&all.iter().collect::<Vec<_>>(), &fields);
        }
    }
    assert_eq!(
        pg.psql(&db, "SELECT count(*) FROM (SELECT field_id FROM leases GROUP BY field_id HAVING count(*) > 1) d"),
        "0"
    );
    assert_eq!(
        pg.psql(
            &db,
            "SELECT count(DISTINCT field_id) FROM leases WHERE expires_at > clock_timestamp()"
        ),
        "300"
    );
    let mut union = BTreeSet::new();
    for r in &all {
        let held = r.held();
        assert!(
            (70..=130).contains(&held.len()),
            "{} holds {} of 300",
            r.id(),
            held.len()
        );
        let in_db = pg.psql(
            &db,
            &format!("SELECT count(*) FROM leases WHERE holder = '{}'", r.id()),
        );
        assert_eq!(in_db, held.len().to_string(), "{}", r.id());
        assert_eq!(r.status().live_replicas, 3);
        union.extend(held);
    }
    assert_eq!(union.len(), 300);
    // settled: another round changes nothing
    for r in &all {
        let c = r.tick(&fields, &none()).await.unwrap();
        assert!(
            c.gained.is_empty() && c.lost.is_empty(),
            "{}: {c:?}",
            r.id()
        );
    }
}

#[tokio::test]
async fn survivors_take_over_a_dead_replica_after_one_lease() {
    let pg = Postgres::shared();
    let (_db, url) = database(pg, 60);
    let lease = Duration::from_millis(1500);
    let every = Duration::from_millis(100);
    let a = manager(&url, "doomed", lease);
    let b = manager(&url, "survivor-1", lease);
    let c = manager(&url, "survivor-2", lease);
    let fields = ids(60);
    for _ in 0..2 {
        for r in [&a, &b, &c] {
            r.tick(&fields, &none()).await.unwrap();
        }
    }
    let last_start = Instant::now();
    a.tick(&fields, &none()).await.unwrap();
    let last_end = Instant::now();
    let orphaned: BTreeSet<i64> = a.held().into_iter().collect();
    assert!(!orphaned.is_empty());
    // `a` stops ticking (a crash or a stall: it keeps its memory, and
    // must stop believing it holds the fields before anyone takes them)
    let mut taken = BTreeSet::new();
    let deadline = last_end + lease * 3;
    let mut takeover = None;
    while Instant::now() < deadline {
        for r in [&b, &c] {
            let change = r.tick(&fields, &none()).await.unwrap();
            for f in change.gained {
                assert!(orphaned.contains(&f), "{f} was not the dead one's");
                assert!(!a.holds(f), "{f} taken while the dead one still holds it");
                taken.insert(f);
            }
            no_split_brain(&[&a, &b, &c], &fields);
        }
        if taken == orphaned {
            takeover = Some(Instant::now());
            break;
        }
        tokio::time::sleep(every).await;
    }
    let takeover = takeover.unwrap_or_else(|| panic!("took {} of {}", taken.len(), orphaned.len()));
    let after = takeover - last_start;
    println!(
        "takeover of {} fields {:.3} s after the dead one's last renewal (lease {:.1} s)",
        orphaned.len(),
        (takeover - last_end).as_secs_f64(),
        lease.as_secs_f64()
    );
    assert!(
        after >= lease,
        "taken after {after:?}, before the lease expired"
    );
    // within lease + 2 ticks (and the ticks' own time)
    let bound = lease + every * 2 + Duration::from_millis(400);
    assert!(
        takeover - last_end <= bound,
        "taken after {:?}, later than {bound:?}",
        takeover - last_end
    );
    assert!(orphaned.iter().all(|&f| b.holds(f) || c.holds(f)));
    drop(a);
}

#[tokio::test]
async fn joining_replica_gets_its_share_from_the_others() {
    let pg = Postgres::shared();
    let (db, url) = database(pg, 120);
    let lease = Duration::from_secs(20);
    let a = manager(&url, "old-a", lease);
    let b = manager(&url, "old-b", lease);
    let fields = ids(120);
    for _ in 0..2 {
        for r in [&a, &b] {
            r.tick(&fields, &none()).await.unwrap();
        }
    }
    assert_eq!(a.held().len() + b.held().len(), 120);
    let n = manager(&url, "newcomer", lease);
    let all = [&a, &b, &n];
    let first = n.tick(&fields, &none()).await.unwrap();
    assert!(first.gained.is_empty(), "everything is held: {first:?}");
    no_split_brain(&all, &fields);
    let la = a.tick(&fields, &none()).await.unwrap();
    no_split_brain(&all, &fields);
    let lb = b.tick(&fields, &none()).await.unwrap();
    no_split_brain(&all, &fields);
    assert!(la.gained.is_empty() && lb.gained.is_empty());
    assert!(!la.lost.is_empty(), "old-a released nothing");
    assert!(!lb.lost.is_empty(), "old-b released nothing");
    let released: BTreeSet<i64> = la.lost.iter().chain(&lb.lost).copied().collect();
    assert!(released.iter().all(|&f| !a.holds(f) && !b.holds(f)));
    let got = n.tick(&fields, &none()).await.unwrap();
    no_split_brain(&all, &fields);
    assert_eq!(
        got.gained.iter().copied().collect::<BTreeSet<_>>(),
        released
    );
    assert!(
        (20..=60).contains(&got.held.len()),
        "newcomer holds {}",
        got.held.len()
    );
    assert_eq!(a.held().len() + b.held().len() + n.held().len(), 120);
    assert_eq!(
        pg.psql(
            &db,
            "SELECT count(*) FROM leases WHERE expires_at > clock_timestamp()"
        ),
        "120"
    );
}

/// Replicas ticking concurrently on their own tasks while one joins and one
/// stalls; a watcher checks every few milliseconds that no field is believed
/// held by two of them.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn concurrent_ticks_never_split_brain() {
    let pg = Postgres::shared();
    let (db, url) = database(pg, 90);
    let lease = Duration::from_millis(1000);
    let fields = Arc::new(ids(90));
    let names = ["conc-a", "conc-b", "conc-c", "conc-late"];
    let all: Vec<Arc<Leases>> = names
        .iter()
        .map(|n| Arc::new(manager(&url, n, lease)))
        .collect();
    let stop: Vec<CancellationToken> = names.iter().map(|_| CancellationToken::new()).collect();
    let ticker = |i: usize| {
        let (me, stop, fields) = (all[i].clone(), stop[i].clone(), fields.clone());
        tokio::spawn(async move {
            let mut errors = 0;
            while !stop.is_cancelled() {
                if let Err(e) = me.tick(&fields, &HashSet::new()).await {
                    // a deadlock right after the join is legitimate (the
                    // server breaks it), but must stay rare
                    println!("{}: {e}", me.id());
                    errors += 1;
                }
                tokio::time::sleep(Duration::from_millis(40 + 7 * i as u64)).await;
            }
            errors
        })
    };
    let watcher = {
        let all = all.clone();
        let fields = fields.clone();
        let done = CancellationToken::new();
        let d = done.clone();
        let task = tokio::spawn(async move {
            let mut checks = 0u64;
            while !d.is_cancelled() {
                no_split_brain(&all.iter().map(|a| a.as_ref()).collect::<Vec<_>>(), &fields);
                checks += 1;
                tokio::time::sleep(Duration::from_millis(2)).await;
            }
            checks
        });
        (done, task)
    };
    let mut tasks = vec![ticker(0), ticker(1), ticker(2)];
    tokio::time::sleep(Duration::from_millis(800)).await;
    tasks.push(ticker(3)); // joins
    tokio::time::sleep(Duration::from_millis(800)).await;
    stop[0].cancel(); // stalls: never releases
    tokio::time::sleep(lease * 2).await;
    let held: usize = all[1..].iter().map(|a| a.held().len()).sum();
    assert!(!all[0].holds(1) && all[0].held().is_empty());
    watcher.0.cancel();
    let checks = watcher.1.await.unwrap();
    for s in &stop {
        s.cancel();
    }
    for t in tasks {
        assert!(t.await.unwrap() <= 2, "ticks failed");
    }
    println!("{checks} split-brain checks; survivors hold {held} of 90");
    assert_eq!(held, 90, "the survivors hold everything");
    assert!(checks > 100);
    assert_eq!(
        pg.psql(
            &db,
            "SELECT count(*) FROM leases WHERE holder = 'conc-a' AND expires_at > clock_timestamp()"
        ),
        "0"
    );
}

#[tokio::test]
async fn busy_fields_are_kept_and_renewed() {
    let pg = Postgres::shared();
    let (db, url) = database(pg, 40);
    let lease = Duration::from_secs(20);
    let a = manager(&url, "worker-a", lease);
    let b = manager(&url, "worker-b", lease);
    let fields = ids(40);
    a.tick(&fields, &none()).await.unwrap();
    assert_eq!(a.held().len(), 40);
    b.tick(&fields, &none()).await.unwrap(); // joins; gets nothing yet
    let b_share: Vec<i64> = fields
        .iter()
        .copied()
        .filter(|&f| replicas::owner(&["worker-a", "worker-b"], f) == Some("worker-b"))
        .collect();
    assert!(b_share.len() >= 4);
    let busy: HashSet<i64> = b_share[..3].iter().copied().collect();
    let expiry = |f: i64| {
        pg.psql(
            &db,
            &format!("SELECT extract(epoch FROM expires_at) FROM leases WHERE field_id = {f}"),
        )
        .parse::<f64>()
        .unwrap()
    };
    let before: Vec<f64> = busy.iter().map(|&f| expiry(f)).collect();
    tokio::time::sleep(Duration::from_millis(50)).await;
    let c = a.tick(&fields, &busy).await.unwrap();
    assert_eq!(c.lost.len(), b_share.len() - 3, "{c:?}");
    assert!(busy.iter().all(|f| !c.lost.contains(f) && a.holds(*f)));
    let after: Vec<f64> = busy.iter().map(|&f| expiry(f)).collect();
    assert!(
        before.iter().zip(&after).all(|(x, y)| y > x),
        "busy leases renewed: {before:?} → {after:?}"
    );
    let g = b.tick(&fields, &none()).await.unwrap();
    assert_eq!(g.gained.len(), b_share.len() - 3);
    assert!(busy.iter().all(|f| !b.holds(*f)));
    // the cycles end: released, then taken by their owner
    let c = a.tick(&fields, &none()).await.unwrap();
    assert_eq!(c.lost.iter().copied().collect::<HashSet<_>>(), busy);
    let g = b.tick(&fields, &none()).await.unwrap();
    assert_eq!(g.gained.iter().copied().collect::<HashSet<_>>(), busy);
    no_split_brain(&[&a, &b], &fields);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn database_loss_lapses_leases_and_recovery_renews() {
    let pg = Postgres::start();
    let (_db, url) = database(&pg, 10);
    let lease = Duration::from_millis(1500);
    let a = manager(&url, "lonely", lease);
    let fields = ids(10);
    let start = Instant::now();
    a.tick(&fields, &none()).await.unwrap();
    assert!(a.holds(1));
    pg.kill();
    while a.holds(1) {
        assert!(
            start.elapsed() <= lease,
            "still held {:?} after the renewal",
            start.elapsed()
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let lapsed = start.elapsed();
    assert!(lapsed <= lease, "lapsed after {lapsed:?}");
    assert!(!a.status().valid);
    let t = Instant::now();
    let err = a.tick(&fields, &none()).await.unwrap_err();
    let took = t.elapsed();
    println!("leases lapsed {lapsed:?} after the renewal; failing tick took {took:?}: {err}");
    assert!(took < Duration::from_secs(5), "failing tick took {took:?}");
    assert!(!a.holds(1), "a failed tick extends nothing");
    pg.resume();
    let c = a.tick(&fields, &none()).await.unwrap();
    assert_eq!(c.held, fields);
    assert_eq!(c.gained, fields, "after a lapse everything is gained anew");
    assert!(c.lost.is_empty());
    assert!(fields.iter().all(|&f| a.holds(f)));
    assert!(a.status().valid);
}

#[tokio::test]
async fn tick_gives_up_on_a_silent_server_within_the_lease() {
    // accepts connections (the kernel's backlog) and never answers
    let silent = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let url = format!(
        "postgres://rootzone@127.0.0.1:{}/x",
        silent.local_addr().unwrap().port()
    );
    let lease = Duration::from_secs(1);
    let a = manager(&url, "patient", lease);
    let t = Instant::now();
    let err = a.tick(&ids(3), &none()).await.unwrap_err();
    let took = t.elapsed();
    println!("tick against a silent server failed after {took:?}: {err}");
    assert!(took <= lease + Duration::from_millis(500), "{took:?}");
    assert!(!a.holds(1));
    assert!(!a.status().valid);
}

#[tokio::test]
async fn tick_blocked_by_a_lock_gives_up_and_lapses() {
    let pg = Postgres::shared();
    let (_db, url) = database(pg, 10);
    let lease = Duration::from_millis(1500);
    let a = manager(&url, "blocked", lease);
    let fields = ids(10);
    a.tick(&fields, &none()).await.unwrap();
    // another session locks every lease row and keeps its transaction open
    let (blocker, conn) = tokio_postgres::connect(&url, tokio_postgres::NoTls)
        .await
        .unwrap();
    let conn = tokio::spawn(conn);
    blocker
        .batch_execute("BEGIN; SELECT * FROM leases FOR UPDATE")
        .await
        .unwrap();
    let t = Instant::now();
    let err = a.tick(&fields, &none()).await.unwrap_err();
    let took = t.elapsed();
    println!("tick blocked by a lock failed after {took:?}: {err}");
    assert!(took <= lease + Duration::from_millis(500), "{took:?}");
    assert!(!a.holds(1), "a blocked renewal extends nothing");
    blocker.batch_execute("COMMIT").await.unwrap();
    let c = a.tick(&fields, &none()).await.unwrap();
    assert_eq!(c.gained, fields);
    assert!(fields.iter().all(|&f| a.holds(f)));
    drop(blocker);
    let _ = conn.await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn listen_forwards_notifications_and_reconnects() {
    let pg = Postgres::start();
    let url = pg.fresh_database();
    let seen: Arc<Mutex<Vec<(String, String)>>> = Arc::default();
    let cancel = CancellationToken::new();
    let task = {
        let seen = seen.clone();
        let cancel = cancel.clone();
        let config: tokio_postgres::Config = url.parse().unwrap();
        tokio::spawn(async move {
            replicas::listen(
                config,
                &["zone_a", "Zone B"],
                move |c, p| seen.lock().unwrap().push((c.to_string(), p.to_string())),
                cancel,
            )
            .await
        })
    };
    // NOTIFY (from another connection) until it arrives
    let notify_until_seen = async |channel: &str, payload: &str| {
        let deadline = Instant::now() + Duration::from_secs(10);
        let want = (channel.to_string(), payload.to_string());
        loop {
            if let Ok((client, conn)) = tokio_postgres::connect(&url, tokio_postgres::NoTls).await {
                let conn = tokio::spawn(conn);
                let _ = client
                    .execute("SELECT pg_notify($1, $2)", &[&channel, &payload])
                    .await;
                drop(client);
                let _ = conn.await;
            }
            for _ in 0..10 {
                if seen.lock().unwrap().contains(&want) {
                    return;
                }
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
            assert!(
                Instant::now() < deadline,
                "{want:?} never arrived: {:?}",
                seen.lock().unwrap()
            );
        }
    };
    notify_until_seen("zone_a", "field 7 changed").await;
    notify_until_seen("Zone B", "x").await;
    assert!(
        !seen.lock().unwrap().iter().any(|(_, p)| p.is_empty()),
        "no re-check before any reconnect"
    );
    let mark = seen.lock().unwrap().len();
    pg.kill();
    tokio::time::sleep(Duration::from_millis(500)).await;
    pg.resume();
    notify_until_seen("zone_a", "after the crash").await;
    let events = seen.lock().unwrap()[mark..].to_vec();
    for ch in ["zone_a", "Zone B"] {
        let rechecks = events
            .iter()
            .filter(|(c, p)| c == ch && p.is_empty())
            .count();
        assert_eq!(rechecks, 1, "one re-check of {ch}: {events:?}");
    }
    let recheck = events
        .iter()
        .position(|(c, p)| c == "zone_a" && p.is_empty());
    let again = events
        .iter()
        .position(|(c, p)| c == "zone_a" && p == "after the crash");
    assert!(
        recheck < again,
        "re-check before the new notification: {events:?}"
    );
    cancel.cancel();
    tokio::time::timeout(Duration::from_secs(2), task)
        .await
        .expect("listen ends when cancelled")
        .unwrap();
}

#[test]
fn settings_are_validated() {
    let ok = ReplicaSettings::default();
    assert_eq!(ok.lease_s, 60.0);
    assert_eq!(ok.id, None);
    ok.validate().unwrap();
    let with = |id: Option<&str>, lease_s: f64| ReplicaSettings {
        id: id.map(String::from),
        lease_s,
    };
    for bad in [0.0, 0.5, 5000.0, f64::NAN] {
        let e = with(None, bad).validate().unwrap_err();
        assert!(e.contains("replicas.lease_s"), "{e}");
    }
    with(None, 1.0).validate().unwrap();
    with(None, 3600.0).validate().unwrap();
    let long = "x".repeat(65);
    for bad in ["", "has space", "slash/y", "ümlaut", long.as_str()] {
        let e = with(Some(bad), 60.0).validate().unwrap_err();
        assert!(e.contains("replicas.id"), "{e}");
    }
    with(Some(&"x".repeat(64)), 60.0).validate().unwrap();
    with(Some("node-1.zone_a"), 60.0).validate().unwrap();
    let generated = ok.replica_id();
    assert!(replicas::valid_id(&generated), "{generated}");
    assert!(
        generated.contains(&format!("-{}-", std::process::id())),
        "{generated}"
    );
    assert_ne!(generated, ok.replica_id(), "random part");
    assert_eq!(with(Some("fixed"), 60.0).replica_id(), "fixed");
    // clock seconds to wall seconds, floored
    assert_eq!(ok.wall_lease(1.0), Duration::from_secs(60));
    assert_eq!(ok.wall_lease(10.0), Duration::from_secs(6));
    assert_eq!(ok.wall_lease(1000.0), Duration::from_millis(200));
    // the file's keys
    let parsed: ReplicaSettings = serde_json::from_str(r#"{"lease_s": "30"}"#).unwrap();
    assert_eq!(parsed.lease_s, 30.0);
    assert!(serde_json::from_str::<ReplicaSettings>(r#"{"lease": 30}"#).is_err());
}

#[test]
fn rendezvous_weights_are_stable_and_balanced() {
    // pinned: every build of every replica must compute the same weights
    let pinned = [
        replicas::weight("replica-a", 1),
        replicas::weight("replica-b", 42),
    ];
    println!("pinned weights {pinned:?}");
    assert_eq!(pinned, PINNED);
    let live = ["r1", "r2", "r3", "r4"];
    let mut counts = [0usize; 4];
    for f in 1..=4000 {
        let o = replicas::owner(&live, f).unwrap();
        counts[live.iter().position(|r| *r == o).unwrap()] += 1;
    }
    assert!(
        counts.iter().all(|&c| (850..=1150).contains(&c)),
        "{counts:?}"
    );
    // removing a replica moves only its fields
    let fewer = ["r1", "r2", "r4"];
    for f in 1..=4000 {
        let before = replicas::owner(&live, f).unwrap();
        let after = replicas::owner(&fewer, f).unwrap();
        if before != "r3" {
            assert_eq!(before, after, "field {f} moved");
        }
    }
    assert_eq!(replicas::owner::<&str>(&[], 1), None);
}

/// FNV-1a + splitmix64 as in the module, computed independently (Python).
const PINNED: [u64; 2] = [17_007_379_720_223_337_797, 8_648_740_832_797_773_767];
