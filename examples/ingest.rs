//! The ingest figure of issue 19: `CLIENTS` HTTP clients (default 16) each
//! POST batches of `BATCH` measurements (default 100) to a field of their
//! own for `SECONDS` (default 10) against the daemon on `STORAGE` (default
//! an embedded SQLite file; `postgres://…` for a server). Reported: the
//! acknowledged (201) measurements per second, and the count read back
//! from the store afterwards, which must equal them (durable: every answer
//! is sent after its transaction committed).
//!
//! `cargo run --release --example ingest [-- STORAGE CLIENTS BATCH SECONDS]`.
//! The daemon runs in-process (the same `App` as `rootzone serve`).

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use chrono::{TimeDelta, Utc};
use rootzone::service::wire::{Actuator, FieldSpec};
use rootzone::service::{App, Settings};

const TOKEN: &str = "ingest-benchmark-token";

#[tokio::main]
async fn main() {
    let args: Vec<String> = std::env::args().collect();
    let storage = args.get(1).cloned().filter(|s| s != "sqlite");
    let clients: usize = args.get(2).and_then(|a| a.parse().ok()).unwrap_or(16);
    let batch: usize = args.get(3).and_then(|a| a.parse().ok()).unwrap_or(100);
    let seconds: f64 = args.get(4).and_then(|a| a.parse().ok()).unwrap_or(10.0);
    let dir = tempfile::tempdir().expect("temp dir");
    let mut settings = Settings {
        listen: "127.0.0.1:0".into(),
        data_dir: dir.path().join("data"),
        api_token: Some(TOKEN.into()),
        fields: Vec::new(),
        ..Settings::default()
    };
    settings.storage.url = storage.clone();
    settings.limits.worker_threads = 2;
    let app = App::build(settings).await.expect("the daemon starts");
    let base = format!("http://{}", app.local_addr().expect("address"));
    let state = app.state.clone();
    tokio::spawn(async move { app.run(std::future::pending()).await });
    let http = reqwest::Client::new();
    let run = Utc::now().timestamp_millis();
    let mut ids = Vec::new();
    for c in 0..clients {
        let spec = FieldSpec {
            name: format!("ingest-{run}-{c}"),
            actuator: Actuator::None,
            simulation: None,
            control_period_s: 86_400.0,
            ..FieldSpec::demo()
        };
        let r = http
            .post(format!("{base}/v1/fields"))
            .bearer_auth(TOKEN)
            .json(&spec)
            .send()
            .await
            .expect("create");
        assert_eq!(r.status(), 201, "{}", r.text().await.unwrap_or_default());
        let doc: serde_json::Value = r.json().await.expect("field");
        ids.push(doc["id"].as_i64().expect("id"));
    }
    let acked = Arc::new(AtomicU64::new(0));
    let failed = Arc::new(AtomicU64::new(0));
    let started = Instant::now();
    let until = started + Duration::from_secs_f64(seconds);
    let t0 = Utc::now() - TimeDelta::days(20);
    let mut tasks = Vec::new();
    for &id in &ids {
        let (http, base, acked, failed) =
            (http.clone(), base.clone(), acked.clone(), failed.clone());
        tasks.push(tokio::spawn(async move {
            let mut k: i64 = 0;
            while Instant::now() < until {
                let body: Vec<serde_json::Value> = (0..batch)
                    .map(|_| {
                        k += 1;
                        serde_json::json!({
                            "time": (t0 + TimeDelta::milliseconds(k * 1000)).to_rfc3339(),
                            "theta": 0.2 + (k % 100) as f64 * 1e-4,
                        })
                    })
                    .collect();
                let r = http
                    .post(format!("{base}/v1/fields/{id}/measurements"))
                    .bearer_auth(TOKEN)
                    .json(&body)
                    .send()
                    .await;
                match r {
                    Ok(r) if r.status() == 201 => {
                        acked.fetch_add(batch as u64, Ordering::Relaxed);
                    }
                    _ => {
                        failed.fetch_add(1, Ordering::Relaxed);
                    }
                }
            }
        }));
    }
    for t in tasks {
        t.await.expect("client");
    }
    let elapsed = started.elapsed().as_secs_f64();
    let acked = acked.load(Ordering::Relaxed);
    let engine = state.engine.clone();
    let stored: u64 = tokio::task::spawn_blocking(move || {
        ids.iter()
            .map(|&id| engine.store.count_measurements(id).expect("count"))
            .sum()
    })
    .await
    .expect("count");
    println!(
        "storage {}: {clients} clients × batches of {batch}, {elapsed:.1} s: {acked} acknowledged \
         ({:.0}/s), {stored} stored, {} failed requests",
        storage.as_deref().unwrap_or("sqlite (embedded)"),
        acked as f64 / elapsed,
        failed.load(Ordering::Relaxed)
    );
    assert_eq!(stored, acked, "every acknowledged measurement is stored");
}
