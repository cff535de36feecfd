//! MQTT (issue 18) against a real Mosquitto broker, which the tests start
//! on a free port with a generated configuration in a temporary folder
//! (`.ci/run` installs Debian's `mosquitto`; without it these tests fail).
//! The daemon is the real binary, read back over HTTP.

mod common;

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use common::{TOKEN, config, create_field, curl, json_of, start};
use rumqttc::{Client, Event, MqttOptions, Packet, QoS};
use serde_json::{Value, json};

/// The mosquitto binary: on PATH or Debian's /usr/sbin.
fn mosquitto_binary() -> PathBuf {
    let on_path = std::env::var_os("PATH")
        .map(|p| std::env::split_paths(&p).collect::<Vec<_>>())
        .unwrap_or_default()
        .into_iter()
        .map(|d| d.join("mosquitto"))
        .find(|p| p.is_file());
    on_path
        .or_else(|| Some(PathBuf::from("/usr/sbin/mosquitto")).filter(|p| p.is_file()))
        .unwrap_or_else(|| {
            panic!(
                "the MQTT tests need Debian's mosquitto broker: \
                 apt-get install -y --no-install-recommends mosquitto (.ci/run does)"
            )
        })
}

/// A mosquitto broker on a free port of 127.0.0.1, with persistence in
/// its folder; stopped (SIGTERM, which saves its sessions) and started
/// again on the same port.
struct Broker {
    child: Option<Child>,
    port: u16,
    dir: PathBuf,
}

impl Broker {
    fn start(dir: &Path) -> Broker {
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port();
        let dir = dir.join("broker");
        std::fs::create_dir_all(&dir).unwrap();
        let conf = format!(
            "listener {port} 127.0.0.1\nallow_anonymous true\npersistence true\nuser root\n\
             persistence_location {}/\nautosave_interval 1\nmax_queued_messages 100000\n\
             max_inflight_messages 100\nlog_dest file {}/mosquitto.log\n",
            dir.display(),
            dir.display()
        );
        std::fs::write(dir.join("mosquitto.conf"), conf).unwrap();
        let mut b = Broker {
            child: None,
            port,
            dir,
        };
        b.run();
        b
    }

    fn run(&mut self) {
        let child = Command::new(mosquitto_binary())
            .arg("-c")
            .arg(self.dir.join("mosquitto.conf"))
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(self.dir.join("stderr.log")).unwrap())
            .spawn()
            .expect("mosquitto starts");
        self.child = Some(child);
        let deadline = Instant::now() + Duration::from_secs(10);
        while std::net::TcpStream::connect(("127.0.0.1", self.port)).is_err() {
            assert!(Instant::now() < deadline, "mosquitto did not listen");
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// SIGTERM and wait: mosquitto saves its sessions and retained
    /// messages on the way out.
    fn stop(&mut self) {
        if let Some(mut child) = self.child.take() {
            let pid = child.id().to_string();
            let _ = Command::new("kill").args(["-TERM", &pid]).status();
            let _ = child.wait();
        }
    }

    fn url(&self) -> String {
        format!("mqtt://127.0.0.1:{}", self.port)
    }
}

impl Drop for Broker {
    fn drop(&mut self) {
        if let Some(mut child) = self.child.take() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

/// A message seen: topic and payload.
type Message = (String, Vec<u8>);

/// A test client: publishes, and records every message of its
/// subscriptions (topic, payload).
struct Peer {
    client: Client,
    seen: Arc<Mutex<Vec<Message>>>,
}

impl Peer {
    fn connect(broker: &Broker, id: &str, clean: bool, subscribe: &[&str]) -> Peer {
        let mut options = MqttOptions::new(id, "127.0.0.1", broker.port);
        options
            .set_keep_alive(Duration::from_secs(5))
            .set_clean_session(clean)
            .set_max_packet_size(1 << 20, 1 << 20);
        let (client, mut connection) = Client::new(options, 1000);
        let seen = Arc::new(Mutex::new(Vec::new()));
        let (s, c, filters) = (
            seen.clone(),
            client.clone(),
            subscribe.iter().map(|f| f.to_string()).collect::<Vec<_>>(),
        );
        std::thread::spawn(move || {
            for event in connection.iter() {
                match event {
                    Ok(Event::Incoming(Packet::ConnAck(_))) => {
                        for f in &filters {
                            let _ = c.try_subscribe(f.clone(), QoS::AtLeastOnce);
                        }
                    }
                    Ok(Event::Incoming(Packet::Publish(p))) => {
                        s.lock()
                            .unwrap()
                            .push((p.topic.clone(), p.payload.to_vec()));
                    }
                    Ok(_) => {}
                    Err(rumqttc::ConnectionError::RequestsDone) => return,
                    Err(_) => std::thread::sleep(Duration::from_millis(100)),
                }
            }
        });
        Peer { client, seen }
    }

    fn publish(&self, topic: &str, payload: impl Into<Vec<u8>>) {
        self.client
            .publish(topic, QoS::AtLeastOnce, false, payload)
            .unwrap();
    }

    fn publish_retained(&self, topic: &str, payload: impl Into<Vec<u8>>) {
        self.client
            .publish(topic, QoS::AtLeastOnce, true, payload)
            .unwrap();
    }

    /// The last message on `topic` for which `pred` holds, waiting up to
    /// `secs`.
    fn wait_for(&self, topic: &str, secs: u64, pred: impl Fn(&Value) -> bool) -> Value {
        let deadline = Instant::now() + Duration::from_secs(secs);
        loop {
            let found = self
                .seen
                .lock()
                .unwrap()
                .iter()
                .rev()
                .filter(|(t, _)| t == topic)
                .filter_map(|(_, p)| serde_json::from_slice::<Value>(p).ok())
                .find(|v| pred(v));
            if let Some(v) = found {
                return v;
            }
            assert!(
                Instant::now() < deadline,
                "no matching message on {topic} within {secs} s; seen: {:?}",
                self.seen
                    .lock()
                    .unwrap()
                    .iter()
                    .map(|(t, p)| format!("{t} {}", String::from_utf8_lossy(p)))
                    .collect::<Vec<_>>()
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    fn raw_on(&self, topic: &str) -> Vec<Vec<u8>> {
        self.seen
            .lock()
            .unwrap()
            .iter()
            .filter(|(t, _)| t == topic)
            .map(|(_, p)| p.clone())
            .collect()
    }
}

/// A metric's value (0 when absent), `name` with its labels as printed.
fn metric(d: &common::Daemon, name: &str) -> f64 {
    let text = curl(d, "GET", "/metrics", None, None).2;
    text.lines()
        .find(|l| l.starts_with(name) && l[name.len()..].starts_with(' '))
        .and_then(|l| l.rsplit(' ').next())
        .map(|v| v.parse().unwrap())
        .unwrap_or(0.0)
}

fn wait_until(what: &str, secs: u64, mut ok: impl FnMut() -> bool) {
    let deadline = Instant::now() + Duration::from_secs(secs);
    while !ok() {
        assert!(Instant::now() < deadline, "{what}: not within {secs} s");
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// The daemon's configuration with MQTT on `broker`, retrying a lost
/// connection after `retry_s`.
fn mqtt_config(broker: &Broker, extra: &str, retry_s: f64) -> String {
    config(&format!(
        "{extra}\n[mqtt]\nurl = \"{}\"\nclient_id = \"rootzone-test\"\n\
         reconnect_min_s = {retry_s}\nreconnect_max_s = {retry_s}\n",
        broker.url()
    ))
}

fn measurements(d: &common::Daemon, id: i64) -> Vec<Value> {
    let r = curl(
        d,
        "GET",
        &format!("/v1/fields/{id}/measurements?limit=100000"),
        None,
        None,
    );
    assert_eq!(r.0, 200, "{}", r.2);
    json_of(&r.2).as_array().unwrap().clone()
}

#[test]
fn a_sensor_reading_drives_the_next_cycle_and_its_valve_command_arrives() {
    let dir = tempfile::tempdir().unwrap();
    let broker = Broker::start(dir.path());
    // 60× clock: a 600 s period passes every 10 s
    let d = start(
        dir.path(),
        &mqtt_config(&broker, "[clock]\nspeedup = 60.0\n", 0.5),
    );
    let watcher = Peer::connect(&broker, "watcher", true, &["rootzone/#", "homeassistant/#"]);
    wait_until("the daemon is connected and subscribed", 20, || {
        metric(&d, "rootzone_mqtt_connected") == 1.0
    });
    let (area, rate_mm_h) = (1_000.0, 80.0);
    // θ = 0.0005·raw: raw 300 is θ 0.15, below sandy loam's zone
    let id = create_field(
        &d,
        json!({
            "name": "orchard",
            "model": "richards",
            "control_period_s": 600.0,
            "measurement_wait_s": 0.0,
            "sensors": [{"id": "probe", "depth": 0.15,
                         "calibration": {"kind": "linear", "slope": 0.0005, "offset": 0.0}}],
            "irrigation_system": {"area_m2": area, "application_rate_mm_h": rate_mm_h}
        }),
    );
    // discovery: four sensors and a valve reading the field's state topic
    let state_topic = format!("rootzone/fields/{id}/state");
    for key in [
        "measured_theta",
        "estimated_theta",
        "next_irrigation",
        "status",
    ] {
        let doc = watcher.wait_for(
            &format!("homeassistant/sensor/rootzone-test_{id}_{key}/config"),
            10,
            |_| true,
        );
        assert_eq!(doc["state_topic"], state_topic.as_str(), "{doc}");
        assert_eq!(doc["availability_topic"], "rootzone/status");
        assert_eq!(doc["unique_id"], format!("rootzone-test_{id}_{key}"));
    }
    let valve = watcher.wait_for(
        &format!("homeassistant/valve/rootzone-test_{id}/config"),
        10,
        |_| true,
    );
    assert_eq!(valve["value_template"], "{{ value_json.valve }}");
    assert!(valve.get("command_topic").is_none(), "read-only: {valve}");
    assert_eq!(watcher.raw_on("rootzone/status").last().unwrap(), b"online");

    // Home Assistant's birth message brings the discovery again
    let valve_topic = format!("homeassistant/valve/rootzone-test_{id}/config");
    let before = watcher.raw_on(&valve_topic).len();
    watcher.publish("homeassistant/status", "online");
    wait_until("the discovery is published again", 10, || {
        watcher.raw_on(&valve_topic).len() > before
    });

    // the sensor publishes a plain raw number; the daemon stamps it
    let sensor = Peer::connect(&broker, "probe-node", true, &[]);
    sensor.publish(&format!("rootzone/fields/{id}/sensors/probe"), "300");
    let mut stored = Vec::new();
    wait_until("the reading is stored", 10, || {
        stored = measurements(&d, id);
        !stored.is_empty()
    });
    assert_eq!(stored.len(), 1, "{stored:?}");
    let m = &stored[0];
    assert_eq!(m["raw"], 300.0);
    assert!((m["theta"].as_f64().unwrap() - 0.15).abs() < 1e-12, "{m}");
    assert!(m.get("sensor").is_none(), "the primary sensor's: {m}");
    let measured_at: chrono::DateTime<chrono::Utc> = m["time"].as_str().unwrap().parse().unwrap();

    // the next scheduled cycle starts from it, and its command arrives
    let command_topic = format!("rootzone/fields/{id}/valve/command");
    let command = watcher.wait_for(&command_topic, 30, |c| {
        c["valid_from"]
            .as_str()
            .and_then(|t| t.parse::<chrono::DateTime<chrono::Utc>>().ok())
            .is_some_and(|t| t > measured_at)
    });
    let r = curl(
        &d,
        "GET",
        &format!("/v1/fields/{id}/setpoints?limit=1000"),
        None,
        None,
    );
    assert_eq!(r.0, 200, "{}", r.2);
    let setpoints = json_of(&r.2);
    let sp = setpoints
        .as_array()
        .unwrap()
        .iter()
        .find(|s| s["valid_from"] == command["valid_from"])
        .unwrap_or_else(|| panic!("no setpoint for {command}"))
        .clone();
    let used: chrono::DateTime<chrono::Utc> = sp["measured_at"].as_str().unwrap().parse().unwrap();
    assert_eq!(used, measured_at, "the cycle used the MQTT reading: {sp}");
    let amount = sp["amount_mm"].as_f64().unwrap();
    assert!(amount > 0.0, "θ 0.15 is below the zone: {sp}");
    assert_eq!(command["rate_m_s"], sp["rate"]);
    assert_eq!(command["amount_mm"], sp["amount_mm"]);
    // the valve runs amount / rate, at most the 10-minute period
    let expected = (amount / rate_mm_h * 60.0).min(10.0);
    let minutes = command["minutes"].as_f64().unwrap();
    assert!((minutes - expected).abs() < 1e-9, "{command}");
    let litres = command["litres"].as_f64().unwrap();
    let applied_mm = minutes / 60.0 * rate_mm_h;
    assert!(
        (litres - applied_mm * area).abs() < 1e-6 * litres,
        "{command}"
    );
    assert!((command["volume_m3"].as_f64().unwrap() - litres / 1e3).abs() < 1e-9);
    let pulses = command["pulses"].as_array().unwrap();
    let total: f64 = pulses.iter().map(|p| p["minutes"].as_f64().unwrap()).sum();
    assert!((total - minutes).abs() < 1e-9, "{command}");
    assert_eq!(command["valid_until"], sp["valid_until"]);

    // the retained state for Home Assistant
    let state = watcher.wait_for(&state_topic, 10, |s| {
        s["next_irrigation_at"] == command["valid_from"]
    });
    assert!((state["measured_theta"].as_f64().unwrap() - 0.15).abs() < 1e-12);
    assert_eq!(state["next_irrigation_mm"], sp["amount_mm"]);
    assert_eq!(state["status"], sp["status"]);
    assert_eq!(state["valve"], "open");
    let est = state["estimated_theta"].as_f64().unwrap();
    assert!(est > 0.0 && est < 0.5, "{state}");
    // retained: a client that comes later gets the command at once
    let late = Peer::connect(&broker, "late", true, &[command_topic.as_str()]);
    let again = late.wait_for(&command_topic, 10, |_| true);
    assert!(again["valid_from"].is_string());

    // deleting the field clears its retained topics
    let r = curl(&d, "DELETE", &format!("/v1/fields/{id}"), None, Some(TOKEN));
    assert_eq!(r.0, 204, "{}", r.2);
    wait_until("the retained command is cleared", 10, || {
        watcher
            .raw_on(&command_topic)
            .last()
            .is_some_and(|p| p.is_empty())
    });
}

#[test]
fn bad_payloads_are_refused_counted_and_never_stored() {
    let dir = tempfile::tempdir().unwrap();
    let broker = Broker::start(dir.path());
    // a retained reading without its time comes again with every
    // subscription (the daemon's at its start here): it is refused, or each
    // reconnect would store it anew. (The first field will be field 1.)
    let early = Peer::connect(&broker, "early-sensor", true, &[]);
    early.publish_retained("rootzone/fields/1/sensors/a", "0.2");
    let marker = Peer::connect(&broker, "marker", true, &["rootzone/fields/1/sensors/a"]);
    marker.wait_for("rootzone/fields/1/sensors/a", 10, |_| true);
    let d = start(dir.path(), &mqtt_config(&broker, "", 0.5));
    wait_until("the daemon is connected and subscribed", 20, || {
        metric(&d, "rootzone_mqtt_connected") == 1.0
    });
    let id = create_field(
        &d,
        json!({
            "name": "bed",
            "model": "richards",
            "sensors": [
                {"id": "a", "depth": 0.15},
                {"id": "c", "depth": 0.3,
                 "calibration": {"kind": "table", "points": [[100, 0.05], [500, 0.40]]}}
            ]
        }),
    );
    assert_eq!(id, 1, "the retained reading above is field 1's");
    let p = Peer::connect(&broker, "bad-sensor", true, &[]);
    let a = format!("rootzone/fields/{id}/sensors/a");
    let c = format!("rootzone/fields/{id}/sensors/c");
    let now = chrono::Utc::now();
    let cases: Vec<(String, Vec<u8>, &str)> = vec![
        (a.clone(), b"abc".to_vec(), "payload"),
        (a.clone(), b"".to_vec(), "payload"),
        (
            a.clone(),
            br#"{"theta": 0.2, "extra": 1}"#.to_vec(),
            "payload",
        ),
        (a.clone(), br#"{"theta": null}"#.to_vec(), "payload"),
        (a.clone(), vec![b' '; 5000], "too-large"),
        (a.clone(), b"1.5".to_vec(), "range"),
        (a.clone(), b"-0.1".to_vec(), "range"),
        (
            a.clone(),
            br#"{"theta": 0.2, "raw": 300}"#.to_vec(),
            "value",
        ),
        (a.clone(), br#"{"raw": 300}"#.to_vec(), "calibration"),
        (c.clone(), b"700".to_vec(), "range"),
        (
            a.clone(),
            br#"{"theta": 0.2, "time": "2199-12-31T00:00:00Z"}"#.to_vec(),
            "time",
        ),
        (
            a.clone(),
            br#"{"theta": 0.2, "time": "yesterday"}"#.to_vec(),
            "time",
        ),
        (
            format!("rootzone/fields/{id}/sensors/nope"),
            b"0.2".to_vec(),
            "unknown-sensor",
        ),
        (
            format!("rootzone/fields/{}/sensors/a", id + 100),
            b"0.2".to_vec(),
            "unknown-field",
        ),
        (
            "rootzone/fields/x1/sensors/a".into(),
            b"0.2".to_vec(),
            "topic",
        ),
    ];
    let mut expected: std::collections::BTreeMap<&str, f64> = Default::default();
    for (topic, payload, reason) in &cases {
        p.publish(topic, payload.clone());
        *expected.entry(reason).or_default() += 1.0;
    }
    // the retained reading left before the daemon came
    *expected.entry("retained").or_default() += 1.0;
    // then good ones: a plain θ, and a raw reading of the calibrated sensor
    let t = (now - chrono::TimeDelta::minutes(5)).to_rfc3339();
    p.publish(&a, format!(r#"{{"theta": 0.21, "time": "{t}"}}"#));
    p.publish(&c, format!(r#"{{"raw": 300, "time": "{t}"}}"#));
    wait_until("the good readings are stored", 10, || {
        measurements(&d, id).len() == 2
    });
    wait_until("every refusal is counted", 10, || {
        expected.iter().all(|(reason, n)| {
            metric(
                &d,
                &format!("rootzone_mqtt_readings_refused_total{{reason=\"{reason}\"}}"),
            ) == *n
        })
    });
    let total: f64 = expected.values().sum();
    assert_eq!(total, cases.len() as f64 + 1.0);
    let stored = measurements(&d, id);
    assert_eq!(stored.len(), 2, "only the good readings: {stored:?}");
    let primary = stored.iter().find(|m| m.get("sensor").is_none()).unwrap();
    assert_eq!(primary["theta"], 0.21);
    let calibrated = stored.iter().find(|m| m["sensor"] == "c").unwrap();
    // the table: 0.05 + (0.40 − 0.05)·(300 − 100)/(500 − 100)
    let theta = 0.05 + 0.35 * 200.0 / 400.0;
    assert!((calibrated["theta"].as_f64().unwrap() - theta).abs() < 1e-12);
    // a resent reading is a duplicate, not a second measurement
    p.publish(&a, format!(r#"{{"theta": 0.21, "time": "{t}"}}"#));
    p.publish(&a, format!(r#"{{"theta": 0.25, "time": "{t}"}}"#));
    wait_until("the resend and the conflict are counted", 10, || {
        metric(&d, "rootzone_mqtt_readings_duplicate_total") == 1.0
            && metric(
                &d,
                "rootzone_mqtt_readings_refused_total{reason=\"conflict\"}",
            ) == 1.0
    });
    assert_eq!(measurements(&d, id).len(), 2);
    // the daemon is alive and still subscribed
    assert_eq!(curl(&d, "GET", "/healthz", None, None).0, 200);
    assert_eq!(metric(&d, "rootzone_mqtt_connected"), 1.0);
}

#[test]
fn a_broker_restart_loses_no_reading_at_qos1() {
    let dir = tempfile::tempdir().unwrap();
    let mut broker = Broker::start(dir.path());
    // the daemon is back 3 s after a restart, the sensor within 0.1 s: what
    // the sensor sends in between waits in the daemon's session
    let d = start(dir.path(), &mqtt_config(&broker, "", 3.0));
    wait_until("the daemon is connected and subscribed", 20, || {
        metric(&d, "rootzone_mqtt_connected") == 1.0
    });
    let id = create_field(&d, json!({"name": "plot", "model": "richards"}));
    let topic = format!("rootzone/fields/{id}/sensors/default");
    // the sensor keeps a persistent session too, so what it sent while the
    // broker was down goes out when it is back
    let sensor = Peer::connect(&broker, "field-node", false, &[]);
    let start_t = chrono::Utc::now() - chrono::TimeDelta::minutes(50);
    let reading = |i: usize| {
        let t = start_t + chrono::TimeDelta::minutes(i as i64);
        (
            t,
            0.2 + 0.001 * i as f64,
            json!({"time": t.to_rfc3339(), "theta": 0.2 + 0.001 * i as f64}).to_string(),
        )
    };
    let count = |n: usize| {
        let d = &d;
        move || measurements(d, id).len() == n
    };
    for i in 0..5 {
        sensor.publish(&topic, reading(i).2);
    }
    wait_until("the first readings are stored", 10, count(5));
    let connections = metric(&d, "rootzone_mqtt_connections_total");

    // 1. the broker restarts with its sessions (persistence): readings
    // sent while the daemon was not yet back reach it through its session
    broker.stop();
    for i in 5..10 {
        sensor.publish(&topic, reading(i).2);
    }
    broker.run();
    wait_until("the readings across the restart are stored", 20, count(10));
    wait_until("the daemon reconnected", 20, || {
        metric(&d, "rootzone_mqtt_connections_total") > connections
            && metric(&d, "rootzone_mqtt_connected") == 1.0
    });

    // 2. the broker restarts without its sessions: only the daemon's own
    // subscription after the ConnAck brings further readings
    broker.stop();
    let db = broker.dir.join("mosquitto.db");
    if db.exists() {
        std::fs::remove_file(&db).unwrap();
    }
    let connections = metric(&d, "rootzone_mqtt_connections_total");
    broker.run();
    wait_until("the daemon reconnected and subscribed again", 20, || {
        metric(&d, "rootzone_mqtt_connections_total") > connections
            && metric(&d, "rootzone_mqtt_connected") == 1.0
    });
    for i in 10..15 {
        sensor.publish(&topic, reading(i).2);
    }
    wait_until(
        "the readings after a lost session are stored",
        20,
        count(15),
    );
    let stored = measurements(&d, id);
    for (i, m) in stored.iter().enumerate() {
        let (t, theta, _) = reading(i);
        let at: chrono::DateTime<chrono::Utc> = m["time"].as_str().unwrap().parse().unwrap();
        assert_eq!(at.timestamp_millis(), t.timestamp_millis(), "{m}");
        assert_eq!(m["theta"].as_f64().unwrap(), theta, "{m}");
    }
    assert_eq!(
        metric(
            &d,
            "rootzone_mqtt_readings_refused_total{reason=\"payload\"}"
        ),
        0.0
    );
}

#[test]
fn readings_that_arrive_while_the_database_is_away_are_acknowledged_only_once_stored() {
    // a PostgreSQL server of its own, to stop; the `_on_postgres` twin
    // would only run this again
    if common::on_postgres() {
        return;
    }
    let pg = common::postgres::Postgres::start();
    let url = pg.fresh_database();
    let dir = tempfile::tempdir().unwrap();
    let broker = Broker::start(dir.path());
    let config = mqtt_config(&broker, "", 0.5);
    let env = [("ROOTZONE_STORAGE__URL", url.as_str())];
    let mut d = common::start_with(dir.path(), &config, &env);
    wait_until("the daemon is connected and subscribed", 20, || {
        metric(&d, "rootzone_mqtt_connected") == 1.0
    });
    let id = create_field(&d, json!({"name": "plot", "model": "richards"}));
    let topic = format!("rootzone/fields/{id}/sensors/default");
    let sensor = Peer::connect(&broker, "field-node", false, &[]);
    let t0 = chrono::Utc::now() - chrono::TimeDelta::minutes(50);
    let reading = |i: usize| {
        let t = t0 + chrono::TimeDelta::minutes(i as i64);
        (t, 0.2 + 0.001 * i as f64)
    };
    let send = |i: usize| {
        let (t, theta) = reading(i);
        sensor.publish(
            &topic,
            json!({"time": t.to_rfc3339(), "theta": theta}).to_string(),
        );
    };
    for i in 0..3 {
        send(i);
    }
    wait_until("the first readings are stored", 10, || {
        measurements(&d, id).len() == 3
    });

    // 1. the database goes away: readings arrive, wait unacknowledged, and
    // are stored when it is back
    pg.kill();
    for i in 3..6 {
        send(i);
    }
    wait_until("the daemon has received them", 10, || {
        metric(&d, "rootzone_mqtt_messages_received_total") >= 6.0
    });
    std::thread::sleep(Duration::from_secs(2));
    pg.resume();
    wait_until("the readings sent while it was away are stored", 30, || {
        measurements(&d, id).len() == 6
    });

    // 2. the database goes away and the daemon is killed (-9) with readings
    // it has received but not stored: the broker still holds them for its
    // session, and the daemon started again stores them
    pg.kill();
    for i in 6..9 {
        send(i);
    }
    wait_until("the daemon has received them too", 10, || {
        metric(&d, "rootzone_mqtt_messages_received_total") >= 9.0
    });
    d.child.kill().unwrap();
    d.child.wait().unwrap();
    pg.resume();
    d = common::start_with(dir.path(), &config, &env);
    wait_until("the readings of the killed daemon are stored", 30, || {
        measurements(&d, id).len() == 9
    });
    let stored = measurements(&d, id);
    for (i, m) in stored.iter().enumerate() {
        let (t, theta) = reading(i);
        let at: chrono::DateTime<chrono::Utc> = m["time"].as_str().unwrap().parse().unwrap();
        assert_eq!(at.timestamp_millis(), t.timestamp_millis(), "{m}");
        assert_eq!(m["theta"].as_f64().unwrap(), theta, "{m}");
    }
    for reason in ["unknown-field", "payload"] {
        let name = format!("rootzone_mqtt_readings_refused_total{{reason=\"{reason}\"}}");
        assert_eq!(metric(&d, &name), 0.0, "{reason}");
    }

    // 3. a graceful stop has acknowledged everything it stored: started
    // again, the daemon is delivered nothing old
    d.sigterm();
    d.child.wait().unwrap();
    let d = common::start_with(dir.path(), &config, &env);
    wait_until("the daemon is connected again", 20, || {
        metric(&d, "rootzone_mqtt_connected") == 1.0
    });
    std::thread::sleep(Duration::from_secs(2));
    assert_eq!(
        metric(&d, "rootzone_mqtt_messages_received_total"),
        0.0,
        "messages delivered again after a graceful stop"
    );
    assert_eq!(measurements(&d, id).len(), 9);
}
