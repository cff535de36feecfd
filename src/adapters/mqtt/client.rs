//! The MQTT connection (rumqttc) and the ingest of its readings.
//!
//! - One event-loop task polls the connection. On every `ConnAck` it
//!   subscribes again (rumqttc does not restore subscriptions, rumqtt issue
//!   250; a broker that lost the session would otherwise send nothing) and
//!   republishes the availability, the discovery documents and every
//!   field's state and command, in a task of its own so the loop keeps
//!   polling. Failed connections are retried after a wait doubled per
//!   failure (`reconnect_min_s` … `reconnect_max_s`).
//! - The session is persistent (clean session false, the fixed client id),
//!   subscriptions and publications are QoS 1: a broker that keeps its
//!   sessions (mosquitto with `persistence true`) delivers the readings
//!   that arrived while the daemon was away.
//! - A sensor message is checked on arrival (size, topic, payload syntax)
//!   and queued for the ingest task (bounded, `mqtt.queue`; when full, the
//!   loop waits, and the broker holds the messages). The ingest takes what
//!   has queued up (at most `mqtt.batch_max`), checks each reading against
//!   its field ([`check_reading`], the same as the HTTP API) and stores the
//!   batch in one transaction; then it wakes the fields' waiting cycles.
//!   Every refusal is counted (`rootzone_mqtt_readings_refused_total` by
//!   reason) and logged (at most one warning per reason every 10 s), never
//!   stored, never fatal.
//! - Acknowledgements are manual: a QoS 1 message is acknowledged (PUBACK)
//!   only after its batch's transaction committed, or once it was refused.
//!   Every message, refused or not, passes through the ingest queue, so
//!   the acknowledgements leave in the order the messages arrived (MQTT
//!   3.1.1 §4.6). A batch the database cannot take (unavailable) is
//!   retried, waiting 0.5 s doubled up to 5 s, until it is stored or the
//!   daemon stops; its messages stay unacknowledged meanwhile, so the
//!   broker keeps them and its in-flight window holds back more. A stop
//!   stores the queue and sends its acknowledgements before it
//!   disconnects. A daemon
//!   killed before a batch committed has acknowledged none of it: the
//!   broker delivers it again to the persistent session (at least once; a
//!   reading that carries its time is then stored once, one stamped on
//!   arrival gets the time of its second arrival).

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use chrono::{DateTime, Utc};
use rumqttc::{AsyncClient, Event, EventLoop, LastWill, MqttOptions, Packet, QoS};
use tokio::sync::mpsc;

use super::{FieldState, MAX_PACKET_BYTES, MqttSettings, Payload, Refusal, Topics};
use crate::service::AppState;
use crate::service::store::ReadingOutcome;
use crate::service::wire::{Field, Measurement, ReadingIn, Setpoint, check_reading};

/// Requests (publications, subscriptions) waiting for the connection; when
/// full, a publication is dropped and counted (states and commands are
/// published again at the next connection).
const REQUEST_QUEUE: usize = 4096;

/// The daemon's side of MQTT: the client handle and the topic scheme.
pub struct Mqtt {
    client: AsyncClient,
    pub topics: Topics,
    pub settings: MqttSettings,
    /// The last warning per refusal reason (log throttle).
    warned: Mutex<HashMap<&'static str, Instant>>,
}

/// A message for the ingest task: a reading that passed the arrival
/// checks (`None`: refused on arrival, or not a reading), and the message,
/// acknowledged once its batch is settled.
struct Queued {
    arrival: Option<Arrival>,
    publish: rumqttc::Publish,
}

/// A sensor message that passed the arrival checks.
struct Arrival {
    field: i64,
    sensor: String,
    payload: Payload,
    /// The daemon's clock at arrival (the reading's time when it names none).
    arrived: DateTime<Utc>,
    received: Instant,
    topic: String,
}

impl Mqtt {
    /// The client and its (not yet polled) event loop, or None when
    /// `mqtt.url` is unset.
    pub fn new(settings: &MqttSettings) -> Result<Option<(Mqtt, EventLoop)>, String> {
        let Some(url) = &settings.url else {
            return Ok(None);
        };
        let broker = super::parse_broker(url)?;
        let topics = Topics::new(settings);
        let mut options = MqttOptions::new(settings.client_id.clone(), broker.host, broker.port);
        options
            .set_keep_alive(Duration::from_secs_f64(settings.keep_alive_s))
            .set_clean_session(false)
            .set_manual_acks(true)
            .set_max_packet_size(MAX_PACKET_BYTES, MAX_PACKET_BYTES)
            .set_last_will(LastWill::new(
                topics.availability(),
                "offline",
                QoS::AtLeastOnce,
                true,
            ));
        if let Some(user) = &settings.username {
            options.set_credentials(user.clone(), settings.password.clone().unwrap_or_default());
        }
        let (client, eventloop) = AsyncClient::new(options, REQUEST_QUEUE);
        Ok(Some((
            Mqtt {
                client,
                topics,
                settings: settings.clone(),
                warned: Mutex::new(HashMap::new()),
            },
            eventloop,
        )))
    }

    /// Queues a retained QoS 1 publication without waiting; false (counted)
    /// when the request queue is full.
    fn publish_now(&self, state: &AppState, topic: String, payload: Vec<u8>) -> bool {
        let ok = self
            .client
            .try_publish(topic, QoS::AtLeastOnce, true, payload)
            .is_ok();
        state
            .metrics
            .mqtt_published
            .with_label_values(&[if ok { "queued" } else { "dropped" }])
            .inc();
        ok
    }

    /// Publishes a new setpoint: the field's valve command and its state.
    pub fn publish_setpoint(&self, state: &AppState, field: &Field, sp: &Setpoint) {
        let command = super::valve_command(sp).to_string().into_bytes();
        if !self.publish_now(state, self.topics.valve_command(field.id), command) {
            tracing::warn!(
                field = field.id,
                "MQTT request queue full: the valve command waits for the next connection"
            );
        }
        let doc = state_document(state, field, Some(sp));
        self.publish_now(state, self.topics.state(field.id), doc.into_bytes());
    }

    /// Publishes a field's discovery documents (a new field).
    pub fn announce(&self, state: &AppState, field: &Field) {
        if self.settings.discovery {
            for (topic, doc) in super::discovery(&self.topics, field.id, &field.spec.name) {
                self.publish_now(state, topic, doc.to_string().into_bytes());
            }
        }
    }

    /// Clears a deleted field's retained topics (empty retained payloads,
    /// which also remove its entities from Home Assistant).
    pub fn withdraw(&self, state: &AppState, field: i64) {
        for topic in self.topics.retained_of(field, self.settings.discovery) {
            self.publish_now(state, topic, Vec::new());
        }
    }

    /// Counts and logs a refused message.
    fn refuse(&self, state: &AppState, topic: &str, r: &Refusal) {
        state
            .metrics
            .mqtt_refused
            .with_label_values(&[r.reason])
            .inc();
        let now = Instant::now();
        let loud = {
            let mut warned = self.warned.lock().unwrap_or_else(|p| p.into_inner());
            let last = warned.get(r.reason).copied();
            let loud = last.is_none_or(|t| now.duration_since(t) >= Duration::from_secs(10));
            if loud {
                warned.insert(r.reason, now);
            }
            loud
        };
        if loud {
            tracing::warn!(%topic, reason = r.reason, error = %r.message,
                "MQTT reading refused (further ones of this reason within 10 s at debug)");
        } else {
            tracing::debug!(%topic, reason = r.reason, error = %r.message, "MQTT reading refused");
        }
    }
}

/// A field's state document from storage: the primary sensor's latest
/// reading, the estimate's θ at its depth, the setpoint (given, or the
/// latest stored).
fn state_document(state: &AppState, field: &Field, sp: Option<&Setpoint>) -> String {
    let store = &state.engine.store;
    let measured = store
        .measurement_before(
            field.id,
            crate::service::clock::add_seconds(state.clock.now(), 1e9),
        )
        .ok()
        .flatten()
        .map(|m| (m.theta, m.time));
    let depth = field.spec.effective_sensors()[0].depth;
    let estimated_theta = state
        .engine
        .current_estimate(field)
        .ok()
        .flatten()
        .and_then(|(_, est)| {
            est.profile()
                .into_iter()
                .min_by(|a, b| (a.depth - depth).abs().total_cmp(&(b.depth - depth).abs()))
                .map(|p| p.theta_mean)
        });
    let latest;
    let setpoint = match sp {
        Some(sp) => Some(sp),
        None => {
            latest = store
                .recent_setpoints(field.id, 1)
                .ok()
                .and_then(|mut v| v.pop());
            latest.as_ref()
        }
    };
    super::field_state(&FieldState {
        measured,
        estimated_theta,
        setpoint,
    })
    .to_string()
}

/// Runs the connection and the ingest until shutdown.
pub async fn run(state: Arc<AppState>, mqtt: Arc<Mqtt>, mut eventloop: EventLoop) {
    let (tx, rx) = mpsc::channel::<Queued>(mqtt.settings.queue);
    let ingest = {
        let (state, mqtt) = (state.clone(), mqtt.clone());
        tokio::spawn(async move { ingest_loop(state, mqtt, rx).await })
    };
    let shutdown = state.shutdown_token();
    let m = &state.metrics;
    let mut backoff = mqtt.settings.reconnect_min_s;
    let mut failures = 0u64;
    let mut on_connect: Option<tokio::task::JoinHandle<()>> = None;
    let ha_status = mqtt.topics.ha_status();
    loop {
        let event = tokio::select! {
            e = eventloop.poll() => e,
            _ = shutdown.cancelled() => break,
        };
        match event {
            Ok(Event::Incoming(Packet::ConnAck(ack))) => {
                m.mqtt_connections.inc();
                tracing::info!(session_present = ack.session_present, "MQTT connected");
                backoff = mqtt.settings.reconnect_min_s;
                failures = 0;
                if let Some(old) = on_connect.take() {
                    old.abort();
                }
                let (state, mqtt) = (state.clone(), mqtt.clone());
                on_connect = Some(tokio::spawn(async move {
                    connected(&state, &mqtt, true).await;
                }));
            }
            Ok(Event::Incoming(Packet::SubAck(ack))) => {
                let granted = ack
                    .return_codes
                    .iter()
                    .all(|c| matches!(c, rumqttc::SubscribeReasonCode::Success(_)));
                if granted {
                    m.mqtt_connected.set(1);
                } else {
                    tracing::error!(codes = ?ack.return_codes,
                        "MQTT broker refused a subscription: no sensor readings will arrive");
                }
            }
            Ok(Event::Incoming(Packet::Publish(p))) => {
                m.mqtt_received.inc();
                let arrival = if p.topic == ha_status {
                    // one republication at a time, however often it is asked for
                    let idle = on_connect.as_ref().is_none_or(|h| h.is_finished());
                    if mqtt.settings.discovery && &p.payload[..] == b"online" && idle {
                        let (state, mqtt) = (state.clone(), mqtt.clone());
                        on_connect = Some(tokio::spawn(async move {
                            connected(&state, &mqtt, false).await;
                        }));
                    }
                    None
                } else {
                    let checked = mqtt
                        .topics
                        .parse_sensor(&p.topic)
                        .map_err(|e| Refusal::new("topic", e))
                        .and_then(|t| {
                            let payload =
                                super::parse_payload(&p.payload, mqtt.settings.max_payload_bytes)?;
                            // a retained reading comes again with every new
                            // subscription: without its own time it would be
                            // stored again at each reconnect
                            if p.retain && !matches!(payload, Payload::Json { time: Some(_), .. }) {
                                return Err(Refusal::new(
                                    "retained",
                                    "a retained reading must carry its time",
                                ));
                            }
                            Ok(Arrival {
                                field: t.field,
                                sensor: t.sensor,
                                payload,
                                arrived: state.clock.now(),
                                received: Instant::now(),
                                topic: p.topic.clone(),
                            })
                        });
                    match checked {
                        Ok(a) => Some(a),
                        Err(r) => {
                            mqtt.refuse(&state, &p.topic, &r);
                            None
                        }
                    }
                };
                // a full queue holds the loop (and so the broker's
                // deliveries) until the ingest catches up
                let queued = Queued {
                    arrival,
                    publish: p,
                };
                tokio::select! {
                    r = tx.send(queued) => if r.is_err() { break },
                    _ = shutdown.cancelled() => break,
                }
            }
            Ok(_) => {}
            Err(e) => {
                m.mqtt_connected.set(0);
                failures += 1;
                if failures == 1 {
                    tracing::warn!(error = %e, retry_s = backoff, "MQTT connection lost or refused");
                } else {
                    tracing::debug!(error = %e, retry_s = backoff, failures, "MQTT connection");
                }
                tokio::select! {
                    _ = tokio::time::sleep(Duration::from_secs_f64(backoff)) => {}
                    _ = shutdown.cancelled() => break,
                }
                backoff = (backoff * 2.0).min(mqtt.settings.reconnect_max_s);
            }
        }
    }
    if let Some(t) = on_connect.take() {
        t.abort();
    }
    // the ingest stores what is queued and queues its acknowledgements,
    // then ends; they go out before the disconnect below
    drop(tx);
    let _ = ingest.await;
    // offline, then a clean disconnect (the last will is for crashes);
    // the loop is polled a little so they leave
    m.mqtt_connected.set(0);
    let _ = mqtt.client.try_publish(
        mqtt.topics.availability(),
        QoS::AtLeastOnce,
        true,
        "offline",
    );
    let _ = mqtt.client.try_disconnect();
    let _ = tokio::time::timeout(Duration::from_secs(1), async {
        loop {
            match eventloop.poll().await {
                Ok(Event::Outgoing(rumqttc::Outgoing::Disconnect)) | Err(_) => break,
                Ok(_) => {}
            }
        }
    })
    .await;
}

/// After a connection (`subscribe`) or Home Assistant's birth message: the
/// subscriptions, the availability, the discovery and every field's state
/// and latest command, waiting for room in the request queue.
async fn connected(state: &Arc<AppState>, mqtt: &Mqtt, subscribe: bool) {
    let c = &mqtt.client;
    if subscribe {
        let mut filters = vec![rumqttc::SubscribeFilter::new(
            mqtt.topics.sensor_filter(),
            QoS::AtLeastOnce,
        )];
        if mqtt.settings.discovery {
            filters.push(rumqttc::SubscribeFilter::new(
                mqtt.topics.ha_status(),
                QoS::AtLeastOnce,
            ));
        }
        if c.subscribe_many(filters).await.is_err() {
            return;
        }
        if c.publish(mqtt.topics.availability(), QoS::AtLeastOnce, true, "online")
            .await
            .is_err()
        {
            return;
        }
    }
    for field in state.all_fields().await {
        let mut docs: Vec<(String, Vec<u8>)> = Vec::new();
        if mqtt.settings.discovery {
            for (topic, doc) in super::discovery(&mqtt.topics, field.id, &field.spec.name) {
                docs.push((topic, doc.to_string().into_bytes()));
            }
        }
        let (s, f) = (state.clone(), field.clone());
        let (doc, latest) = tokio::task::spawn_blocking(move || {
            let latest = s
                .engine
                .store
                .recent_setpoints(f.id, 1)
                .ok()
                .and_then(|mut v| v.pop());
            (state_document(&s, &f, latest.as_ref()), latest)
        })
        .await
        .unwrap_or_default();
        docs.push((mqtt.topics.state(field.id), doc.into_bytes()));
        if let Some(sp) = latest {
            docs.push((
                mqtt.topics.valve_command(field.id),
                super::valve_command(&sp).to_string().into_bytes(),
            ));
        }
        for (topic, payload) in docs {
            if c.publish(topic, QoS::AtLeastOnce, true, payload)
                .await
                .is_err()
            {
                return;
            }
        }
    }
}

/// Takes what has queued (at most `batch_max`), checks and stores it in
/// one transaction (again, after a wait, while the database is
/// unavailable), acknowledges its messages in their order, wakes the
/// fields; until the queue closes or the daemon stops.
async fn ingest_loop(state: Arc<AppState>, mqtt: Arc<Mqtt>, mut rx: mpsc::Receiver<Queued>) {
    let max = mqtt.settings.batch_max;
    let shutdown = state.shutdown_token();
    let mut batch = Vec::with_capacity(max);
    while rx.recv_many(&mut batch, max).await > 0 {
        let (arrivals, publishes): (Vec<_>, Vec<_>) = std::mem::take(&mut batch)
            .into_iter()
            .map(|q| (q.arrival, q.publish))
            .unzip();
        let arrivals: Arc<Vec<Arrival>> = Arc::new(arrivals.into_iter().flatten().collect());
        let mut wait = Duration::from_millis(500);
        let stored = loop {
            let (s, m, a) = (state.clone(), mqtt.clone(), arrivals.clone());
            match tokio::task::spawn_blocking(move || store_batch(&s, &m, &a)).await {
                Ok(Ok(stored)) => break Some(stored),
                Ok(Err(e)) if e.is_unavailable() => {
                    tracing::warn!(error = %e, readings = arrivals.len(), retry_s = wait.as_secs_f64(),
                        "MQTT ingest: the database is unavailable; the batch waits, unacknowledged");
                    tokio::select! {
                        _ = tokio::time::sleep(wait) => {}
                        // unacknowledged: the broker delivers them again
                        _ = shutdown.cancelled() => return,
                    }
                    wait = (wait * 2).min(Duration::from_secs(5));
                }
                Ok(Err(e)) => {
                    // not a lost connection: trying again would fail again
                    tracing::error!(error = %e, readings = arrivals.len(), "MQTT ingest: storing failed");
                    break None;
                }
                Err(e) => {
                    tracing::error!(error = %e, "MQTT ingest batch failed");
                    break None;
                }
            }
        };
        for p in &publishes {
            // the event loop sends it; at shutdown it may no longer run,
            // and the broker delivers the message again
            let _ = mqtt.client.try_ack(p);
        }
        for id in stored.unwrap_or_default() {
            state.measured(id).notify_waiters();
        }
    }
}

/// Checks and stores one batch; returns the fields that got readings.
fn store_batch(
    state: &AppState,
    mqtt: &Mqtt,
    batch: &[Arrival],
) -> Result<Vec<i64>, crate::service::store::StoreError> {
    let store = &state.engine.store;
    let skew = state.settings.limits.max_future_skew_s;
    let mut fields: HashMap<i64, Option<Field>> = HashMap::new();
    let mut checked: Vec<(i64, Measurement)> = Vec::with_capacity(batch.len());
    let mut origin: Vec<&Arrival> = Vec::with_capacity(batch.len());
    // refusals are told once the batch is settled (a batch tried again
    // would tell them twice)
    let mut refused: Vec<(&str, Refusal)> = Vec::new();
    for a in batch {
        // a database that cannot be read fails the batch (tried again)
        let field = match fields.entry(a.field) {
            std::collections::hash_map::Entry::Occupied(e) => e.into_mut(),
            std::collections::hash_map::Entry::Vacant(e) => e.insert(store.field(a.field)?),
        };
        let Some(field) = field else {
            let r = Refusal::new("unknown-field", format!("there is no field {}", a.field));
            refused.push((&a.topic, r));
            continue;
        };
        let calibrated = field
            .spec
            .effective_sensors()
            .iter()
            .find(|s| s.id == a.sensor)
            .is_some_and(|s| s.calibration.is_some());
        let (theta, raw, time) = a.payload.values(calibrated, a.arrived);
        let reading = ReadingIn {
            time,
            theta,
            raw,
            sensor: Some(&a.sensor),
        };
        match check_reading(&a.topic, reading, field, state.clock.now(), skew) {
            Ok(m) => {
                checked.push((a.field, m));
                origin.push(a);
            }
            Err(e) => refused.push((&a.topic, Refusal::new(e.reason, e.message))),
        }
    }
    let outcomes = store.add_readings(&checked)?;
    for (topic, r) in &refused {
        mqtt.refuse(state, topic, r);
    }
    let m = &state.metrics;
    let mut stored = Vec::new();
    for (((field, reading), outcome), a) in checked.iter().zip(outcomes).zip(origin) {
        match outcome {
            ReadingOutcome::Stored => {
                m.measurements.inc();
                m.mqtt_ingest_seconds
                    .observe(a.received.elapsed().as_secs_f64());
                if reading.sensor.is_none() {
                    m.theta
                        .with_label_values(&[field.to_string().as_str()])
                        .set(reading.theta);
                }
                stored.push(*field);
            }
            ReadingOutcome::Duplicate => m.mqtt_duplicates.inc(),
            ReadingOutcome::Conflict(theta) => mqtt.refuse(
                state,
                &a.topic,
                &Refusal::new(
                    "conflict",
                    format!(
                        "field {field} already has θ = {theta} at {} from this sensor; this one \
                         says θ = {}",
                        reading.time.to_rfc3339(),
                        reading.theta
                    ),
                ),
            ),
            ReadingOutcome::NoField => mqtt.refuse(
                state,
                &a.topic,
                &Refusal::new("unknown-field", format!("field {field} is gone")),
            ),
        }
    }
    stored.sort_unstable();
    stored.dedup();
    Ok(stored)
}
