//! MQTT with Home Assistant discovery (issue 18): the settings, the topic
//! scheme, the parsing of sensor payloads and the documents the daemon
//! publishes, all pure here; [`client`] runs the connection (rumqttc) and
//! the ingest. README.md § MQTT documents the topics for users.
//!
//! Topics, under `mqtt.topic_prefix` (`P`, default `rootzone`) and
//! `mqtt.discovery_prefix` (`D`, default `homeassistant`):
//!
//! - `P/fields/{field id}/sensors/{sensor id}` in: one reading, a plain
//!   number or JSON `{"theta": 0.21}` / `{"raw": 512}` with an optional
//!   `"time"` (RFC 3339; default: the daemon's clock at arrival). A plain
//!   number is the sensor's raw reading when the sensor declares a
//!   calibration, else θ [m³/m³].
//! - `P/fields/{field id}/valve/command` out, retained: the valve schedule
//!   of the latest setpoint ([`valve_command`]).
//! - `P/fields/{field id}/state` out, retained: measured and estimated θ,
//!   the next irrigation, the status ([`field_state`]).
//! - `P/status` out, retained: `online`, and `offline` as the last will.
//! - `D/sensor/{node}_{field id}_{key}/config` and
//!   `D/valve/{node}_{field id}/config` out, retained: discovery.
//! - `D/status` in: Home Assistant's birth message; on `online` the
//!   discovery and the states are published again.

pub mod client;

use chrono::{DateTime, Utc};
use serde::{Deserialize, Serialize};

use crate::service::wire::{Setpoint, check_range};

/// Largest MQTT packet the client reads [bytes]. A larger one cannot be
/// read at all (the connection drops and the broker sends it again): keep
/// the broker's `message_size_limit` at or below it.
pub const MAX_PACKET_BYTES: usize = 1 << 20;

/// The `[mqtt]` settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MqttSettings {
    /// The broker, `mqtt://host:port` (or `tcp://`; port default 1883).
    /// Unset (the default): no MQTT.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub url: Option<String>,
    /// The fixed client id of the persistent session, 1 to 64 letters,
    /// digits or `-_.` (default `rootzone`); also the discovery node id.
    pub client_id: String,
    /// Credentials (at most 200 characters each; a password needs a user).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub username: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub password: Option<String>,
    /// Prefix of the daemon's own topics (default `rootzone`).
    pub topic_prefix: String,
    /// Publish Home Assistant discovery (default true).
    pub discovery: bool,
    /// Prefix of the discovery topics (default `homeassistant`).
    pub discovery_prefix: String,
    /// Keep-alive [s], in [5, 3600] (default 30).
    #[serde(deserialize_with = "crate::service::settings::lenient_f64")]
    pub keep_alive_s: f64,
    /// First wait after a failed connection [s], doubled per failure, in
    /// [0.1, 60] (default 1).
    #[serde(deserialize_with = "crate::service::settings::lenient_f64")]
    pub reconnect_min_s: f64,
    /// Longest wait between connection attempts [s], in
    /// [reconnect_min_s, 600] (default 30).
    #[serde(deserialize_with = "crate::service::settings::lenient_f64")]
    pub reconnect_max_s: f64,
    /// Largest sensor payload [bytes], in [64, 65536] (default 4096);
    /// larger ones are refused and counted.
    pub max_payload_bytes: usize,
    /// Readings waiting for storage, in [1, 100000] (default 10000); when
    /// it is full the client stops reading from the broker (which keeps
    /// the messages of the persistent session) until there is room.
    pub queue: usize,
    /// Most readings stored in one transaction, in [1, 10000] (default
    /// 1000).
    pub batch_max: usize,
}

impl Default for MqttSettings {
    fn default() -> Self {
        MqttSettings {
            url: None,
            client_id: "rootzone".into(),
            username: None,
            password: None,
            topic_prefix: "rootzone".into(),
            discovery: true,
            discovery_prefix: "homeassistant".into(),
            keep_alive_s: 30.0,
            reconnect_min_s: 1.0,
            reconnect_max_s: 30.0,
            max_payload_bytes: 4096,
            queue: 10_000,
            batch_max: 1000,
        }
    }
}

/// A broker address from `mqtt.url`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Broker {
    pub host: String,
    pub port: u16,
}

/// `mqtt://host:port` or `tcp://host:port` (port default 1883); no TLS,
/// credentials, path or query.
pub fn parse_broker(text: &str) -> Result<Broker, String> {
    let bad = |why: &str| Err(format!("mqtt.url = '{text}' {why}"));
    let url = match url::Url::parse(text) {
        Ok(u) => u,
        Err(e) => return bad(&format!("is not a URL ({e}); e.g. mqtt://127.0.0.1:1883")),
    };
    match url.scheme() {
        "mqtt" | "tcp" => {}
        "mqtts" | "ssl" => return bad("asks for TLS, which this build does not speak"),
        s => return bad(&format!("has the scheme '{s}'; use mqtt://host:port")),
    }
    if !url.username().is_empty() || url.password().is_some() {
        return bad("carries credentials; set mqtt.username and mqtt.password instead");
    }
    if !matches!(url.path(), "" | "/") || url.query().is_some() || url.fragment().is_some() {
        return bad("has a path or query; give mqtt://host:port only");
    }
    let Some(host) = url.host_str().filter(|h| !h.is_empty()) else {
        return bad("names no host");
    };
    let host = host
        .trim_start_matches('[')
        .trim_end_matches(']')
        .to_string();
    Ok(Broker {
        host,
        port: url.port().unwrap_or(1883),
    })
}

/// A topic prefix: 1 to 100 characters, levels separated by `/`, none
/// empty, no wildcard (`+`, `#`), no NUL, not starting with `$`.
fn check_prefix(key: &str, p: &str) -> Result<(), String> {
    let ok = (1..=100).contains(&p.chars().count())
        && !p.starts_with('$')
        && p.split('/').all(|level| !level.is_empty())
        && !p
            .chars()
            .any(|c| c == '+' || c == '#' || c == '\0' || c.is_control());
    if ok {
        Ok(())
    } else {
        Err(format!(
            "{key} = '{p}' must have 1 to 100 characters in non-empty levels separated by /, \
             without +, #, control characters or a leading $"
        ))
    }
}

impl MqttSettings {
    pub fn validate(&self) -> Result<(), String> {
        if let Some(url) = &self.url {
            parse_broker(url)?;
        }
        let id_ok = (1..=64).contains(&self.client_id.len())
            && self
                .client_id
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || "-_.".contains(c));
        if !id_ok {
            return Err(format!(
                "mqtt.client_id = '{}' must have 1 to 64 letters, digits or -_.",
                self.client_id
            ));
        }
        for (key, v) in [("username", &self.username), ("password", &self.password)] {
            if let Some(v) = v
                && (v.chars().count() > 200 || v.chars().any(|c| c.is_control()))
            {
                return Err(format!(
                    "mqtt.{key} must have at most 200 characters, none a control character"
                ));
            }
        }
        if self.password.is_some() && self.username.is_none() {
            return Err("mqtt.password is set without mqtt.username".into());
        }
        check_prefix("mqtt.topic_prefix", &self.topic_prefix)?;
        check_prefix("mqtt.discovery_prefix", &self.discovery_prefix)?;
        check_range("mqtt.keep_alive_s", self.keep_alive_s, (5.0, 3600.0))?;
        check_range("mqtt.reconnect_min_s", self.reconnect_min_s, (0.1, 60.0))?;
        check_range(
            "mqtt.reconnect_max_s",
            self.reconnect_max_s,
            (self.reconnect_min_s, 600.0),
        )?;
        for (key, v, (lo, hi)) in [
            ("max_payload_bytes", self.max_payload_bytes, (64, 65_536)),
            ("queue", self.queue, (1, 100_000)),
            ("batch_max", self.batch_max, (1, 10_000)),
        ] {
            if !(lo..=hi).contains(&v) {
                return Err(format!("mqtt.{key} = {v} must lie in [{lo}, {hi}]"));
            }
        }
        Ok(())
    }

    /// The discovery node id: the client id with `.` as `_`.
    pub fn node_id(&self) -> String {
        self.client_id.replace('.', "_")
    }
}

/// The topic scheme.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Topics {
    prefix: String,
    discovery: String,
    node: String,
}

/// A sensor topic's field and sensor.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SensorTopic {
    pub field: i64,
    pub sensor: String,
}

/// The discovery keys of a field's sensor entities, with their names and
/// units.
pub const SENSOR_KEYS: [(&str, &str, Option<&str>); 4] = [
    ("measured_theta", "measured water content", Some("m³/m³")),
    ("estimated_theta", "estimated water content", Some("m³/m³")),
    ("next_irrigation", "next irrigation", Some("mm")),
    ("status", "controller status", None),
];

impl Topics {
    pub fn new(settings: &MqttSettings) -> Topics {
        Topics {
            prefix: settings.topic_prefix.clone(),
            discovery: settings.discovery_prefix.clone(),
            node: settings.node_id(),
        }
    }

    /// The one subscription of every sensor of every field.
    pub fn sensor_filter(&self) -> String {
        format!("{}/fields/+/sensors/#", self.prefix)
    }

    pub fn sensor(&self, field: i64, sensor: &str) -> String {
        format!("{}/fields/{field}/sensors/{sensor}", self.prefix)
    }

    pub fn valve_command(&self, field: i64) -> String {
        format!("{}/fields/{field}/valve/command", self.prefix)
    }

    pub fn state(&self, field: i64) -> String {
        format!("{}/fields/{field}/state", self.prefix)
    }

    /// The daemon's availability (`online`, last will `offline`).
    pub fn availability(&self) -> String {
        format!("{}/status", self.prefix)
    }

    /// Home Assistant's birth and last-will topic.
    pub fn ha_status(&self) -> String {
        format!("{}/status", self.discovery)
    }

    pub fn discovery_sensor(&self, field: i64, key: &str) -> String {
        format!(
            "{}/sensor/{}_{field}_{key}/config",
            self.discovery, self.node
        )
    }

    pub fn discovery_valve(&self, field: i64) -> String {
        format!("{}/valve/{}_{field}/config", self.discovery, self.node)
    }

    /// Every retained topic of a field (cleared when it is deleted).
    pub fn retained_of(&self, field: i64, discovery: bool) -> Vec<String> {
        let mut topics = vec![self.valve_command(field), self.state(field)];
        if discovery {
            topics.extend(
                SENSOR_KEYS
                    .iter()
                    .map(|(k, _, _)| self.discovery_sensor(field, k)),
            );
            topics.push(self.discovery_valve(field));
        }
        topics
    }

    /// The field and sensor of a sensor topic, or why it is not one: the
    /// field id a positive integer in decimal, the sensor id 1 to 64
    /// letters, digits or `-._/` (the rest of the topic).
    pub fn parse_sensor(&self, topic: &str) -> Result<SensorTopic, String> {
        let rest = topic
            .strip_prefix(self.prefix.as_str())
            .and_then(|r| r.strip_prefix("/fields/"))
            .ok_or_else(|| format!("'{topic}' is not under {}/fields/", self.prefix))?;
        let (id, rest) = rest
            .split_once('/')
            .ok_or_else(|| format!("'{topic}' names no sensor"))?;
        let field = (!id.is_empty() && id.len() <= 18 && id.bytes().all(|b| b.is_ascii_digit()))
            .then(|| id.parse::<i64>().ok())
            .flatten()
            .filter(|&n| n > 0)
            .ok_or_else(|| format!("'{topic}': the field id '{id}' is not a positive integer"))?;
        let sensor = rest
            .strip_prefix("sensors/")
            .ok_or_else(|| format!("'{topic}' is not …/fields/{{id}}/sensors/{{sensor}}"))?;
        let ok = (1..=64).contains(&sensor.chars().count())
            && sensor
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || "-._/".contains(c));
        if !ok {
            return Err(format!(
                "'{topic}': the sensor id must have 1 to 64 letters, digits or -._/"
            ));
        }
        Ok(SensorTopic {
            field,
            sensor: sensor.to_string(),
        })
    }
}

/// A sensor payload.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Payload {
    /// A plain number: raw when the sensor has a calibration, else θ.
    Plain(f64),
    /// JSON: θ or raw, and a time.
    Json {
        theta: Option<f64>,
        raw: Option<f64>,
        time: Option<DateTime<Utc>>,
    },
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct JsonPayload {
    #[serde(default, deserialize_with = "number")]
    theta: Option<f64>,
    #[serde(default, deserialize_with = "number")]
    raw: Option<f64>,
    #[serde(default)]
    time: Option<String>,
}

/// A number that may be left out but not given as null.
fn number<'de, D: serde::Deserializer<'de>>(d: D) -> Result<Option<f64>, D::Error> {
    f64::deserialize(d).map(Some)
}

/// Why a payload was refused: a reason (metrics label) and a message.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Refusal {
    /// too-large, payload, time, retained (and, from the daemon's check, topic,
    /// unknown-field, unknown-sensor, value, range, calibration, conflict).
    pub reason: &'static str,
    pub message: String,
}

impl Refusal {
    pub fn new(reason: &'static str, message: impl Into<String>) -> Refusal {
        Refusal {
            reason,
            message: message.into(),
        }
    }
}

/// Parses a sensor payload of at most `max_bytes`: UTF-8, a plain number
/// (JSON number syntax, surrounding white space allowed) or a JSON object
/// with `theta` or `raw` (numbers) and optionally `time` (RFC 3339), no
/// other keys.
pub fn parse_payload(bytes: &[u8], max_bytes: usize) -> Result<Payload, Refusal> {
    if bytes.len() > max_bytes {
        return Err(Refusal::new(
            "too-large",
            format!("the payload has {} bytes; at most {max_bytes}", bytes.len()),
        ));
    }
    let text = std::str::from_utf8(bytes)
        .map_err(|_| Refusal::new("payload", "the payload is not UTF-8"))?
        .trim();
    let value: serde_json::Value = serde_json::from_str(text).map_err(|_| {
        Refusal::new(
            "payload",
            format!(
                "'{}' is neither a number nor a JSON object",
                text.chars().take(80).collect::<String>()
            ),
        )
    })?;
    match value {
        serde_json::Value::Number(n) => n
            .as_f64()
            .filter(|v| v.is_finite())
            .map(Payload::Plain)
            .ok_or_else(|| Refusal::new("payload", format!("{n} is not a finite number"))),
        serde_json::Value::Object(_) => {
            let p: JsonPayload = serde_json::from_value(value).map_err(|e| {
                Refusal::new(
                    "payload",
                    format!("a JSON payload is {{theta | raw, time?}} with numbers ({e})"),
                )
            })?;
            let time = p
                .time
                .map(|t| {
                    DateTime::parse_from_rfc3339(&t)
                        .map(|t| t.to_utc())
                        .map_err(|e| {
                            Refusal::new(
                                "time",
                                format!("time = '{t}' is not an RFC 3339 timestamp ({e})"),
                            )
                        })
                })
                .transpose()?;
            Ok(Payload::Json {
                theta: p.theta,
                raw: p.raw,
                time,
            })
        }
        _ => Err(Refusal::new(
            "payload",
            "a payload is a number or a JSON object",
        )),
    }
}

impl Payload {
    /// (θ, raw, time): a plain number is raw for a calibrated sensor, else
    /// θ; a missing time is `arrived`.
    pub fn values(
        self,
        calibrated: bool,
        arrived: DateTime<Utc>,
    ) -> (Option<f64>, Option<f64>, DateTime<Utc>) {
        match self {
            Payload::Plain(v) if calibrated => (None, Some(v), arrived),
            Payload::Plain(v) => (Some(v), None, arrived),
            Payload::Json { theta, raw, time } => (theta, raw, time.unwrap_or(arrived)),
        }
    }
}

/// The valve command of a setpoint: when it applies, the rate and amount,
/// and, for a field with an `irrigation_system`, valve minutes, litres,
/// m³, the pulses (start offset after `valid_from` [s], minutes) and the
/// soak between them [min] (null without one). A receiver applies a
/// command once per (`field_id`, `valid_from`): the daemon publishes the
/// retained command again after every reconnect.
pub fn valve_command(sp: &Setpoint) -> serde_json::Value {
    let v = sp.valve.as_ref();
    serde_json::json!({
        "field_id": sp.field_id,
        "valid_from": sp.valid_from,
        "valid_until": sp.valid_until,
        "rate_m_s": sp.rate,
        "amount_mm": sp.amount_mm,
        "minutes": v.map(|v| v.valve_minutes),
        "litres": v.map(|v| v.litres),
        "volume_m3": v.map(|v| v.volume_m3),
        "pulses": v.map(|v| v.pulses.iter().map(|p| serde_json::json!({
            "start_offset_s": p.start_offset_s,
            "minutes": p.minutes,
        })).collect::<Vec<_>>()).unwrap_or_default(),
        "soak_minutes": v.map(|v| v.soak_minutes),
        "status": sp.status,
    })
}

/// What a field's state document says.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct FieldState<'a> {
    /// The latest reading of the primary sensor: θ and its time.
    pub measured: Option<(f64, DateTime<Utc>)>,
    /// The state estimate's θ at the primary sensor's depth.
    pub estimated_theta: Option<f64>,
    pub setpoint: Option<&'a Setpoint>,
}

/// The retained state document: `measured_theta`, `measured_at`,
/// `estimated_theta` [m³/m³], `next_irrigation_mm` (the current period's
/// amount) from `next_irrigation_at` to `next_irrigation_until`, `valve`
/// (`open` while the current period has water to apply, else `closed`),
/// `status` (the solver status of the latest cycle, or `waiting` before
/// the first) and `degraded` (its flags). Absent values are null.
pub fn field_state(s: &FieldState<'_>) -> serde_json::Value {
    let sp = s.setpoint;
    let open = sp.is_some_and(|sp| sp.amount_mm > 0.0);
    serde_json::json!({
        "measured_theta": s.measured.map(|m| m.0),
        "measured_at": s.measured.map(|m| m.1),
        "estimated_theta": s.estimated_theta,
        "next_irrigation_mm": sp.map(|sp| sp.amount_mm),
        "next_irrigation_at": sp.map(|sp| sp.valid_from),
        "next_irrigation_until": sp.map(|sp| sp.valid_until),
        "valve": if open { "open" } else { "closed" },
        "status": sp.map(|sp| sp.status.as_str()).unwrap_or("waiting"),
        "degraded": sp.map(|sp| sp.degraded.clone()).unwrap_or_default(),
    })
}

/// The discovery documents of a field (topic, retained JSON): a sensor
/// entity per [`SENSOR_KEYS`] and a valve entity, all reading the field's
/// state topic, with the daemon's availability. The valve has no command
/// topic: Home Assistant shows it and cannot move it (rootzone decides).
pub fn discovery(topics: &Topics, field: i64, name: &str) -> Vec<(String, serde_json::Value)> {
    let device = serde_json::json!({
        "identifiers": [format!("{}_field_{field}", topics.node)],
        "name": format!("rootzone {name}"),
        "manufacturer": "rootzone",
        "model": "closed-loop irrigation field",
        "sw_version": env!("CARGO_PKG_VERSION"),
    });
    let common = |doc: &mut serde_json::Value| {
        doc["availability_topic"] = topics.availability().into();
        doc["payload_available"] = "online".into();
        doc["payload_not_available"] = "offline".into();
        doc["state_topic"] = topics.state(field).into();
        doc["device"] = device.clone();
    };
    let mut docs = Vec::new();
    for (key, label, unit) in SENSOR_KEYS {
        let value = match key {
            "next_irrigation" => "next_irrigation_mm",
            k => k,
        };
        let mut doc = serde_json::json!({
            "name": label,
            "unique_id": format!("{}_{field}_{key}", topics.node),
            "value_template": format!("{{{{ value_json.{value} }}}}"),
        });
        if let Some(unit) = unit {
            doc["unit_of_measurement"] = unit.into();
            doc["state_class"] = "measurement".into();
        }
        common(&mut doc);
        docs.push((topics.discovery_sensor(field, key), doc));
    }
    let mut valve = serde_json::json!({
        "name": "valve",
        "unique_id": format!("{}_{field}_valve", topics.node),
        "device_class": "water",
        "value_template": "{{ value_json.valve }}",
        "state_open": "open",
        "state_closed": "closed",
        "reports_position": false,
    });
    common(&mut valve);
    docs.push((topics.discovery_valve(field), valve));
    docs
}

#[cfg(test)]
mod tests {
    use super::*;

    fn topics() -> Topics {
        Topics::new(&MqttSettings::default())
    }

    #[test]
    fn sensor_topics_name_a_field_and_a_sensor_or_are_refused() {
        let t = topics();
        assert_eq!(t.sensor_filter(), "rootzone/fields/+/sensors/#");
        assert_eq!(
            t.parse_sensor("rootzone/fields/12/sensors/probe-1"),
            Ok(SensorTopic {
                field: 12,
                sensor: "probe-1".into()
            })
        );
        // a sensor id may hold '/', as the API allows
        assert_eq!(
            t.parse_sensor("rootzone/fields/3/sensors/row2/deep")
                .unwrap(),
            SensorTopic {
                field: 3,
                sensor: "row2/deep".into()
            }
        );
        assert_eq!(
            t.parse_sensor(&t.sensor(7, "a.b")).unwrap(),
            SensorTopic {
                field: 7,
                sensor: "a.b".into()
            }
        );
        for bad in [
            "rootzone/fields/0/sensors/a",
            "rootzone/fields/-1/sensors/a",
            "rootzone/fields/+1/sensors/a",
            "rootzone/fields/x/sensors/a",
            "rootzone/fields/99999999999999999999/sensors/a",
            "rootzone/fields/1/sensors/",
            "rootzone/fields/1/sensors/a b",
            "rootzone/fields/1/valve/command",
            "rootzone/fields/1",
            "other/fields/1/sensors/a",
            "rootzonex/fields/1/sensors/a",
        ] {
            assert!(t.parse_sensor(bad).is_err(), "{bad} should be refused");
        }
        let long = format!("rootzone/fields/1/sensors/{}", "a".repeat(65));
        assert!(t.parse_sensor(&long).is_err());
    }

    #[test]
    fn payloads_are_numbers_or_objects_within_the_size_limit() {
        assert_eq!(parse_payload(b"0.21", 4096), Ok(Payload::Plain(0.21)));
        assert_eq!(parse_payload(b" 512\n", 4096), Ok(Payload::Plain(512.0)));
        assert_eq!(parse_payload(b"1e-1", 4096), Ok(Payload::Plain(0.1)));
        assert_eq!(
            parse_payload(br#"{"theta": 0.25}"#, 4096),
            Ok(Payload::Json {
                theta: Some(0.25),
                raw: None,
                time: None
            })
        );
        let t: DateTime<Utc> = "2026-05-01T10:00:00Z".parse().unwrap();
        assert_eq!(
            parse_payload(
                br#"{"raw": 400, "time": "2026-05-01T12:00:00+02:00"}"#,
                4096
            ),
            Ok(Payload::Json {
                theta: None,
                raw: Some(400.0),
                time: Some(t)
            })
        );
        let refused = |b: &[u8]| parse_payload(b, 4096).unwrap_err().reason;
        for bad in [
            &b"abc"[..],
            b"",
            b"NaN",
            b"inf",
            b"0.2 0.3",
            b"[0.2]",
            b"\"0.2\"",
            b"true",
            b"null",
            br#"{"theta": null}"#,
            br#"{"theta": "0.2"}"#,
            br#"{"theta": 0.2, "extra": 1}"#,
            b"\xff\xfe",
        ] {
            assert_eq!(
                refused(bad),
                "payload",
                "{:?}",
                String::from_utf8_lossy(bad)
            );
        }
        assert_eq!(refused(br#"{"theta": 0.2, "time": "noon"}"#), "time");
        // the limit is on bytes, checked before anything is parsed
        let big = format!("{{\"theta\": 0.2{}}}", " ".repeat(100));
        assert_eq!(
            parse_payload(big.as_bytes(), 64).unwrap_err().reason,
            "too-large"
        );
        assert!(parse_payload(big.as_bytes(), big.len()).is_ok());
    }

    #[test]
    fn a_plain_number_is_raw_only_for_a_calibrated_sensor() {
        let now: DateTime<Utc> = "2026-05-01T10:00:00Z".parse().unwrap();
        assert_eq!(
            Payload::Plain(0.2).values(false, now),
            (Some(0.2), None, now)
        );
        assert_eq!(
            Payload::Plain(512.0).values(true, now),
            (None, Some(512.0), now)
        );
        let t: DateTime<Utc> = "2026-05-01T09:00:00Z".parse().unwrap();
        let json = Payload::Json {
            theta: Some(0.3),
            raw: None,
            time: Some(t),
        };
        // JSON says what it is whatever the sensor
        assert_eq!(json.values(true, now), (Some(0.3), None, t));
    }

    #[test]
    fn settings_are_checked_with_their_ranges() {
        let ok = MqttSettings {
            url: Some("mqtt://127.0.0.1:18830".into()),
            ..MqttSettings::default()
        };
        assert_eq!(ok.validate(), Ok(()));
        assert_eq!(MqttSettings::default().validate(), Ok(()));
        assert_eq!(
            parse_broker("mqtt://broker.local").unwrap(),
            Broker {
                host: "broker.local".into(),
                port: 1883
            }
        );
        assert_eq!(parse_broker("tcp://[::1]:1884").unwrap().host, "::1");
        for (s, key) in [
            (
                MqttSettings {
                    url: Some("http://x:1".into()),
                    ..Default::default()
                },
                "scheme",
            ),
            (
                MqttSettings {
                    url: Some("mqtts://x:8883".into()),
                    ..Default::default()
                },
                "TLS",
            ),
            (
                MqttSettings {
                    url: Some("mqtt://u:p@x:1".into()),
                    ..Default::default()
                },
                "credentials",
            ),
            (
                MqttSettings {
                    url: Some("mqtt://x:1/a".into()),
                    ..Default::default()
                },
                "path",
            ),
            (
                MqttSettings {
                    client_id: "".into(),
                    ..Default::default()
                },
                "client_id",
            ),
            (
                MqttSettings {
                    client_id: "a b".into(),
                    ..Default::default()
                },
                "client_id",
            ),
            (
                MqttSettings {
                    topic_prefix: "a/+/b".into(),
                    ..Default::default()
                },
                "topic_prefix",
            ),
            (
                MqttSettings {
                    topic_prefix: "a//b".into(),
                    ..Default::default()
                },
                "topic_prefix",
            ),
            (
                MqttSettings {
                    discovery_prefix: "$SYS".into(),
                    ..Default::default()
                },
                "discovery_prefix",
            ),
            (
                MqttSettings {
                    keep_alive_s: 1.0,
                    ..Default::default()
                },
                "keep_alive_s",
            ),
            (
                MqttSettings {
                    reconnect_min_s: 5.0,
                    reconnect_max_s: 2.0,
                    ..Default::default()
                },
                "reconnect_max_s",
            ),
            (
                MqttSettings {
                    max_payload_bytes: 10,
                    ..Default::default()
                },
                "max_payload_bytes",
            ),
            (
                MqttSettings {
                    queue: 0,
                    ..Default::default()
                },
                "queue",
            ),
            (
                MqttSettings {
                    batch_max: 20_000,
                    ..Default::default()
                },
                "batch_max",
            ),
            (
                MqttSettings {
                    password: Some("p".into()),
                    ..Default::default()
                },
                "password",
            ),
        ] {
            let e = s.validate().unwrap_err();
            assert!(e.contains(key), "'{e}' should name {key}");
        }
    }

    fn setpoint(valve: Option<serde_json::Value>) -> Setpoint {
        let mut doc = serde_json::json!({
            "field_id": 3, "time": "2026-05-01T10:00:00Z",
            "valid_from": "2026-05-01T10:00:00Z", "valid_until": "2026-05-01T12:00:00Z",
            "rate": 2.5e-7, "amount_mm": 1.8, "plan": [2.5e-7], "predicted_theta": [0.2],
            "zone": [[0.18, 0.23]], "model": "richards", "status": "converged",
            "iterations": 4, "solve_ms": 12.0, "degraded": ["default-forecast"], "bias": 0.0
        });
        if let Some(v) = valve {
            doc["valve"] = v;
        }
        serde_json::from_value(doc).unwrap()
    }

    #[test]
    fn the_valve_command_carries_the_schedule_and_the_state_its_values() {
        let valve = serde_json::json!({
            "valve_minutes": 5.4, "litres": 1800.0, "volume_m3": 1.8, "applied_mm": 1.8,
            "pulses": [{"start_offset_s": 0.0, "minutes": 2.7},
                       {"start_offset_s": 3600.0, "minutes": 2.7}],
            "soak_minutes": 57.3
        });
        let sp = setpoint(Some(valve));
        let c = valve_command(&sp);
        assert_eq!(c["field_id"], 3);
        assert_eq!(c["valid_from"], "2026-05-01T10:00:00Z");
        assert_eq!(c["rate_m_s"], 2.5e-7);
        assert_eq!(c["amount_mm"], 1.8);
        assert_eq!(c["minutes"], 5.4);
        assert_eq!(c["litres"], 1800.0);
        assert_eq!(c["volume_m3"], 1.8);
        assert_eq!(c["soak_minutes"], 57.3);
        assert_eq!(c["pulses"][1]["start_offset_s"], 3600.0);
        assert_eq!(c["pulses"].as_array().unwrap().len(), 2);
        // no irrigation system: the rate and amount only
        let bare = valve_command(&setpoint(None));
        assert!(bare["minutes"].is_null() && bare["litres"].is_null());
        assert_eq!(bare["pulses"], serde_json::json!([]));

        let t: DateTime<Utc> = "2026-05-01T09:55:00Z".parse().unwrap();
        let doc = field_state(&FieldState {
            measured: Some((0.17, t)),
            estimated_theta: Some(0.175),
            setpoint: Some(&sp),
        });
        assert_eq!(doc["measured_theta"], 0.17);
        assert_eq!(doc["measured_at"], "2026-05-01T09:55:00Z");
        assert_eq!(doc["estimated_theta"], 0.175);
        assert_eq!(doc["next_irrigation_mm"], 1.8);
        assert_eq!(doc["valve"], "open");
        assert_eq!(doc["status"], "converged");
        assert_eq!(doc["degraded"][0], "default-forecast");
        let dry = Setpoint {
            amount_mm: 0.0,
            ..sp.clone()
        };
        let doc = field_state(&FieldState {
            setpoint: Some(&dry),
            ..Default::default()
        });
        assert_eq!(doc["valve"], "closed");
        assert!(doc["measured_theta"].is_null());
        let none = field_state(&FieldState::default());
        assert_eq!(none["status"], "waiting");
        assert!(none["next_irrigation_mm"].is_null());
    }

    #[test]
    fn discovery_documents_read_the_state_topic_and_name_the_device() {
        let t = topics();
        let docs = discovery(&t, 4, "orchard");
        assert_eq!(docs.len(), 5);
        let topics_out: Vec<&str> = docs.iter().map(|(t, _)| t.as_str()).collect();
        assert_eq!(
            topics_out,
            [
                "homeassistant/sensor/rootzone_4_measured_theta/config",
                "homeassistant/sensor/rootzone_4_estimated_theta/config",
                "homeassistant/sensor/rootzone_4_next_irrigation/config",
                "homeassistant/sensor/rootzone_4_status/config",
                "homeassistant/valve/rootzone_4/config",
            ]
        );
        for (_, doc) in &docs {
            assert_eq!(doc["state_topic"], "rootzone/fields/4/state");
            assert_eq!(doc["availability_topic"], "rootzone/status");
            assert_eq!(doc["device"]["identifiers"][0], "rootzone_field_4");
            assert_eq!(doc["device"]["name"], "rootzone orchard");
            assert!(doc.get("command_topic").is_none(), "read-only: {doc}");
        }
        assert_eq!(
            docs[2].1["value_template"],
            "{{ value_json.next_irrigation_mm }}"
        );
        assert_eq!(docs[4].1["value_template"], "{{ value_json.valve }}");
        let mut unique: Vec<&str> = docs
            .iter()
            .map(|(_, d)| d["unique_id"].as_str().unwrap())
            .collect();
        unique.sort();
        unique.dedup();
        assert_eq!(unique.len(), 5);
        assert_eq!(t.retained_of(4, true).len(), 7);
        assert_eq!(t.retained_of(4, false).len(), 2);
    }
}
