//! The real daemon polls its fields' forecast source (a local server
//! replaying Open-Meteo's documented format; nothing reaches the internet):
//! two fields at one location make one request, and the next cycle plans
//! with the provider's rain and ET0 and records which forecast it used.

mod common;

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use axum::Router;
use axum::extract::State;
use axum::http::Uri;
use axum::response::IntoResponse;
use chrono::{DateTime, TimeDelta, Timelike, Utc};
use common::{TOKEN, config, create_field, curl, json_of, problem, start};
use serde_json::{Value, json};

/// Open-Meteo's hourly answer in UTC (offset 0): each value is the sum over
/// the hour before its stamp; 0.25 mm rain and 0.1 mm ET0 every hour, from
/// three hours ago for three days.
fn answer_body(now: DateTime<Utc>) -> Value {
    let first = now
        .with_minute(0)
        .unwrap()
        .with_second(0)
        .unwrap()
        .with_nanosecond(0)
        .unwrap()
        - TimeDelta::hours(3);
    let n = 72;
    let times: Vec<String> = (0..n)
        .map(|i| {
            (first + TimeDelta::hours(i))
                .format("%Y-%m-%dT%H:%M")
                .to_string()
        })
        .collect();
    json!({
        "latitude": 52.52, "longitude": 13.42, "generationtime_ms": 0.2,
        "utc_offset_seconds": 0, "timezone": "GMT", "timezone_abbreviation": "GMT",
        "elevation": 38.0,
        "hourly_units": {"time": "iso8601", "et0_fao_evapotranspiration": "mm", "precipitation": "mm"},
        "hourly": {
            "time": times,
            "et0_fao_evapotranspiration": vec![0.1; n as usize],
            "precipitation": vec![0.25; n as usize],
        }
    })
}

type Seen = Arc<Mutex<Vec<String>>>;

async fn replay(State((seen, body)): State<(Seen, Value)>, uri: Uri) -> impl IntoResponse {
    seen.lock()
        .unwrap()
        .push(format!("{}?{}", uri.path(), uri.query().unwrap_or("")));
    (
        [
            ("content-type", "application/json"),
            ("last-modified", "Mon, 01 Jun 2026 00:00:00 GMT"),
        ],
        body.to_string(),
    )
}

#[test]
fn the_daemon_polls_one_request_per_location_and_its_cycle_records_the_forecast() {
    let runtime = tokio::runtime::Runtime::new().unwrap();
    let seen: Seen = Arc::default();
    let listener = runtime
        .block_on(tokio::net::TcpListener::bind("127.0.0.1:0"))
        .unwrap();
    let base = format!("http://{}", listener.local_addr().unwrap());
    let app = Router::new()
        .fallback(replay)
        .with_state((seen.clone(), answer_body(Utc::now())));
    runtime.spawn(async move { axum::serve(listener, app).await.unwrap() });

    let dir = tempfile::tempdir().unwrap();
    // a poll tick of one second (retry_s) so the test need not wait
    let d = start(
        dir.path(),
        &config("[forecasts]\ncontact = \"test@example.org\"\nretry_s = 1.0\n"),
    );
    let mut ids = Vec::new();
    for (name, lat) in [("north", 52.521), ("south", 52.5204)] {
        let body = json!({
            "name": name,
            "model": "two-layer",
            "forecast_source": {
                "provider": "open-meteo", "latitude": lat, "longitude": 13.42,
                "base_url": base,
            }
        });
        ids.push(create_field(&d, body));
    }
    // both fields round to the same location (2 decimals): one request
    let deadline = Instant::now() + Duration::from_secs(30);
    while seen.lock().unwrap().is_empty() {
        assert!(Instant::now() < deadline, "the daemon never polled");
        std::thread::sleep(Duration::from_millis(100));
    }
    std::thread::sleep(Duration::from_millis(1500));
    let requests = seen.lock().unwrap().clone();
    assert_eq!(requests.len(), 1, "{requests:?}");
    assert!(requests[0].starts_with("/v1/forecast?"), "{requests:?}");
    assert!(requests[0].contains("latitude=52.52"), "{requests:?}");
    for id in ids {
        let fp = format!("/v1/fields/{id}");
        let readings = json!([{"time": Utc::now().to_rfc3339(), "theta": 0.2}]);
        let r = curl(
            &d,
            "POST",
            &format!("{fp}/measurements"),
            Some(&readings.to_string()),
            Some(TOKEN),
        );
        assert_eq!(r.0, 201, "{}", r.2);
        let r = curl(&d, "POST", &format!("{fp}/control"), None, Some(TOKEN));
        assert_eq!(r.0, 200, "{}", r.2);
        let sp = json_of(&r.2);
        assert_eq!(sp["forecast"]["source"], "open-meteo", "{sp}");
        assert!(sp["forecast"]["fetched_at"].is_string(), "{sp}");
        let degraded = sp["degraded"].as_array().unwrap();
        assert!(
            !degraded
                .iter()
                .any(|f| f == "default-forecast" || f == "stale-forecast"),
            "{sp}"
        );
        // the provider's hourly amounts, summed into 2-h control periods
        let rain = sp["rain_mm"].as_array().unwrap();
        let et0 = sp["et0_mm"].as_array().unwrap();
        assert_eq!(rain.len(), 20, "{sp}");
        for (r, e) in rain.iter().zip(et0) {
            assert!((r.as_f64().unwrap() - 0.5).abs() < 1e-9, "{sp}");
            assert!((e.as_f64().unwrap() - 0.2).abs() < 1e-9, "{sp}");
        }
        assert!(
            sp["explanation"]
                .as_str()
                .unwrap()
                .contains("10.0 mm rain, 4.0 mm ET0 (open-meteo)"),
            "{sp}"
        );
    }
}

/// PATCH is a merge patch (openapi.yaml, FieldPatch): a field's forecast
/// source takes the keys a patch names and keeps the others, and a patch
/// that leaves a source without a required key is refused, naming it,
/// with the field as it was.
#[test]
fn a_patch_merges_into_the_forecast_source_key_by_key() {
    let dir = tempfile::tempdir().unwrap();
    let d = start(dir.path(), &config(""));
    let body = json!({
        "name": "with-source",
        "model": "two-layer",
        "forecast_source": {
            "provider": "open-meteo", "latitude": 52.52, "longitude": 13.42,
            "base_url": "http://127.0.0.1:9",
        }
    });
    let with = create_field(&d, body);
    let without = create_field(&d, json!({"name": "without", "model": "two-layer"}));

    let patch_field = |id: i64, patch: &Value| {
        curl(
            &d,
            "PATCH",
            &format!("/v1/fields/{id}"),
            Some(&patch.to_string()),
            Some(TOKEN),
        )
    };
    let source_of = |id: i64| {
        let r = curl(&d, "GET", &format!("/v1/fields/{id}"), None, Some(TOKEN));
        assert_eq!(r.0, 200, "{}", r.2);
        json_of(&r.2).get("forecast_source").cloned()
    };

    let patch = json!({"forecast_source": {"latitude": -33.9, "provider": "met-norway"}});
    let r = patch_field(with, &patch);
    assert_eq!(r.0, 200, "{}", r.2);
    let source = json_of(&r.2)["forecast_source"].clone();
    assert_eq!(source["latitude"], -33.9, "{source}");
    assert_eq!(source["provider"], "met-norway", "{source}");
    assert_eq!(source["longitude"], 13.42, "{source}");
    assert_eq!(source["base_url"], "http://127.0.0.1:9", "{source}");

    // the same patch leaves a field without a source without a longitude
    problem(patch_field(without, &patch), 422, "longitude");
    // and removing a required key is refused too, the source kept
    let removal = json!({"forecast_source": {"longitude": null}});
    problem(patch_field(with, &removal), 422, "longitude");
    assert_eq!(source_of(with), Some(source));
    assert_eq!(source_of(without), None);
}
