//! The fleet figure of issue 19: `FIELDS` two-layer fields (default
//! 10,000) across `REPLICAS` `rootzone serve` processes (default 2) that
//! share one PostgreSQL at `URL`, on a clock accelerated `SPEEDUP` times
//! (default 20; control period 2 h, so a boundary every 360 wall-s).
//!
//! Each field first gets a window of history (20 readings, one per
//! period). At each boundary the driver posts one reading per field stamped at it,
//! as a field's own sensor would (sent from a little before it, within
//! the allowed future skew, so that no cycle waits for its reading); the
//! replicas then run their leased fields' cycles of that boundary. The
//! first boundary starts each field's state estimate over its window (a
//! catch-up of 20 readings); the later ones are the steady state the
//! figure is about. For every boundary the example
//! reads `cycle_runs` (each row's `done_at` is the database's wall clock at
//! commit) and reports how many fields ran it, on which replica, and how
//! long after the boundary (in wall seconds) the fields' cycles were
//! committed: median, 99th percentile, last. It also reports when the
//! replicas had stored every state estimate the cycles deferred (their
//! `rootzone_deferred_estimates_pending` back at 0).
//!
//! `cargo build --release --bins --examples` first (the example starts
//! `target/release/rootzone`), then
//! `target/release/examples/fleet URL [FIELDS REPLICAS SPEEDUP BOUNDARIES]`.
//! The database must be empty (a fresh one): its fields are the fleet.

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::time::Duration;

use chrono::{DateTime, TimeDelta, Utc};
use tokio::sync::Semaphore;

const TOKEN: &str = "fleet-benchmark-token";
const PERIOD_S: f64 = 7200.0;

struct Replica {
    child: Child,
    base: String,
}

impl Drop for Replica {
    fn drop(&mut self) {
        // SIGTERM, so that the replica releases its leases
        let _ = Command::new("kill")
            .arg(self.child.id().to_string())
            .status();
        let _ = self.child.wait();
    }
}

fn start_replica(dir: &std::path::Path, url: &str, id: &str, speedup: f64, epoch: &str) -> Replica {
    let exe = std::env::current_exe().expect("own path");
    let bin = exe
        .parent()
        .and_then(|p| p.parent())
        .expect("target/<profile>/examples")
        .join("rootzone");
    std::fs::create_dir_all(dir).expect("replica folder");
    let config = dir.join("rootzone.toml");
    std::fs::write(&config, "fields = []\n[limits]\nmax_batch = 1000\n").expect("config");
    // a lease of 60 wall-s, as at real time
    let lease = (60.0 * speedup).min(3600.0);
    let mut child = Command::new(&bin)
        .args(["serve", "--config"])
        .arg(&config)
        .env("ROOTZONE_LISTEN", "127.0.0.1:0")
        .env("ROOTZONE_DATA_DIR", dir.join("data"))
        .env("ROOTZONE_API_TOKEN", TOKEN)
        .env("ROOTZONE_STORAGE__URL", url)
        .env("ROOTZONE_REPLICAS__ID", id)
        .env("ROOTZONE_REPLICAS__LEASE_S", lease.to_string())
        .env("ROOTZONE_CLOCK__SPEEDUP", speedup.to_string())
        .env("ROOTZONE_CLOCK__EPOCH", epoch)
        .env("RUST_LOG", "error")
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .unwrap_or_else(|e| panic!("cannot start {}: {e}", bin.display()));
    let mut reader = BufReader::new(child.stdout.take().expect("stdout"));
    let mut line = String::new();
    reader.read_line(&mut line).expect("first line");
    std::thread::spawn(move || std::io::copy(&mut reader, &mut std::io::sink()));
    let base = line
        .split_whitespace()
        .find(|w| w.starts_with("http://"))
        .unwrap_or_else(|| panic!("no address in '{line}'"))
        .to_string();
    Replica { child, base }
}

/// The accelerated clock of every replica: epoch + (wall − epoch) × speedup.
#[derive(Clone, Copy)]
struct Clock {
    epoch: DateTime<Utc>,
    speedup: f64,
}

impl Clock {
    fn now(&self) -> DateTime<Utc> {
        self.at(Utc::now())
    }
    fn at(&self, wall: DateTime<Utc>) -> DateTime<Utc> {
        let real = (wall - self.epoch).num_microseconds().unwrap_or(0) as f64 * 1e-6;
        self.epoch + TimeDelta::microseconds((real * self.speedup * 1e6) as i64)
    }
    fn wall(&self, clock: DateTime<Utc>) -> DateTime<Utc> {
        let c = (clock - self.epoch).num_microseconds().unwrap_or(0) as f64 * 1e-6;
        self.epoch + TimeDelta::microseconds((c / self.speedup * 1e6) as i64)
    }
}

fn next_boundary(t: DateTime<Utc>) -> DateTime<Utc> {
    let p = (PERIOD_S * 1000.0) as i64;
    DateTime::from_timestamp_millis((t.timestamp_millis().div_euclid(p) + 1) * p).expect("time")
}

/// User + system CPU time [s] of the processes `pids` (Linux /proc).
fn cpu_seconds(pids: &[u32]) -> f64 {
    let tick = 100.0; // USER_HZ on Linux
    pids.iter()
        .filter_map(|p| std::fs::read_to_string(format!("/proc/{p}/stat")).ok())
        .filter_map(|s| {
            // the fields after the command name (which may hold spaces)
            let rest = s.rsplit_once(')')?.1.split_whitespace().collect::<Vec<_>>();
            let ut: f64 = rest.get(11)?.parse().ok()?;
            let st: f64 = rest.get(12)?.parse().ok()?;
            Some((ut + st) / tick)
        })
        .sum()
}

/// How many fields have run boundary `b`'s cycle.
async fn cycles_run(db: &tokio_postgres::Client, b: DateTime<Utc>) -> usize {
    let n: i64 = db
        .query_one(
            "SELECT count(*) FROM cycle_runs WHERE boundary = $1",
            &[&b.timestamp_millis()],
        )
        .await
        .expect("count")
        .get(0);
    n as usize
}

/// The replicas' deferred-estimate queues, summed (their `/metrics`); None
/// when one does not answer.
async fn estimates_pending(http: &reqwest::Client, bases: &[String]) -> Option<i64> {
    let mut sum = 0;
    for base in bases {
        let text = http
            .get(format!("{base}/metrics"))
            .send()
            .await
            .ok()?
            .text()
            .await
            .ok()?;
        sum += text
            .lines()
            .find_map(|l| l.strip_prefix("rootzone_deferred_estimates_pending "))?
            .trim()
            .parse::<f64>()
            .ok()? as i64;
    }
    Some(sum)
}

fn percentile(sorted: &[f64], q: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * q).round() as usize]
}

async fn sleep_until_wall(t: DateTime<Utc>) {
    let left = (t - Utc::now()).num_milliseconds();
    if left > 0 {
        tokio::time::sleep(Duration::from_millis(left as u64)).await;
    }
}

/// POSTs each (replica, field, body) as a measurement batch, at most 32 at
/// a time; returns how many were stored (201).
async fn post_readings(
    http: &reqwest::Client,
    gate: &Arc<Semaphore>,
    posts: Vec<(String, i64, String)>,
) -> usize {
    let mut tasks = Vec::new();
    for (base, id, body) in posts {
        let (http, gate) = (http.clone(), gate.clone());
        tasks.push(tokio::spawn(async move {
            let _permit = gate.acquire_owned().await.expect("gate");
            http.post(format!("{base}/v1/fields/{id}/measurements"))
                .bearer_auth(TOKEN)
                .body(body)
                .send()
                .await
                .is_ok_and(|r| r.status() == 201)
        }));
    }
    let mut ok = 0;
    for t in tasks {
        ok += usize::from(t.await.unwrap_or(false));
    }
    ok
}

#[tokio::main]
async fn main() {
    let args: Vec<String> = std::env::args().collect();
    let Some(url) = args.get(1).cloned() else {
        eprintln!("usage: fleet URL [FIELDS REPLICAS SPEEDUP BOUNDARIES]");
        std::process::exit(2);
    };
    let fields: usize = args.get(2).and_then(|a| a.parse().ok()).unwrap_or(10_000);
    let replicas: usize = args.get(3).and_then(|a| a.parse().ok()).unwrap_or(2);
    let speedup: f64 = args.get(4).and_then(|a| a.parse().ok()).unwrap_or(20.0);
    let boundaries: usize = args.get(5).and_then(|a| a.parse().ok()).unwrap_or(3);
    let dir = tempfile::tempdir().expect("temp dir");
    let clock = Clock {
        epoch: Utc::now(),
        speedup,
    };
    let epoch = clock.epoch.to_rfc3339();
    let daemons: Vec<Replica> = (0..replicas)
        .map(|k| {
            let id = format!("r{}", k + 1);
            start_replica(&dir.path().join(&id), &url, &id, speedup, &epoch)
        })
        .collect();
    let bases: Vec<String> = daemons.iter().map(|d| d.base.clone()).collect();
    let pids: Vec<u32> = daemons.iter().map(|d| d.child.id()).collect();
    println!("replica processes: {pids:?}");
    rootzone::service::install_tls();
    let http = reqwest::Client::new();
    let gate = Arc::new(Semaphore::new(32));

    // the fleet, created through every replica in turn
    let mut tasks = Vec::new();
    for k in 0..fields {
        let (http, gate) = (http.clone(), gate.clone());
        let base = bases[k % bases.len()].clone();
        tasks.push(tokio::spawn(async move {
            let _permit = gate.acquire_owned().await.expect("gate");
            let body = serde_json::json!({
                "name": format!("fleet-{k}"), "model": "two-layer",
                "control_period_s": PERIOD_S,
            });
            let r = http
                .post(format!("{base}/v1/fields"))
                .bearer_auth(TOKEN)
                .json(&body)
                .send()
                .await
                .expect("create");
            assert_eq!(r.status(), 201, "{}", r.text().await.unwrap_or_default());
            let doc: serde_json::Value = r.json().await.expect("field");
            doc["id"].as_i64().expect("id")
        }));
    }
    let mut ids = Vec::new();
    for t in tasks {
        ids.push(t.await.expect("create task"));
    }
    println!("{fields} two-layer fields created on {replicas} replicas");

    // each field's window of history: a reading at each of the 20
    // boundaries before the first one measured, in one batch per field
    let first = next_boundary(clock.now());
    let posts = ids
        .iter()
        .enumerate()
        .map(|(k, &id)| {
            let readings: Vec<String> = (1..=20)
                .rev()
                .map(|j| {
                    let t = first - TimeDelta::seconds(PERIOD_S as i64 * j);
                    let theta = 0.17 + 0.0005 * ((k + j as usize) % 40) as f64;
                    format!("{{\"time\": \"{}\", \"theta\": {theta}}}", t.to_rfc3339())
                })
                .collect();
            (
                bases[k % bases.len()].clone(),
                id,
                format!("[{}]", readings.join(",")),
            )
        })
        .collect();
    let ok = post_readings(&http, &gate, posts).await;
    println!("{ok} fields got a window of 20 readings");

    let (db, connection) = tokio_postgres::connect(&url, tokio_postgres::NoTls)
        .await
        .expect("database");
    tokio::spawn(connection);

    let mut measured = Vec::new();
    for round in 0..boundaries {
        // the next boundary at least 5 wall-s away, so the readings are in
        let mut b = next_boundary(
            measured
                .last()
                .copied()
                .unwrap_or(clock.now())
                .max(clock.now()),
        );
        while clock.wall(b) - Utc::now() < TimeDelta::seconds(5) {
            b = next_boundary(b);
        }
        // stamped at the boundary, as a sensor that measures on it; sent
        // from 280 clock-s before it (within the 300-s future skew), so the
        // cycles find them unless posting takes longer than that
        let stamp = b;
        sleep_until_wall(clock.wall(b - TimeDelta::seconds(280))).await;
        let posted = std::time::Instant::now();
        let posts = ids
            .iter()
            .enumerate()
            .map(|(k, &id)| {
                let theta = 0.17 + 0.0005 * ((k + round) % 40) as f64;
                let body = format!(
                    "[{{\"time\": \"{}\", \"theta\": {theta}}}]",
                    stamp.to_rfc3339()
                );
                (bases[k % bases.len()].clone(), id, body)
            })
            .collect();
        let ok = post_readings(&http, &gate, posts).await;
        let late = clock.now() > b;
        println!(
            "boundary {} ({}): {ok} readings posted in {:.1} wall-s{}",
            round + 1,
            b.to_rfc3339(),
            posted.elapsed().as_secs_f64(),
            if late {
                " — after the boundary: the cycles may wait for them"
            } else {
                ""
            }
        );
        measured.push(b);
        // the replicas' CPU time over the boundary's first 60 wall-s
        let before = cpu_seconds(&pids);
        sleep_until_wall(clock.wall(b) + TimeDelta::seconds(60)).await;
        println!(
            "boundary {}: the replicas used {:.1} CPU-s in the 60 wall-s after it",
            round + 1,
            cpu_seconds(&pids) - before
        );
        // the state estimates the cycles deferred: when the replicas' queues
        // ran empty after the boundary's last cycle (polled each wall second,
        // until 20 wall-s before the next boundary's readings are sent)
        let stop = clock.wall(next_boundary(b) - TimeDelta::seconds(280)) - TimeDelta::seconds(20);
        loop {
            let n = cycles_run(&db, b).await;
            let pending = estimates_pending(&http, &bases).await;
            let after = (Utc::now() - clock.wall(b)).num_milliseconds() as f64 / 1e3;
            if n >= fields && pending == Some(0) {
                println!(
                    "boundary {}: every deferred state estimate stored by {after:.1} wall-s after it",
                    round + 1
                );
                break;
            }
            if Utc::now() > stop {
                println!(
                    "boundary {}: {n} cycles, {pending:?} estimates still queued {after:.1} wall-s after it",
                    round + 1
                );
                break;
            }
            tokio::time::sleep(Duration::from_secs(1)).await;
        }
    }
    // wait for the last boundary's cycles: all done, or a period gone by
    let last = *measured.last().expect("a boundary");
    let give_up = clock.wall(last) + TimeDelta::milliseconds((PERIOD_S / speedup * 1e3) as i64);
    loop {
        let n = cycles_run(&db, last).await;
        if n >= fields || Utc::now() > give_up {
            break;
        }
        tokio::time::sleep(Duration::from_millis(500)).await;
    }
    for (k, b) in measured.iter().enumerate() {
        let rows = db
            .query(
                "SELECT replica, done_at FROM cycle_runs WHERE boundary = $1",
                &[&b.timestamp_millis()],
            )
            .await
            .expect("runs");
        let due = clock.wall(*b);
        let mut late: Vec<f64> = rows
            .iter()
            .map(|r| {
                let at: std::time::SystemTime = r.get(1);
                let at: DateTime<Utc> = at.into();
                (at - due).num_microseconds().unwrap_or(0) as f64 * 1e-6
            })
            .collect();
        late.sort_by(f64::total_cmp);
        let mut per: std::collections::BTreeMap<String, usize> = Default::default();
        for r in &rows {
            *per.entry(r.get::<_, String>(0)).or_default() += 1;
        }
        if late.is_empty() {
            println!("boundary {}: no cycle ran", k + 1);
            continue;
        }
        println!(
            "boundary {}{}: {} of {fields} fields ran ({per:?}); done after the boundary \
             (wall s): median {:.1}, p99 {:.1}, last {:.1}",
            k + 1,
            if k == 0 { " (first cycles)" } else { "" },
            late.len(),
            percentile(&late, 0.5),
            percentile(&late, 0.99),
            late.last().copied().unwrap_or(f64::NAN),
        );
    }
    drop(daemons);
}
