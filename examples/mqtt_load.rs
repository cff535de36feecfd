//! The MQTT figure of issue 18: `FIELDS` fields (default 1,000) each
//! publish one reading per `WINDOW_S` (default 900 s, one per 15 minutes)
//! through a local Mosquitto broker, for `ROUNDS` rounds (default 1); the
//! readings of a round are spread evenly over its window. Reported: how
//! many were stored (none may be lost) and the latency from the publish to
//! the commit (the field's measurement notification, which the ingest
//! sends after the transaction), p50 / p99 / max.
//!
//! `cargo run --release --example mqtt_load [-- FIELDS WINDOW_S ROUNDS]`.
//! The daemon runs in-process (the same `App` as `rootzone serve`) on a
//! temporary data directory; mosquitto (Debian's package) is started on a
//! free port. The fields' first control cycles run before the measurement
//! starts (their period is a day, so no other cycle falls in it).

use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use rootzone::service::wire::{Actuator, FieldSpec};
use rootzone::service::{App, Settings};
use rumqttc::{AsyncClient, MqttOptions, QoS};

fn percentile(sorted: &[f64], q: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * q).round() as usize]
}

fn mosquitto() -> &'static str {
    if std::path::Path::new("/usr/sbin/mosquitto").is_file() {
        "/usr/sbin/mosquitto"
    } else {
        "mosquitto"
    }
}

#[tokio::main]
async fn main() {
    let args: Vec<String> = std::env::args().collect();
    let fields: usize = args.get(1).and_then(|a| a.parse().ok()).unwrap_or(1000);
    let window_s: f64 = args.get(2).and_then(|a| a.parse().ok()).unwrap_or(900.0);
    let rounds: usize = args.get(3).and_then(|a| a.parse().ok()).unwrap_or(1);
    let dir = tempfile::tempdir().expect("temp dir");

    // the broker
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("a free port")
        .port();
    let conf = dir.path().join("mosquitto.conf");
    std::fs::write(
        &conf,
        format!(
            "listener {port} 127.0.0.1\nallow_anonymous true\nmax_queued_messages 100000\n\
             max_inflight_messages 100\nlog_dest none\nuser root\n"
        ),
    )
    .expect("broker config");
    let mut broker = Command::new(mosquitto())
        .arg("-c")
        .arg(&conf)
        .stdout(Stdio::null())
        .spawn()
        .expect("mosquitto starts (apt-get install mosquitto)");
    while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
        std::thread::sleep(Duration::from_millis(50));
    }

    // the daemon with its fields
    let specs: Vec<FieldSpec> = (0..fields)
        .map(|i| FieldSpec {
            name: format!("f{i}"),
            actuator: Actuator::None,
            simulation: None,
            control_period_s: 86_400.0,
            ..FieldSpec::demo()
        })
        .collect();
    let mut settings = Settings {
        listen: "127.0.0.1:0".into(),
        data_dir: dir.path().join("data"),
        api_token: Some("mqtt-load-token-0123".into()),
        fields: specs,
        ..Settings::default()
    };
    settings.mqtt.url = Some(format!("mqtt://127.0.0.1:{port}"));
    settings.mqtt.client_id = "rootzone-load".into();
    let app = App::build(settings).await.expect("the daemon builds");
    let state = app.state.clone();
    let stop = tokio_util::sync::CancellationToken::new();
    let s = stop.clone();
    let server = tokio::spawn(app.run(async move { s.cancelled().await }));
    let ids: Vec<i64> = state
        .engine
        .store
        .fields()
        .expect("fields")
        .iter()
        .map(|f| f.id)
        .collect();
    let started = Instant::now();
    loop {
        let cycles: f64 = state
            .metrics
            .render()
            .lines()
            .filter(|l| l.starts_with("rootzone_control_cycles_total{"))
            .filter_map(|l| l.rsplit(' ').next()?.parse::<f64>().ok())
            .sum();
        if cycles as usize >= fields && state.metrics.mqtt_connected.get() == 1 {
            break;
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    println!(
        "{fields} fields: first cycles done and MQTT subscribed after {:.1} s",
        started.elapsed().as_secs_f64()
    );

    // one gateway publishes every field's sensor, QoS 1
    let mut options = MqttOptions::new("load-sensors", "127.0.0.1", port);
    options.set_keep_alive(Duration::from_secs(30));
    let (client, mut eventloop) = AsyncClient::new(options, 10_000);
    tokio::spawn(async move {
        loop {
            if eventloop.poll().await.is_err() {
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
        }
    });

    let t0 = tokio::time::Instant::now() + Duration::from_secs(1);
    let mut tasks = Vec::new();
    for round in 0..rounds {
        for (k, &id) in ids.iter().enumerate() {
            let offset = window_s * (round as f64 + k as f64 / fields as f64);
            let at = t0 + Duration::from_secs_f64(offset);
            let (client, state) = (client.clone(), state.clone());
            tasks.push(tokio::spawn(async move {
                tokio::time::sleep_until(at).await;
                let notify = state.measured(id);
                let stored = notify.notified();
                tokio::pin!(stored);
                stored.as_mut().enable();
                let theta = 0.18 + 0.0001 * ((k + round) % 300) as f64;
                let payload = format!(
                    "{{\"theta\": {theta}, \"time\": \"{}\"}}",
                    chrono::Utc::now().to_rfc3339()
                );
                let sent = Instant::now();
                client
                    .publish(
                        format!("rootzone/fields/{id}/sensors/default"),
                        QoS::AtLeastOnce,
                        false,
                        payload,
                    )
                    .await
                    .ok()?;
                tokio::time::timeout(Duration::from_secs(30), stored)
                    .await
                    .ok()?;
                Some(sent.elapsed().as_secs_f64())
            }));
        }
    }
    let mut latencies = Vec::new();
    let mut timed_out = 0;
    for t in tasks {
        match t.await.ok().flatten() {
            Some(l) => latencies.push(l),
            None => timed_out += 1,
        }
    }
    let published = fields * rounds;
    let store = state.engine.store.clone();
    let stored: u64 = tokio::task::spawn_blocking(move || {
        ids.iter()
            .map(|&id| store.count_measurements(id).unwrap_or(0))
            .sum()
    })
    .await
    .expect("count");
    latencies.sort_by(f64::total_cmp);
    println!(
        "{published} readings ({fields} fields × {rounds} rounds, one per field per {window_s} s, \
         {:.2} readings/s): {stored} stored, {} lost, {timed_out} not confirmed within 30 s",
        fields as f64 / window_s,
        published as i64 - stored as i64
    );
    if !latencies.is_empty() {
        println!(
            "publish → committed: p50 {:.1} ms, p99 {:.1} ms, max {:.1} ms",
            percentile(&latencies, 0.5) * 1e3,
            percentile(&latencies, 0.99) * 1e3,
            latencies.last().copied().unwrap_or(0.0) * 1e3
        );
    }
    let refused: u64 = state
        .metrics
        .render()
        .lines()
        .filter(|l| l.starts_with("rootzone_mqtt_readings_refused_total{"))
        .filter_map(|l| l.rsplit(' ').next()?.parse::<u64>().ok())
        .sum();
    let ingest_p99 = state.metrics.mqtt_ingest_seconds.get_sample_count();
    println!("refused: {refused}; readings in the ingest histogram: {ingest_p99}");
    stop.cancel();
    let _ = server.await;
    let _ = broker.kill();
    let _ = broker.wait();
}
