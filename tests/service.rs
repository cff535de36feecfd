//! The daemon end to end: the real `rootzone serve` on an ephemeral port with
//! a temporary data directory, driven with curl.

use std::time::{Duration, Instant};

use serde_json::{Value, json};

mod common;
use common::*;

const EXTERNAL_FIELD: &str = r#"{"name": "north", "model": "two-layer"}"#;

#[test]
fn api_stores_controls_and_rejects_bad_input() {
    let dir = tempfile::tempdir().unwrap();
    let d = start(dir.path(), &config(""));
    assert_eq!(curl(&d, "GET", "/healthz", None, None).0, 200);
    assert_eq!(curl(&d, "GET", "/readyz", None, None).0, 200);

    // auth: 401 without, 403 with a wrong token
    problem(
        curl(&d, "POST", "/v1/fields", Some(EXTERNAL_FIELD), None),
        401,
        "Bearer",
    );
    problem(
        curl(
            &d,
            "POST",
            "/v1/fields",
            Some(EXTERNAL_FIELD),
            Some("wrong-token"),
        ),
        403,
        "token",
    );
    let r = curl(&d, "POST", "/v1/fields", Some(EXTERNAL_FIELD), Some(TOKEN));
    assert_eq!(r.0, 201, "{}", r.2);
    let field = json_of(&r.2);
    let id = field["id"].as_i64().unwrap();
    // the zone in force, in both forms (sandy loam: [0.18, 0.23], heads
    // about −0.43 … −0.27 m)
    assert_eq!(field["effective_zone"]["low"], 0.18);
    assert_eq!(field["effective_zone"]["up"], 0.23);
    let head = field["effective_zone"]["low_head"].as_f64().unwrap();
    assert!((head + 0.43).abs() < 0.01, "{head}");
    let fp = format!("/v1/fields/{id}");

    // measurements: one, then a batch of twelve over the last two days
    let one = json!({"time": now_minus(1), "theta": 0.2}).to_string();
    assert_eq!(
        curl(
            &d,
            "POST",
            &format!("{fp}/measurements"),
            Some(&one),
            Some(TOKEN)
        )
        .0,
        201
    );
    let batch: Vec<Value> = (1..=12)
        .map(|k| json!({"time": now_minus(240 * k), "theta": 0.2 + 0.002 * k as f64}))
        .collect();
    let r = curl(
        &d,
        "POST",
        &format!("{fp}/measurements"),
        Some(&Value::from(batch).to_string()),
        Some(TOKEN),
    );
    assert_eq!(
        (r.0, json_of(&r.2)["stored"].as_i64()),
        (201, Some(12)),
        "{}",
        r.2
    );
    let all = json_of(
        &curl(
            &d,
            "GET",
            &format!("{fp}/measurements?limit=100"),
            None,
            None,
        )
        .2,
    );
    assert_eq!(all.as_array().unwrap().len(), 13);
    let some = json_of(
        &curl(
            &d,
            "GET",
            &format!(
                "{fp}/measurements?from={}&limit=3",
                now_minus(24 * 60).replace('+', "%2B")
            ),
            None,
            None,
        )
        .2,
    );
    assert_eq!(some.as_array().unwrap().len(), 3);

    // a forecast, then a control cycle
    let forecast = json!({"issued_at": now_minus(5), "start": now_minus(5), "step_s": 3600.0,
        "et0_mm": vec![0.2; 48], "precip_mm": vec![0.0; 48]})
    .to_string();
    assert_eq!(
        curl(
            &d,
            "PUT",
            &format!("{fp}/forecast"),
            Some(&forecast),
            Some(TOKEN)
        )
        .0,
        200
    );
    assert_eq!(
        json_of(&curl(&d, "GET", &format!("{fp}/forecast"), None, None).2)["step_s"],
        3600.0
    );
    // the first cycle ran when the field was created, before any
    // measurement: a setpoint exists at once, flagged
    let first = curl(&d, "GET", &format!("{fp}/setpoint"), None, None);
    assert_eq!(first.0, 200, "{}", first.2);
    let first = json_of(&first.2);
    assert!(
        first["degraded"]
            .as_array()
            .unwrap()
            .contains(&json!("no-measurement")),
        "{first}"
    );
    let r = curl(&d, "POST", &format!("{fp}/control"), None, Some(TOKEN));
    assert_eq!(r.0, 200, "{}", r.2);
    let sp = json_of(&r.2);
    let rate = sp["rate"].as_f64().unwrap();
    assert!((0.0..=1e-5).contains(&rate), "{rate}");
    assert_eq!(sp["plan"].as_array().unwrap().len(), 20);
    assert_eq!(sp["predicted_theta"].as_array().unwrap().len(), 20);
    assert!((sp["amount_mm"].as_f64().unwrap() - rate * 7200.0 * 1000.0).abs() < 1e-9);
    assert!(sp["degraded"].as_array().unwrap().is_empty(), "{sp}");
    assert_eq!(
        json_of(&curl(&d, "GET", &format!("{fp}/setpoint"), None, None).2),
        sp
    );
    let history = json_of(&curl(&d, "GET", &format!("{fp}/setpoints"), None, None).2);
    assert_eq!(
        history.as_array().unwrap().len(),
        2,
        "the first cycle and this one"
    );

    // bad input: each a problem+json naming the value, nothing stored
    let post = |body: &str| {
        curl(
            &d,
            "POST",
            &format!("{fp}/measurements"),
            Some(body),
            Some(TOKEN),
        )
    };
    problem(post("{\"time\": "), 400, "JSON");
    problem(
        post(&json!({"time": now_minus(1), "theta": 0.2, "depth": 3}).to_string()),
        422,
        "no other keys",
    );
    problem(
        post(&json!({"time": now_minus(1), "theta": 1.5}).to_string()),
        422,
        "1.5",
    );
    problem(
        post(&json!({"time": "yesterday noon", "theta": 0.2}).to_string()),
        422,
        "yesterday noon",
    );
    let future = (chrono::Utc::now() + chrono::TimeDelta::hours(3)).to_rfc3339();
    problem(
        post(&json!({"time": future, "theta": 0.2}).to_string()),
        422,
        "future",
    );
    let half_bad =
        json!([{"time": now_minus(2), "theta": 0.21}, {"time": now_minus(3), "theta": -0.1}]);
    problem(post(&half_bad.to_string()), 422, "measurements[1].theta");
    let too_many: Vec<Value> = (0..51)
        .map(|k| json!({"time": now_minus(k), "theta": 0.2}))
        .collect();
    problem(post(&Value::from(too_many).to_string()), 413, "at most 50");
    let huge = format!(
        "[{}]",
        vec![json!({"time": now_minus(1), "theta": 0.2}).to_string(); 30_000].join(",")
    );
    problem(post(&huge), 413, "exceeds");
    assert_eq!(
        json_of(
            &curl(
                &d,
                "GET",
                &format!("{fp}/measurements?limit=1000"),
                None,
                None
            )
            .2
        )
        .as_array()
        .unwrap()
        .len(),
        13
    );
    problem(
        curl(&d, "GET", "/v1/fields/999/setpoint", None, None),
        404,
        "999",
    );
    problem(
        curl(
            &d,
            "POST",
            "/v1/fields/abc/measurements",
            Some(&one),
            Some(TOKEN),
        ),
        404,
        "abc",
    );
    let put = |body: String| {
        curl(
            &d,
            "PUT",
            &format!("{fp}/forecast"),
            Some(&body),
            Some(TOKEN),
        )
    };
    let mismatched = json!({"issued_at": now_minus(1), "start": now_minus(1), "step_s": 3600.0, "et0_mm": [0.1, 0.2], "precip_mm": [0.0]});
    problem(put(mismatched.to_string()), 422, "precip_mm has 1");
    let negative = json!({"issued_at": now_minus(1), "start": now_minus(1), "step_s": 3600.0, "et0_mm": [0.1, 0.2], "precip_mm": [0.0, -2.0]});
    problem(put(negative.to_string()), 422, "precip_mm[1] = -2");
    problem(
        curl(
            &d,
            "POST",
            "/v1/fields",
            Some(
                r#"{"name": "x", "zone": {"low": 0.3, "up": 0.2, "terminal_low": 0.3, "terminal_up": 0.2, "mu": 0}}"#,
            ),
            Some(TOKEN),
        ),
        422,
        "zone",
    );
    problem(
        curl(
            &d,
            "POST",
            "/v1/fields",
            Some(r#"{"name": "x", "soil": "clay"}"#),
            Some(TOKEN),
        ),
        422,
        "richards",
    );
    problem(
        curl(
            &d,
            "POST",
            "/v1/fields",
            Some(r#"{"name": "x", "measurement_wait_s": -1}"#),
            Some(TOKEN),
        ),
        422,
        "measurement_wait_s",
    );

    // a resent measurement is stored once
    let r = curl(
        &d,
        "POST",
        &format!("{fp}/measurements"),
        Some(&one),
        Some(TOKEN),
    );
    assert_eq!(json_of(&r.2)["duplicates"], 1, "{}", r.2);
    // degraded modes: no measurement and no forecast
    let other = json_of(
        &curl(
            &d,
            "POST",
            "/v1/fields",
            Some(r#"{"name": "empty"}"#),
            Some(TOKEN),
        )
        .2,
    );
    let r = curl(
        &d,
        "POST",
        &format!("/v1/fields/{}/control", other["id"]),
        None,
        Some(TOKEN),
    );
    let sp = json_of(&r.2);
    assert_eq!(
        (sp["status"].as_str(), sp["rate"].as_f64()),
        (Some("fallback"), Some(0.0)),
        "{sp}"
    );
    let flags: Vec<&str> = sp["degraded"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(|v| v.as_str())
        .collect();
    for flag in ["no-measurement", "default-forecast", "solver-fallback"] {
        assert!(flags.contains(&flag), "{flags:?}");
    }
    assert!(sp.get("predicted_next").is_none(), "{sp}");
    // a measurement arrives: the next cycle reads the fallback back and runs
    let op = format!("/v1/fields/{}", other["id"]);
    let one = json!({"time": now_minus(1), "theta": 0.2}).to_string();
    let r = curl(
        &d,
        "POST",
        &format!("{op}/measurements"),
        Some(&one),
        Some(TOKEN),
    );
    assert_eq!(r.0, 201, "{}", r.2);
    let r = curl(&d, "POST", &format!("{op}/control"), None, Some(TOKEN));
    assert_eq!(r.0, 200, "{}", r.2);
    let sp = json_of(&r.2);
    assert_ne!(sp["status"], "fallback", "{sp}");
    assert!(sp["predicted_next"].as_f64().is_some(), "{sp}");
    assert!(sp["measured_at"].is_string(), "{sp}");
    let history = json_of(&curl(&d, "GET", &format!("{op}/setpoints"), None, None).2);
    // the first cycle at creation, then the two asked for
    assert_eq!(history.as_array().unwrap().len(), 3, "{history}");

    // patch and delete
    let r = curl(
        &d,
        "PATCH",
        &fp,
        Some(r#"{"zone": {"mu": 1.0, "terminal_low": 0.2, "terminal_up": 0.21}}"#),
        Some(TOKEN),
    );
    assert_eq!(r.0, 200, "{}", r.2);
    assert_eq!(json_of(&r.2)["zone"]["mu"], 1.0);
    // a key no field has, even as a no-op removal, and a key the actuator
    // kind does not have: refused, the field unchanged (schemathesis found
    // both answered 200)
    problem(
        curl(&d, "PATCH", &fp, Some(r#"{"": null}"#), Some(TOKEN)),
        422,
        "no such key",
    );
    problem(
        curl(
            &d,
            "PATCH",
            &fp,
            Some(r#"{"actuator": {"url": ""}}"#),
            Some(TOKEN),
        ),
        422,
        "actuator.url",
    );
    let now = json_of(&curl(&d, "GET", &fp, None, None).2);
    assert_eq!(now["zone"]["mu"], 1.0, "{now}");
    let metrics = curl(&d, "GET", "/metrics", None, None).2;
    assert!(
        metrics.contains("rootzone_measurements_ingested_total 14"),
        "{metrics}"
    );
    assert!(
        // the two first cycles at creation and one asked for before a measurement
        metrics.contains("rootzone_degraded_cycles_total{flag=\"no-measurement\"} 3"),
        "{metrics}"
    );
    let cycles: f64 = metrics
        .lines()
        .filter(|l| l.starts_with("rootzone_control_cycles_total{"))
        .filter_map(|l| l.split_whitespace().last()?.parse::<f64>().ok())
        .sum();
    assert_eq!(
        cycles, 5.0,
        "two first cycles and three asked for: {metrics}"
    );
    assert_eq!(curl(&d, "DELETE", &fp, None, Some(TOKEN)).0, 204);
    problem(curl(&d, "GET", &fp, None, None), 404, &id.to_string());
}

#[test]
fn acknowledged_data_survives_kill_9_and_a_restart() {
    let dir = tempfile::tempdir().unwrap();
    let d = start(dir.path(), &config(""));
    let id = json_of(&curl(&d, "POST", "/v1/fields", Some(EXTERNAL_FIELD), Some(TOKEN)).2)["id"]
        .as_i64()
        .unwrap();
    let fp = format!("/v1/fields/{id}");
    for k in 0..20 {
        let m = json!({"time": now_minus(100 - k), "theta": 0.19}).to_string();
        assert_eq!(
            curl(
                &d,
                "POST",
                &format!("{fp}/measurements"),
                Some(&m),
                Some(TOKEN)
            )
            .0,
            201
        );
    }
    let sp = json_of(&curl(&d, "POST", &format!("{fp}/control"), None, Some(TOKEN)).2);
    drop(d); // SIGKILL
    let mut d = start(dir.path(), &config(""));
    let stored = json_of(&curl(&d, "GET", &format!("{fp}/measurements"), None, None).2);
    assert_eq!(stored.as_array().unwrap().len(), 20);
    // the acknowledged setpoint is kept (the restart's first cycle adds one)
    let all = json_of(&curl(&d, "GET", &format!("{fp}/setpoints"), None, None).2);
    assert!(all.as_array().unwrap().contains(&sp), "{all}");
    // SIGTERM: a clean stop
    d.sigterm();
    let deadline = Instant::now() + Duration::from_secs(20);
    let status = loop {
        if let Some(status) = d.child.try_wait().unwrap() {
            break status;
        }
        assert!(Instant::now() < deadline, "no exit after SIGTERM");
        std::thread::sleep(Duration::from_millis(50));
    };
    assert!(status.success(), "{status:?}");
}

#[test]
fn an_accelerated_simulated_field_moves_into_its_zone_over_a_day() {
    let dir = tempfile::tempdir().unwrap();
    // 2 h of clock time per real second; the field starts wetter than the zone
    let d = start(
        dir.path(),
        &format!(
            "{}\n[clock]\nspeedup = 7200.0\n",
            r#"
[[fields]]
name = "sim"
model = "two-layer"
actuator = { kind = "simulated" }
[fields.simulation]
scenario = "dry"
measurement_noise = 0.02
process_noise = 0.0
forecast_error = 0.2
seed = 5
measurement_interval_s = 900.0
initial_head = -0.2
"#
        )
        .replace("fields = []", ""),
    );
    let start_state = json_of(&curl(&d, "GET", "/v1/fields/1/simulation", None, None).2);
    let theta0 = start_state["theta"].as_f64().unwrap();
    assert!(theta0 > 0.25, "{theta0}");
    let t0 = chrono::DateTime::parse_from_rfc3339(start_state["time"].as_str().unwrap()).unwrap();
    let deadline = Instant::now() + Duration::from_secs(90);
    let state = loop {
        let s = json_of(&curl(&d, "GET", "/v1/fields/1/simulation", None, None).2);
        let t = chrono::DateTime::parse_from_rfc3339(s["time"].as_str().unwrap()).unwrap();
        if t - t0 >= chrono::TimeDelta::hours(26) {
            break s;
        }
        assert!(Instant::now() < deadline, "the simulated day did not pass");
        std::thread::sleep(Duration::from_millis(200));
    };
    let theta = state["theta"].as_f64().unwrap();
    let setpoints = json_of(&curl(&d, "GET", "/v1/fields/1/setpoints?limit=1000", None, None).2);
    let setpoints = setpoints.as_array().unwrap();
    assert!(
        setpoints.len() >= 11,
        "{} cycles in a simulated day",
        setpoints.len()
    );
    for s in setpoints {
        let rate = s["rate"].as_f64().unwrap();
        assert!((0.0..=1e-5).contains(&rate), "{s}");
        assert_ne!(s["status"], "fallback", "{s}");
    }
    // from 0.27 the field dries into the zone and is held there
    assert!(
        (0.175..=0.235).contains(&theta),
        "θ {theta} after a day (from {theta0})"
    );
    let measured = json_of(
        &curl(
            &d,
            "GET",
            "/v1/fields/1/measurements?limit=100000",
            None,
            None,
        )
        .2,
    );
    assert!(measured.as_array().unwrap().len() >= 100);
}

/// A field whose cycles cannot finish within their solve budget (a clay
/// field under the Richards model, dry: its trial plans pond the surface)
/// gets a setpoint that says how its solve ended, does not hold up another
/// field's cycle, and does not hold up SIGTERM.
#[test]
fn a_field_that_cannot_finish_blocks_neither_others_nor_shutdown() {
    let dir = tempfile::tempdir().unwrap();
    let mut d = start(dir.path(), &config(""));
    let stuck = create_field(
        &d,
        json!({"name": "clay", "model": "richards", "soil": "clay"}),
    );
    let other = create_field(&d, json!({"name": "sandy", "model": "two-layer"}));
    for (id, theta) in [(stuck, 0.30), (other, 0.20)] {
        let m = format!(r#"{{"time": "{}", "theta": {theta}}}"#, now_minus(1));
        let r = curl(
            &d,
            "POST",
            &format!("/v1/fields/{id}/measurements"),
            Some(&m),
            Some(TOKEN),
        );
        assert_eq!(r.0, 201, "{}", r.2);
    }
    let base = d.base.clone();
    let slow = std::thread::spawn(move || {
        let path = format!("/v1/fields/{stuck}/control");
        curl_at(&base, "POST", &path, None, Some(TOKEN))
    });
    // the other field's cycle is answered while the stuck one still runs
    let r = curl(
        &d,
        "POST",
        &format!("/v1/fields/{other}/control"),
        None,
        Some(TOKEN),
    );
    assert_eq!(r.0, 200, "{}", r.2);
    assert!(
        !slow.is_finished(),
        "the other field's cycle waited for the stuck one"
    );
    let r = slow.join().unwrap();
    assert_eq!(r.0, 200, "{}", r.2);
    let setpoint = json_of(&r.2);
    let status = setpoint["status"].as_str().unwrap();
    assert!(
        [
            "work-budget",
            "time-budget",
            "fallback",
            "converged",
            "iteration-cap"
        ]
        .contains(&status),
        "{setpoint}"
    );
    // the solve ran into its work budget (60,000 Newton iterations) or, on
    // a machine too loaded for that, its 2-s time budget, no further than
    // one sampling step
    let solve_ms = setpoint["solve_ms"].as_f64().unwrap();
    assert!(solve_ms > 100.0 && solve_ms < 3_000.0, "{setpoint}");
    if status == "fallback" {
        assert!(setpoint["fallback_reason"].as_str().is_some(), "{setpoint}");
    }
    // SIGTERM while the stuck field's next cycle runs: a clean exit soon
    let base = d.base.clone();
    let again = std::thread::spawn(move || {
        let path = format!("/v1/fields/{stuck}/control");
        curl_at(&base, "POST", &path, None, Some(TOKEN))
    });
    std::thread::sleep(Duration::from_millis(200));
    let sent = Instant::now();
    d.sigterm();
    let deadline = sent + Duration::from_secs(8);
    loop {
        if let Some(status) = d.child.try_wait().unwrap() {
            assert!(status.success(), "{status:?}");
            break;
        }
        assert!(Instant::now() < deadline, "no exit within 8 s of SIGTERM");
        std::thread::sleep(Duration::from_millis(50));
    }
    let _ = again.join();
}
