//! Load test of the daemon over loopback (the figures of the daemon issue):
//!
//! 1. ingest: `clients` concurrent clients post single measurements as fast
//!    as they can for `seconds`; throughput of durably stored measurements;
//! 2. latency: single measurements at a steady 200 requests/s; p50/p99;
//! 3. control: one control cycle for each of 200 two-layer fields, all at once.
//!
//! `cargo run --release --example load [-- CLIENTS SECONDS]`. The daemon runs
//! in-process (the same `App` as `rootzone serve`) on a temporary data
//! directory and an ephemeral port.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use rootzone::service::{App, Settings};

const TOKEN: &str = "load-test-token-0123";

fn measurement(k: u64) -> String {
    let t = chrono::Utc::now() - chrono::TimeDelta::milliseconds((k % 100_000) as i64);
    format!("{{\"time\": \"{}\", \"theta\": 0.2}}", t.to_rfc3339())
}

fn percentile(sorted: &[f64], q: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * q).round() as usize]
}

#[tokio::main]
async fn main() {
    let args: Vec<String> = std::env::args().collect();
    let clients: usize = args.get(1).and_then(|a| a.parse().ok()).unwrap_or(16);
    let seconds: u64 = args.get(2).and_then(|a| a.parse().ok()).unwrap_or(10);
    let dir = tempfile::tempdir().expect("temp dir");
    let settings = Settings {
        listen: "127.0.0.1:0".into(),
        data_dir: dir.path().to_path_buf(),
        api_token: Some(TOKEN.into()),
        fields: Vec::new(),
        ..Settings::default()
    };
    let app = App::build(settings).await.expect("the daemon builds");
    let base = format!("http://{}", app.local_addr().expect("bound"));
    let stop = tokio_util::sync::CancellationToken::new();
    let s = stop.clone();
    let server = tokio::spawn(app.run(async move { s.cancelled().await }));
    let http = reqwest::Client::new();
    let field: serde_json::Value = http
        .post(format!("{base}/v1/fields"))
        .bearer_auth(TOKEN)
        .body(r#"{"name": "load", "model": "two-layer"}"#)
        .send()
        .await
        .expect("create")
        .json()
        .await
        .expect("field JSON");
    let url = format!("{base}/v1/fields/{}/measurements", field["id"]);

    // 1. throughput
    let stored = Arc::new(AtomicU64::new(0));
    let deadline = Instant::now() + Duration::from_secs(seconds);
    let start = Instant::now();
    let mut tasks = Vec::new();
    for c in 0..clients {
        let (http, url, stored) = (http.clone(), url.clone(), stored.clone());
        tasks.push(tokio::spawn(async move {
            let mut k = c as u64 * 1_000_000;
            while Instant::now() < deadline {
                let r = http
                    .post(&url)
                    .bearer_auth(TOKEN)
                    .body(measurement(k))
                    .send()
                    .await;
                if r.is_ok_and(|r| r.status().as_u16() == 201) {
                    stored.fetch_add(1, Ordering::Relaxed);
                }
                k += 1;
            }
        }));
    }
    for t in tasks {
        let _ = t.await;
    }
    let n = stored.load(Ordering::Relaxed);
    let rate = n as f64 / start.elapsed().as_secs_f64();
    println!(
        "ingest: {clients} clients, {n} measurements stored (201) in {:.1} s: {rate:.0} per second",
        start.elapsed().as_secs_f64()
    );

    // 2. latency at 200 requests/s
    let mut interval = tokio::time::interval(Duration::from_millis(5));
    let mut latencies = Vec::new();
    let mut handles = Vec::new();
    for k in 0..(200 * seconds) {
        interval.tick().await;
        let (http, url) = (http.clone(), url.clone());
        handles.push(tokio::spawn(async move {
            let t = Instant::now();
            let r = http
                .post(&url)
                .bearer_auth(TOKEN)
                .body(measurement(k))
                .send()
                .await;
            let ok = r.is_ok_and(|r| r.status().as_u16() == 201);
            (ok, t.elapsed().as_secs_f64() * 1e3)
        }));
    }
    let mut failed = 0;
    for h in handles {
        if let Ok((ok, ms)) = h.await {
            if !ok {
                failed += 1;
            }
            latencies.push(ms);
        }
    }
    latencies.sort_by(f64::total_cmp);
    println!(
        "latency at 200 requests/s: {} requests, {failed} failed, p50 {:.2} ms, p99 {:.2} ms, max {:.2} ms",
        latencies.len(),
        percentile(&latencies, 0.5),
        percentile(&latencies, 0.99),
        latencies.last().copied().unwrap_or(0.0)
    );

    // 3. one control cycle for 200 fields with 20 measurements each
    let mut ids = Vec::new();
    for f in 0..200 {
        let field: serde_json::Value = http
            .post(format!("{base}/v1/fields"))
            .bearer_auth(TOKEN)
            .body(format!("{{\"name\": \"f{f}\", \"model\": \"two-layer\"}}"))
            .send()
            .await
            .expect("create")
            .json()
            .await
            .expect("field JSON");
        let id = field["id"].as_i64().expect("id");
        let batch: Vec<String> = (0..20)
            .map(|k| {
                let t = chrono::Utc::now() - chrono::TimeDelta::hours(2 * (20 - k));
                format!(
                    "{{\"time\": \"{}\", \"theta\": {}}}",
                    t.to_rfc3339(),
                    0.17 + 0.0005 * ((f + k) % 40) as f64
                )
            })
            .collect();
        http.post(format!("{base}/v1/fields/{id}/measurements"))
            .bearer_auth(TOKEN)
            .body(format!("[{}]", batch.join(",")))
            .send()
            .await
            .expect("batch");
        ids.push(id);
    }
    let start = Instant::now();
    let cpu_start = process_cpu_seconds();
    let mut handles = Vec::new();
    for id in ids {
        let http = http.clone();
        let url = format!("{base}/v1/fields/{id}/control");
        handles.push(tokio::spawn(async move {
            let r = http.post(url).bearer_auth(TOKEN).send().await;
            r.is_ok_and(|r| r.status().is_success())
        }));
    }
    let mut ok = 0;
    for h in handles {
        if h.await.unwrap_or(false) {
            ok += 1;
        }
    }
    let cpu = process_cpu_seconds() - cpu_start;
    println!(
        "control: {ok} of 200 two-layer fields got a setpoint in {:.2} s \
         ({cpu:.2} CPU-seconds in this process: {:.2} s on 2 idle cores)",
        start.elapsed().as_secs_f64(),
        cpu / 2.0
    );
    stop.cancel();
    let _ = server.await;
}

/// User + system CPU time of this process [s] (Linux `/proc/self/stat`,
/// clock ticks of 1/100 s), so a run on a shared machine still tells what
/// the work costs.
fn process_cpu_seconds() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    // the fields after the command name, which is in parentheses
    let rest = stat.rsplit_once(')').map_or("", |(_, r)| r);
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let ticks = |i: usize| {
        fields
            .get(i)
            .and_then(|v| v.parse::<f64>().ok())
            .unwrap_or(0.0)
    };
    // utime and stime are fields 14 and 15 of stat(5), 12 and 13 after the name
    (ticks(11) + ticks(12)) / 100.0
}
