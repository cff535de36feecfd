//! Several sensors per field (issue 16, part 1): declared with depth, noise
//! and calibration, named by measurements, read by simulated plants at their
//! depths; the single-sensor API keeps working with the primary sensor.

mod common;
use common::*;

use serde_json::{Value, json};

fn post(d: &Daemon, path: &str, body: &Value) -> (u16, String, String) {
    curl(d, "POST", path, Some(&body.to_string()), Some(TOKEN))
}

#[test]
fn measurements_name_their_sensor_and_raw_readings_are_calibrated() {
    let dir = tempfile::tempdir().unwrap();
    let d = start(dir.path(), &config(""));
    let sensors = json!([
        {"id": "s10", "depth": 0.10},
        {"id": "s30", "depth": 0.30, "noise": 0.01,
         "calibration": {"kind": "linear", "slope": 0.001, "offset": -0.1}},
        {"id": "s45", "depth": 0.45,
         "calibration": {"kind": "table", "points": [[100, 0.05], [300, 0.25], [500, 0.40]]}}
    ]);
    let id = create_field(&d, json!({"name": "f", "sensors": sensors}));
    let path = format!("/v1/fields/{id}/measurements");
    let t = now_minus(10);
    let batch = json!([
        {"time": t, "theta": 0.21},                     // the primary sensor, s10
        {"time": t, "raw": 350.0, "sensor": "s30"},     // 0.001·350 − 0.1 = 0.25
        {"time": t, "raw": 400.0, "sensor": "s45"}      // halfway 0.25 … 0.40
    ]);
    let r = post(&d, &path, &batch);
    assert_eq!(r.0, 201, "{}", r.2);
    assert_eq!(json_of(&r.2)["stored"], 3);
    let stored = json_of(&curl(&d, "GET", &path, None, None).2);
    let of = |sensor: Option<&str>| {
        stored
            .as_array()
            .unwrap()
            .iter()
            .find(|m| m["sensor"].as_str() == sensor)
            .cloned()
            .unwrap_or_else(|| panic!("{sensor:?} in {stored}"))
    };
    assert_eq!(of(None)["theta"], 0.21);
    assert!((of(Some("s30"))["theta"].as_f64().unwrap() - 0.25).abs() < 1e-12);
    assert_eq!(of(Some("s30"))["raw"], 350.0);
    assert!((of(Some("s45"))["theta"].as_f64().unwrap() - 0.325).abs() < 1e-12);

    // bad input, each naming what is wrong
    for (body, needle) in [
        (json!({"time": t, "theta": 0.2, "sensor": "nope"}), "nope"),
        (json!({"time": t, "raw": 350.0}), "no calibration"),
        (
            json!({"time": t, "raw": 900.0, "sensor": "s45"}),
            "outside the calibration",
        ),
        (
            json!({"time": t, "raw": 350.0, "theta": 0.2, "sensor": "s30"}),
            "give one",
        ),
        (json!({"time": t, "sensor": "s30"}), "theta or raw"),
    ] {
        problem(post(&d, &path, &body), 422, needle);
    }
    for (sensors, needle) in [
        (json!([{"id": "deep", "depth": 0.8}]), "below the column"),
        (
            json!([{"id": "a", "depth": 0.1}, {"id": "a", "depth": 0.2}]),
            "twice",
        ),
        (
            json!([{"id": "t", "depth": 0.1, "calibration": {"kind": "table",
                "points": [[100, 0.05], [300, 0.30], [500, 0.20]]}}]),
            "monotone",
        ),
        (
            json!([{"id": "l", "depth": 0.1, "calibration": {"kind": "linear",
                "slope": 0.0, "offset": 0.1}}]),
            "monotone",
        ),
    ] {
        problem(
            post(
                &d,
                "/v1/fields",
                &json!({"name": "bad", "sensors": sensors}),
            ),
            422,
            needle,
        );
    }
}

#[test]
fn a_simulated_plant_reads_every_sensor_at_its_depth() {
    let dir = tempfile::tempdir().unwrap();
    let d = start(dir.path(), &config(""));
    let id = create_field(
        &d,
        json!({"name": "sim", "actuator": {"kind": "simulated"},
                "simulation": {"initial_head": -0.5, "measurement_noise": 0.0},
                "sensors": [{"id": "root", "depth": 0.13}, {"id": "deep", "depth": 0.40}]}),
    );
    let stored = json_of(
        &curl(
            &d,
            "GET",
            &format!("/v1/fields/{id}/measurements"),
            None,
            None,
        )
        .2,
    );
    let all = stored.as_array().unwrap();
    // the first reading of both sensors, at the start: a uniform head, so
    // both read θ(−0.5 m) of sandy loam (Carsel & Parrish: θr 0.065, θs 0.41,
    // α 7.5 1/m, n 1.89), without noise
    let expected = {
        let (r, s, a, n) = (0.065, 0.41, 7.5_f64, 1.89_f64);
        r + (s - r) * (1.0 + (a * 0.5).powf(n)).powf(-(1.0 - 1.0 / n))
    };
    let primary: Vec<&Value> = all.iter().filter(|m| m["sensor"].is_null()).collect();
    let deep: Vec<&Value> = all.iter().filter(|m| m["sensor"] == "deep").collect();
    assert!(!primary.is_empty() && !deep.is_empty(), "{stored}");
    for m in [primary[0], deep[0]] {
        assert!(
            (m["theta"].as_f64().unwrap() - expected).abs() < 1e-9,
            "{m}"
        );
    }
}

#[test]
fn the_daemon_estimates_the_state_and_soil_from_the_readings_alone() {
    let dir = tempfile::tempdir().unwrap();
    let d = start(dir.path(), &config(""));
    let id = create_field(
        &d,
        json!({"name": "est", "model": "richards", "soil": "loam",
                "sensors": [{"id": "root", "depth": 0.13}, {"id": "deep", "depth": 0.35}]}),
    );
    let path = format!("/v1/fields/{id}");
    // before any reading: no estimate
    let e = json_of(&curl(&d, "GET", &format!("{path}/estimate"), None, None).2);
    assert_eq!(e["estimated"], false, "{e}");
    // readings of both sensors over two hours, then a cycle
    let batch: Vec<Value> = (0..5)
        .flat_map(|k| {
            let t = now_minus(120 - 30 * k);
            [
                json!({"time": t, "theta": 0.30}),
                json!({"time": t, "theta": 0.32, "sensor": "deep"}),
            ]
        })
        .collect();
    let r = post(&d, &format!("{path}/measurements"), &Value::from(batch));
    assert_eq!(r.0, 201, "{}", r.2);
    let r = curl(&d, "POST", &format!("{path}/control"), None, Some(TOKEN));
    assert_eq!(r.0, 200, "{}", r.2);
    let e = json_of(&curl(&d, "GET", &format!("{path}/estimate"), None, None).2);
    assert_eq!(e["estimated"], true, "{e}");
    let profile = e["profile"].as_array().unwrap();
    assert_eq!(profile.len(), 26);
    // the estimate follows the readings at the sensors' depths, with a band
    let at = |depth: f64| {
        profile
            .iter()
            .min_by(|a, b| {
                let da = (a["depth"].as_f64().unwrap() - depth).abs();
                let db = (b["depth"].as_f64().unwrap() - depth).abs();
                da.partial_cmp(&db).unwrap()
            })
            .unwrap()
            .clone()
    };
    let root = at(0.125);
    assert!(
        (root["theta"].as_f64().unwrap() - 0.30).abs() < 0.03,
        "{root}"
    );
    assert!(root["theta_sd"].as_f64().unwrap() > 0.0, "{root}");
    assert!(root["low"].as_f64() < root["high"].as_f64());
    let params = e["parameters"].as_array().unwrap();
    assert!(params.len() >= 5, "{e}");
    for p in params {
        assert!(
            p["mean"].as_f64().unwrap().is_finite() && p["sd"].as_f64().unwrap() >= 0.0,
            "{p}"
        );
    }
    assert!(!e["innovations"].as_array().unwrap().is_empty(), "{e}");
}

#[test]
fn a_field_of_unknown_soil_is_controlled_on_the_soil_its_estimate_finds() {
    let dir = tempfile::tempdir().unwrap();
    // one clock hour per real second
    let d = start(dir.path(), &config("[clock]\nspeedup = 3600.0"));
    // the plant is a loam; the controller is told nothing about it
    let r = post(
        &d,
        "/v1/fields",
        &json!({"name": "new ground", "soil": "unknown", "model": "richards",
                "zone": {"low_head": -0.43, "up_head": -0.27},
                "actuator": {"kind": "simulated"},
                "simulation": {"soil": "loam", "measurement_noise": 0.01,
                               "measurement_interval_s": 1800, "initial_head": -0.3}}),
    );
    assert_eq!(r.0, 201, "{}", r.2);
    let field = json_of(&r.2);
    let id = field["id"].as_i64().unwrap();
    assert_eq!(field["soil"], "unknown");
    assert_eq!(field["simulation"]["soil"], "loam");
    // a soil the estimate cannot start from is refused, naming the key
    let r = post(
        &d,
        "/v1/fields",
        &json!({"name": "x", "soil": "unknown", "actuator": {"kind": "simulated"},
                "model": "richards", "simulation": {}}),
    );
    problem(r, 422, "simulation.soil");
    // wait for cycles over about 14 h of clock time
    let path = format!("/v1/fields/{id}");
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(60);
    let setpoints = loop {
        let s = json_of(&curl(&d, "GET", &format!("{path}/setpoints"), None, None).2);
        if s.as_array().is_some_and(|a| a.len() >= 8) {
            break s;
        }
        assert!(std::time::Instant::now() < deadline, "no cycles: {s}");
        std::thread::sleep(std::time::Duration::from_millis(250));
    };
    let e = json_of(&curl(&d, "GET", &format!("{path}/estimate"), None, None).2);
    assert_eq!(e["estimated"], true, "{e}");
    assert_eq!(e["prior"], "unknown", "{e}");
    // the estimated θ at the sensor follows the plant's true θ there
    let truth = json_of(&curl(&d, "GET", &format!("{path}/simulation"), None, None).2);
    let true_profile: Vec<f64> = truth["theta_profile"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    assert_eq!(true_profile.len(), 26);
    let profile = e["profile"].as_array().unwrap();
    let cell = (0.13_f64 / (0.5 / 26.0)).floor() as usize;
    let estimated = profile[cell]["theta"].as_f64().unwrap();
    assert!(
        (estimated - true_profile[cell]).abs() < 0.02,
        "estimate {estimated} against truth {}",
        true_profile[cell]
    );
    // the zone of the setpoints is the head band on the estimated soil, not
    // on the nominal one: it differs from cycle to cycle as the soil is learnt
    // and lies inside the estimated soil's [θr, θs]
    let zones: Vec<f64> = setpoints
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["zone"][0][0].as_f64().unwrap())
        .collect();
    assert!(
        zones.windows(2).any(|w| (w[0] - w[1]).abs() > 1e-9),
        "{zones:?}"
    );
    for s in setpoints.as_array().unwrap() {
        assert_ne!(s["status"], "fallback", "{s}");
        let rate = s["rate"].as_f64().unwrap();
        assert!((0.0..=1e-5).contains(&rate), "{s}");
    }
}
