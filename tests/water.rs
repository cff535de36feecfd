//! Valve run times, water accounts and the history export (issue 18), on
//! the real daemon over HTTP.

mod common;

use common::{TOKEN, config, create_field, curl, json_of, now_minus, problem, start};
use serde_json::json;

#[test]
fn setpoints_carry_valve_time_and_the_water_is_accounted_and_exported() {
    let dir = tempfile::tempdir().unwrap();
    let d = start(dir.path(), &config(""));
    // bad hardware is refused naming the key
    for (system, key) in [
        (
            json!({"area_m2": 0.0, "application_rate_mm_h": 10.0}),
            "area_m2",
        ),
        (
            json!({"area_m2": -3.0, "application_rate_mm_h": 10.0}),
            "area_m2",
        ),
        (
            json!({"area_m2": 100.0, "application_rate_mm_h": 0.0}),
            "application_rate_mm_h",
        ),
        (
            json!({"area_m2": 100.0, "application_rate_mm_h": -2.0}),
            "application_rate_mm_h",
        ),
    ] {
        let body = json!({"name": "bad", "model": "richards", "irrigation_system": system});
        problem(
            curl(
                &d,
                "POST",
                "/v1/fields",
                Some(&body.to_string()),
                Some(TOKEN),
            ),
            422,
            key,
        );
    }
    let area = 2_000.0;
    let rate_mm_h = 80.0;
    let body = json!({
        "name": "orchard",
        "model": "richards",
        "irrigation_system": {"area_m2": area, "application_rate_mm_h": rate_mm_h}
    });
    let id = create_field(&d, body);
    let fp = format!("/v1/fields/{id}");
    // dry, below the zone: the controller irrigates
    let readings: Vec<_> = (0..6)
        .map(|i| json!({"time": now_minus(5 + 20 * i), "theta": 0.15 + 0.001 * i as f64}))
        .collect();
    let r = curl(
        &d,
        "POST",
        &format!("{fp}/measurements"),
        Some(&json!(readings).to_string()),
        Some(TOKEN),
    );
    assert_eq!(r.0, 201, "{}", r.2);
    let before = chrono::Utc::now();
    let r = curl(&d, "POST", &format!("{fp}/control"), None, Some(TOKEN));
    assert_eq!(r.0, 200, "{}", r.2);
    let sp = json_of(&r.2);
    let amount = sp["amount_mm"].as_f64().unwrap();
    assert!(amount > 0.0, "a dry field is irrigated: {sp}");
    let valve = &sp["valve"];
    let minutes = valve["valve_minutes"].as_f64().unwrap();
    assert!(
        (minutes - amount / rate_mm_h * 60.0).abs() < 1e-9,
        "{valve}"
    );
    let litres = valve["litres"].as_f64().unwrap();
    assert!((litres - amount * area).abs() < 1e-6 * litres, "{valve}");
    let pulses = valve["pulses"].as_array().unwrap();
    assert!(!pulses.is_empty());
    let total: f64 = pulses.iter().map(|p| p["minutes"].as_f64().unwrap()).sum();
    assert!((total - minutes).abs() < 1e-9);
    assert!(valve["predicted_runoff_mm"].as_f64().unwrap() >= 0.0);
    // the stored setpoint and the latest one carry the same schedule
    let r = curl(&d, "GET", &format!("{fp}/setpoint"), None, None);
    assert_eq!(json_of(&r.2)["valve"], *valve);

    // the day's water: the running setpoint's rate since it began
    let rate = sp["rate"].as_f64().unwrap();
    let from: chrono::DateTime<chrono::Utc> = sp["valid_from"].as_str().unwrap().parse().unwrap();
    std::thread::sleep(std::time::Duration::from_millis(300));
    let r = curl(&d, "GET", &format!("{fp}/water"), None, None);
    let after = chrono::Utc::now();
    assert_eq!(r.0, 200, "{}", r.2);
    let w = json_of(&r.2);
    let day = w["day"]["mm"].as_f64().unwrap();
    let lo = rate * (before - from).as_seconds_f64().max(0.0) * 1e3;
    let hi = rate * (after - from).as_seconds_f64() * 1e3;
    assert!(
        day > 0.0 && day >= lo - 1e-12 && day <= hi + 1e-12,
        "{day} in [{lo}, {hi}]"
    );
    assert!(w["week"]["mm"].as_f64().unwrap() >= day);
    assert!(w["season"]["mm"].as_f64().unwrap() >= w["week"]["mm"].as_f64().unwrap());
    let m3 = w["day"]["m3"].as_f64().unwrap();
    assert!((m3 - day * 1e-3 * area).abs() < 1e-9 * (1.0 + m3));

    // a second cycle replaces the first: its water is booked on the counter
    let r = curl(&d, "POST", &format!("{fp}/control"), None, Some(TOKEN));
    assert_eq!(r.0, 200, "{}", r.2);
    let replaced = chrono::Utc::now();
    let metrics = curl(&d, "GET", "/metrics", None, None).2;
    let line = metrics
        .lines()
        .find(|l| {
            l.starts_with(&format!(
                "rootzone_field_irrigation_mm_total{{field=\"{id}\"}}"
            ))
        })
        .unwrap_or_else(|| panic!("no water counter in\n{metrics}"));
    let booked: f64 = line.rsplit(' ').next().unwrap().parse().unwrap();
    let most = rate * (replaced - from).as_seconds_f64() * 1e3;
    assert!(
        booked >= day - 1e-12 && booked <= most + 1e-12,
        "{line}: [{day}, {most}]"
    );

    // the export: header, every measurement, both setpoints with a reason
    let r = curl(
        &d,
        "GET",
        &format!("{fp}/history.csv?from={}", urlencode(&now_minus(300))),
        None,
        None,
    );
    assert_eq!(r.0, 200, "{}", r.2);
    assert!(r.1.starts_with("text/csv"), "{}", r.1);
    let mut reader = csv::Reader::from_reader(r.2.as_bytes());
    let headers = reader.headers().unwrap().clone();
    assert_eq!(&headers[0], "record");
    assert_eq!(&headers[3], "theta");
    let rows: Vec<csv::StringRecord> = reader.records().map(|r| r.unwrap()).collect();
    let thetas: Vec<f64> = rows
        .iter()
        .filter(|r| &r[0] == "measurement")
        .map(|r| r[3].parse().unwrap())
        .collect();
    assert_eq!(thetas.len(), 6);
    // oldest first: the readings were posted newest first
    assert!((thetas[0] - 0.155).abs() < 1e-12 && (thetas[5] - 0.15).abs() < 1e-12);
    let setpoints: Vec<_> = rows.iter().filter(|r| &r[0] == "setpoint").collect();
    // the one at creation and the two asked for
    let stored = json_of(&curl(&d, "GET", &format!("{fp}/setpoints"), None, None).2);
    assert_eq!(setpoints.len(), stored.as_array().unwrap().len());
    assert_eq!(setpoints.len(), 3);
    assert!(
        setpoints
            .iter()
            .all(|r| r[8].starts_with("Irrigate ") && r[8].contains("optimiser: ")),
        "{setpoints:?}"
    );
    assert!(
        setpoints
            .iter()
            .any(|r| (r[5].parse::<f64>().unwrap() - amount).abs() < 1e-12)
    );
    // a range that ends before it starts holds nothing but the header
    let r = curl(
        &d,
        "GET",
        &format!(
            "{fp}/history.csv?from={}&to={}",
            urlencode(&now_minus(10)),
            urlencode(&now_minus(20))
        ),
        None,
        None,
    );
    assert_eq!(r.0, 200);
    assert_eq!(r.2.lines().count(), 1, "{}", r.2);
}

fn urlencode(s: &str) -> String {
    s.replace('+', "%2B").replace(':', "%3A")
}
