//! Forecast providers against a local HTTP server replaying responses
//! written here from each provider's documented format (nothing reaches
//! the internet): Open-Meteo with a time-zone offset, nulls and a
//! daylight-saving change, MET Norway with its six-hour tail and
//! Hargreaves ET0, one request per distinct source for 1,000 fields,
//! If-Modified-Since, backoff, staleness and refused responses.

use std::sync::{Arc, Mutex};

use axum::Router;
use axum::extract::State;
use axum::http::{HeaderMap, StatusCode, Uri};
use axum::response::{IntoResponse, Response};
use chrono::{DateTime, TimeDelta, Utc};
use serde_json::{Value, json};

use rootzone::adapters::forecast::{
    ForecastSettings, Poller, Provider, SourceSpec, SourceState, for_cycle,
};
use rootzone::service::store::Store;
use rootzone::service::wire::{Actuator, Field, FieldSpec, Forecast};

fn at(s: &str) -> DateTime<Utc> {
    DateTime::parse_from_rfc3339(s).unwrap().to_utc()
}

#[derive(Clone, Copy, PartialEq, Debug)]
enum Mode {
    Ok,
    Down,
    Garbage,
    Truncated,
    WrongUnits,
}

struct Seen {
    path: String,
    query: String,
    user_agent: String,
    if_modified_since: Option<String>,
}

struct Replay {
    open_meteo: Value,
    met: Value,
    mode: Mode,
    last_modified: &'static str,
    /// (Date, Expires) headers sent with every good answer.
    expires: Option<(&'static str, &'static str)>,
    seen: Vec<Seen>,
}

type Shared = Arc<Mutex<Replay>>;

async fn answer(State(s): State<Shared>, uri: Uri, headers: HeaderMap) -> Response {
    let mut r = s.lock().unwrap();
    let header = |n: &str| {
        headers
            .get(n)
            .and_then(|v| v.to_str().ok())
            .map(str::to_string)
    };
    let ims = header("if-modified-since");
    r.seen.push(Seen {
        path: uri.path().to_string(),
        query: uri.query().unwrap_or("").to_string(),
        user_agent: header("user-agent").unwrap_or_default(),
        if_modified_since: ims.clone(),
    });
    let mut body = match uri.path() {
        "/v1/forecast" => r.open_meteo.clone(),
        "/weatherapi/locationforecast/2.0/compact" => r.met.clone(),
        _ => return StatusCode::NOT_FOUND.into_response(),
    };
    match r.mode {
        Mode::Down => return StatusCode::SERVICE_UNAVAILABLE.into_response(),
        Mode::Garbage => return (StatusCode::OK, "<html>oops</html>").into_response(),
        Mode::Truncated => {
            let text = body.to_string();
            return (StatusCode::OK, text[..text.len() / 2].to_string()).into_response();
        }
        Mode::WrongUnits => {
            if uri.path() == "/v1/forecast" {
                body["hourly_units"]["precipitation"] = json!("inch");
            } else {
                body["properties"]["meta"]["units"]["air_temperature"] = json!("fahrenheit");
            }
        }
        Mode::Ok => {}
    }
    let mut validity = HeaderMap::new();
    if let Some((date, expires)) = r.expires {
        validity.insert("date", date.parse().unwrap());
        validity.insert("expires", expires.parse().unwrap());
    }
    // MET Norway honours If-Modified-Since; the replay does for both
    if ims.as_deref() == Some(r.last_modified) {
        return (StatusCode::NOT_MODIFIED, validity).into_response();
    }
    (
        StatusCode::OK,
        validity,
        [
            ("content-type", "application/json"),
            ("last-modified", r.last_modified),
        ],
        body.to_string(),
    )
        .into_response()
}

async fn serve(open_meteo: Value, met: Value) -> (String, Shared) {
    let shared = Arc::new(Mutex::new(Replay {
        open_meteo,
        met,
        mode: Mode::Ok,
        last_modified: "Mon, 01 Jun 2026 00:00:00 GMT",
        expires: None,
        seen: Vec::new(),
    }));
    let app = Router::new().fallback(answer).with_state(shared.clone());
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    tokio::spawn(async move { axum::serve(listener, app).await.unwrap() });
    (format!("http://{addr}"), shared)
}

fn settings() -> ForecastSettings {
    ForecastSettings {
        contact: "test@example.org".into(),
        ..ForecastSettings::default()
    }
}

fn field(store: &Store, name: &str, period: f64, source: SourceSpec) -> Field {
    let spec = FieldSpec {
        name: name.into(),
        actuator: Actuator::None,
        simulation: None,
        control_period_s: period,
        forecast_source: Some(source),
        ..FieldSpec::demo()
    };
    spec.validate().unwrap();
    store
        .create_field(&spec, at("2026-06-01T00:00:00Z"))
        .unwrap()
}

fn source(provider: Provider, base: &str, lat: f64, lon: f64) -> SourceSpec {
    SourceSpec {
        provider,
        latitude: lat,
        longitude: lon,
        base_url: Some(base.into()),
    }
}

/// Open-Meteo hourly data: `time` local stamps from `first` (hourly),
/// each value the sum over the hour before its stamp.
fn open_meteo(
    offset_s: i64,
    timezone: &str,
    times: Vec<String>,
    et0: Vec<Value>,
    precip: Vec<Value>,
) -> Value {
    json!({
        "latitude": 52.52, "longitude": 13.42, "generationtime_ms": 0.5,
        "utc_offset_seconds": offset_s, "timezone": timezone,
        "timezone_abbreviation": "X", "elevation": 38.0,
        "hourly_units": {"time": "iso8601", "et0_fao_evapotranspiration": "mm", "precipitation": "mm"},
        "hourly": {"time": times, "et0_fao_evapotranspiration": et0, "precipitation": precip}
    })
}

fn local_hours(first: &str, n: usize) -> Vec<String> {
    let t0 = chrono::NaiveDateTime::parse_from_str(first, "%Y-%m-%dT%H:%M").unwrap();
    (0..n)
        .map(|i| {
            (t0 + TimeDelta::hours(i as i64))
                .format("%Y-%m-%dT%H:%M")
                .to_string()
        })
        .collect()
}

async fn poll_one(
    base: &str,
    provider: Provider,
    lat: f64,
    lon: f64,
    period: f64,
    now: &str,
) -> Forecast {
    let dir = tempfile::tempdir().unwrap();
    let store = Arc::new(Store::open(dir.path()).unwrap());
    let f = field(&store, "one", period, source(provider, base, lat, lon));
    let poller = Poller::new(settings(), store.clone()).unwrap();
    let report = poller
        .poll(at(now), std::slice::from_ref(&f))
        .await
        .unwrap();
    assert_eq!(
        (report.requests, report.updated, report.failed),
        (1, 1, 0),
        "{report:?}"
    );
    store
        .latest_forecast(f.id)
        .unwrap()
        .expect("a stored forecast")
}

#[tokio::test]
async fn open_meteo_with_a_half_hour_offset_is_split_across_periods_by_hand() {
    rootzone::service::install_tls();
    // India, UTC+05:30: the stamp 2026-06-01T12:00 local ends the hour
    // [05:30, 06:30) UTC; its 1 mm falls half into [04:00, 06:00) and half
    // into [06:00, 08:00). ET0 0.1 mm every hour, 0.3 at stamp 09:00
    // (UTC [02:30, 03:30)).
    let times = local_hours("2026-06-01T00:00", 48);
    let et0: Vec<Value> = times
        .iter()
        .map(|t| json!(if t.ends_with("01T09:00") { 0.3 } else { 0.1 }))
        .collect();
    let precip: Vec<Value> = times
        .iter()
        .map(|t| json!(if t.ends_with("01T12:00") { 1.0 } else { 0.0 }))
        .collect();
    let (base, _) = serve(
        open_meteo(19_800, "Asia/Kolkata", times, et0, precip),
        json!({}),
    )
    .await;
    let f = poll_one(
        &base,
        Provider::OpenMeteo,
        22.5,
        88.3,
        7200.0,
        "2026-06-01T00:10:00Z",
    )
    .await;
    // the first stamp (00:00 local) ends at 18:30 UTC the day before; the
    // last (2026-06-02T23:00 local) at 17:30 UTC on 2 June: from the
    // boundary 00:00 the periods up to 16:00–18:00 are covered but the
    // last (ends 17:30) is not
    assert_eq!(f.start, at("2026-06-01T00:00:00Z"));
    assert_eq!(f.step_s, 7200.0);
    assert_eq!(f.et0_mm.len(), 20, "00:00 on 1 June to 16:00 on 2 June");
    let mut precip = vec![0.0; 20];
    precip[2] = 0.5; // [04:00, 06:00)
    precip[3] = 0.5; // [06:00, 08:00)
    for (k, (got, want)) in f.precip_mm.iter().zip(&precip).enumerate() {
        assert!(
            (got - want).abs() < 1e-12,
            "precip[{k}] = {got}, want {want}"
        );
    }
    // [02:00, 04:00) holds half of [01:30, 02:30) (0.1), all of
    // [02:30, 03:30) (0.3) and half of [03:30, 04:30) (0.1): 0.4
    assert!((f.et0_mm[1] - 0.4).abs() < 1e-12, "{:?}", f.et0_mm);
    assert!((f.et0_mm[0] - 0.2).abs() < 1e-12);
    assert!((f.et0_mm[5] - 0.2).abs() < 1e-12);
}

#[tokio::test]
async fn open_meteo_across_a_daylight_saving_change_keeps_its_one_offset_and_stops_at_nulls() {
    rootzone::service::install_tls();
    // Berlin, fetched on 24 October 2026 in summer time (+02:00). Summer
    // time ends on 25 October at 03:00 local, but Open-Meteo applies the
    // offset valid at the request to the whole series: the stamps go on
    // hour by hour (no repeated 02:00) and each is 7200 s ahead of UTC.
    // 2 mm at the stamp "2026-10-25T03:00" is the UTC hour [00:00, 01:00).
    // The last five hours' ET0 is null (beyond the model's range).
    let times = local_hours("2026-10-24T00:00", 72);
    let n = times.len();
    let et0: Vec<Value> = (0..n)
        .map(|i| if i >= n - 5 { Value::Null } else { json!(0.05) })
        .collect();
    let precip: Vec<Value> = times
        .iter()
        .map(|t| json!(if t == "2026-10-25T03:00" { 2.0 } else { 0.0 }))
        .collect();
    assert_eq!(
        times
            .iter()
            .filter(|t| t.starts_with("2026-10-25T02"))
            .count(),
        1
    );
    let (base, _) = serve(
        open_meteo(7200, "Europe/Berlin", times, et0, precip),
        json!({}),
    )
    .await;
    let f = poll_one(
        &base,
        Provider::OpenMeteo,
        52.52,
        13.41,
        3600.0,
        "2026-10-24T06:00:00Z",
    )
    .await;
    assert_eq!(f.start, at("2026-10-24T06:00:00Z"));
    // stamps from 2026-10-24T00:00 local (ends 22:00 UTC on the 23rd) to
    // 2026-10-26T23:00 (ends 21:00 UTC on the 26th); ET0 null from the
    // stamp 19:00 on the 26th, i.e. the hour ending 17:00 UTC: covered up
    // to 16:00 UTC on the 26th
    let last = f.start + TimeDelta::hours(f.et0_mm.len() as i64);
    assert_eq!(last, at("2026-10-26T16:00:00Z"));
    let k = (at("2026-10-25T00:00:00Z") - f.start).num_hours() as usize;
    for (i, p) in f.precip_mm.iter().enumerate() {
        let want = if i == k { 2.0 } else { 0.0 };
        assert_eq!(*p, want, "hour {i}");
    }
    assert!(f.et0_mm.iter().all(|e| (e - 0.05).abs() < 1e-12));
}

/// FAO-56 eqs 21–25 and 52, written out again for the expectation.
fn hargreaves_day(lat_deg: f64, doy: f64, t_max: f64, t_min: f64) -> f64 {
    let pi = std::f64::consts::PI;
    let phi = lat_deg * pi / 180.0;
    let dr = 1.0 + 0.033 * (2.0 * pi * doy / 365.0).cos();
    let delta = 0.409 * (2.0 * pi * doy / 365.0 - 1.39).sin();
    let ws = (-phi.tan() * delta.tan()).acos();
    let ra = 24.0 * 60.0 / pi
        * 0.082
        * dr
        * (ws * phi.sin() * delta.sin() + phi.cos() * delta.cos() * ws.sin());
    0.0023 * ((t_max + t_min) / 2.0 + 17.8) * (t_max - t_min).sqrt() * 0.408 * ra
}

/// A MET Norway compact answer at 60° N, 0° E: hourly from 1 June 2026
/// 00:00 UTC for 48 h, then six-hourly blocks for 3 June, then one last
/// instant without a next block.
fn met_fixture() -> Value {
    let mut ts = Vec::new();
    let t0 = at("2026-06-01T00:00:00Z");
    for h in 0..48 {
        let t = t0 + TimeDelta::hours(h);
        let day = h / 24;
        let hour = h % 24;
        let temp = match (day, hour) {
            (0, 4) => 8.0,
            (0, 14) => 22.0,
            (1, 5) => 10.0,
            (1, 15) => 25.0,
            _ => 15.0,
        };
        let precip = match h {
            5 => 1.2,
            6 => 0.4,
            47 => 0.6,
            _ => 0.0,
        };
        ts.push(json!({
            "time": t.format("%Y-%m-%dT%H:%M:%SZ").to_string(),
            "data": {
                "instant": {"details": {"air_temperature": temp, "air_pressure_at_sea_level": 1012.0}},
                "next_1_hours": {"summary": {"symbol_code": "cloudy"}, "details": {"precipitation_amount": precip}},
                // the six hours ahead, overlapping the hourly ones: unused
                // where next_1_hours is given
                "next_6_hours": {"summary": {"symbol_code": "cloudy"},
                    "details": {"precipitation_amount": 9.9, "air_temperature_max": 40.0, "air_temperature_min": -5.0}}
            }
        }));
    }
    for (h, inst, max, min, p) in [
        (0, 10.0, 14.0, 9.0, 3.0),
        (6, 14.0, 24.0, 13.0, 0.0),
        (12, 24.0, 27.0, 20.0, 1.5),
        (18, 19.0, 19.0, 12.0, 0.3),
    ] {
        let t = at("2026-06-03T00:00:00Z") + TimeDelta::hours(h);
        ts.push(json!({
            "time": t.format("%Y-%m-%dT%H:%M:%SZ").to_string(),
            "data": {
                "instant": {"details": {"air_temperature": inst}},
                "next_6_hours": {"summary": {"symbol_code": "rain"},
                    "details": {"precipitation_amount": p, "air_temperature_max": max, "air_temperature_min": min}}
            }
        }));
    }
    ts.push(json!({"time": "2026-06-04T00:00:00Z", "data": {"instant": {"details": {"air_temperature": 12.0}}}}));
    json!({
        "type": "Feature",
        "geometry": {"type": "Point", "coordinates": [0.0, 60.0, 10]},
        "properties": {
            "meta": {"updated_at": "2026-05-31T23:41:07Z",
                "units": {"air_temperature": "celsius", "precipitation_amount": "mm", "air_pressure_at_sea_level": "hPa"}},
            "timeseries": ts
        }
    })
}

#[tokio::test]
async fn met_norway_hourly_then_six_hour_tail_with_hargreaves_et0_by_hand() {
    rootzone::service::install_tls();
    let (base, replay) = serve(json!({}), met_fixture()).await;
    let f = poll_one(
        &base,
        Provider::MetNorway,
        60.0,
        0.0,
        7200.0,
        "2026-06-01T00:00:00Z",
    )
    .await;
    assert_eq!(f.start, at("2026-06-01T00:00:00Z"));
    assert_eq!(f.issued_at, at("2026-05-31T23:41:07Z"));
    assert_eq!(f.et0_mm.len(), 36, "three days of 2-h periods");
    // precipitation: hourly, then each six-hour block spread over its
    // three periods
    let mut want = vec![0.0; 36];
    want[2] = 1.2; // 04:00–06:00 holds hour 5
    want[3] = 0.4; // 06:00–08:00 holds hour 6
    want[23] = 0.6; // 22:00–24:00 on 2 June
    for w in &mut want[24..27] {
        *w = 1.0; // 3 mm over 00:00–06:00 on 3 June
    }
    for w in &mut want[30..33] {
        *w = 0.5; // 1.5 mm over 12:00–18:00
    }
    for w in &mut want[33..36] {
        *w = 0.1; // 0.3 mm over 18:00–24:00
    }
    for (k, (got, w)) in f.precip_mm.iter().zip(&want).enumerate() {
        assert!((got - w).abs() < 1e-12, "precip[{k}] = {got}, want {w}");
    }
    // ET0: each day's periods add up to that day's Hargreaves ET0 from its
    // extremes (hourly instants on days 1 and 2; the tail's six-hour
    // extremes on day 3), and nights get none
    for (day, doy, t_max, t_min) in [
        (0, 152.0, 22.0, 8.0),
        (1, 153.0, 25.0, 10.0),
        (2, 154.0, 27.0, 9.0),
    ] {
        let sum: f64 = f.et0_mm[12 * day..12 * (day + 1)].iter().sum();
        let want = hargreaves_day(60.0, doy, t_max, t_min);
        assert!((sum - want).abs() < 1e-9, "day {day}: {sum} vs {want}");
    }
    assert!(
        f.et0_mm[0] < 1e-3 * f.et0_mm[6],
        "midnight vs noon: {:?}",
        &f.et0_mm[..12]
    );
    // the request: MET's 4-decimal location and an identifying User-Agent
    let r = replay.lock().unwrap();
    assert_eq!(r.seen.len(), 1);
    assert_eq!(r.seen[0].path, "/weatherapi/locationforecast/2.0/compact");
    assert_eq!(r.seen[0].query, "lat=60.0000&lon=0.0000");
    assert_eq!(
        r.seen[0].user_agent,
        format!("rootzone/{} test@example.org", env!("CARGO_PKG_VERSION"))
    );
}

#[tokio::test]
async fn a_thousand_fields_at_three_locations_make_one_request_per_source_then_304s() {
    rootzone::service::install_tls();
    let times = local_hours("2026-06-01T00:00", 72);
    let om = open_meteo(
        0,
        "GMT",
        times.clone(),
        vec![json!(0.1); 72],
        vec![json!(0.0); 72],
    );
    let (base, replay) = serve(om, met_fixture()).await;
    let dir = tempfile::tempdir().unwrap();
    let store = Arc::new(Store::open(dir.path()).unwrap());
    // three sites; fields within a few metres of a site share it (rounded
    // to 2 decimals); two providers at the first site: four sources
    let sites = [(52.5200, 13.4100), (48.1400, 11.5800), (60.0000, 0.0000)];
    let mut fields = Vec::new();
    for i in 0..1000 {
        let (lat, lon) = sites[i % 3];
        let jitter = (i % 7) as f64 * 1e-4;
        let provider = if i % 3 == 2 || i % 10 == 0 {
            Provider::MetNorway
        } else {
            Provider::OpenMeteo
        };
        fields.push(field(
            &store,
            &format!("f{i}"),
            7200.0,
            source(provider, &base, lat + jitter, lon - jitter),
        ));
    }
    let mut distinct = std::collections::BTreeSet::new();
    for f in &fields {
        let s = f.spec.forecast_source.as_ref().unwrap();
        distinct.insert((
            s.provider,
            (
                (s.latitude * 100.0).round() as i64,
                (s.longitude * 100.0).round() as i64,
            ),
        ));
    }
    // site 0 and 1 with both providers, site 2 with MET Norway only
    assert_eq!(distinct.len(), 5);
    let poller = Poller::new(settings(), store.clone()).unwrap();
    let t0 = at("2026-06-01T00:00:00Z");
    let started = std::time::Instant::now();
    let r = poller.poll(t0, &fields).await.unwrap();
    let first_poll = started.elapsed();
    assert_eq!(r.sources, distinct.len());
    assert_eq!(r.requests, distinct.len(), "{r:?}");
    assert_eq!(replay.lock().unwrap().seen.len(), distinct.len());
    assert_eq!(r.fields_updated, 1000);
    assert!(
        fields
            .iter()
            .all(|f| store.latest_forecast(f.id).unwrap().is_some())
    );
    // before the poll interval: nothing is due
    let r = poller
        .poll(t0 + TimeDelta::minutes(30), &fields)
        .await
        .unwrap();
    assert_eq!(r.requests, 0);
    // an hour on, unchanged: one conditional request per source, all 304,
    // and no new forecast stored
    let stored_before = store
        .forecasts_since(fields[0].id, t0 - TimeDelta::days(1), 100)
        .unwrap()
        .len();
    let r = poller
        .poll(t0 + TimeDelta::hours(1), &fields)
        .await
        .unwrap();
    assert_eq!(
        (r.requests, r.not_modified, r.fields_updated),
        (distinct.len(), distinct.len(), 0),
        "{r:?}"
    );
    let seen = &replay.lock().unwrap().seen;
    assert_eq!(seen.len(), 2 * distinct.len());
    assert!(
        seen[distinct.len()..]
            .iter()
            .all(|s| s.if_modified_since.as_deref() == Some("Mon, 01 Jun 2026 00:00:00 GMT"))
    );
    assert!(
        seen[..distinct.len()]
            .iter()
            .all(|s| s.if_modified_since.is_none())
    );
    let stored_after = store
        .forecasts_since(fields[0].id, t0 - TimeDelta::days(1), 100)
        .unwrap()
        .len();
    assert_eq!(stored_before, stored_after);
    println!(
        "1000 fields, {} sources: first poll {first_poll:?}",
        distinct.len()
    );
}

#[tokio::test]
async fn an_answer_valid_past_the_poll_interval_is_not_requested_again_before_it_expires() {
    rootzone::service::install_tls();
    let (base, replay) = serve(Value::Null, met_fixture()).await;
    // MET Norway's answer is valid for 3 h (its Expires less its Date);
    // the poll interval is 1 h
    replay.lock().unwrap().expires = Some((
        "Mon, 01 Jun 2026 00:00:05 GMT",
        "Mon, 01 Jun 2026 03:00:05 GMT",
    ));
    let dir = tempfile::tempdir().unwrap();
    let store = Arc::new(Store::open(dir.path()).unwrap());
    let f = field(
        &store,
        "fjord",
        7200.0,
        source(Provider::MetNorway, &base, 59.91, 10.75),
    );
    let poller = Poller::new(settings(), store.clone()).unwrap();
    let t0 = at("2026-06-01T00:00:00Z");
    let fields = std::slice::from_ref(&f);
    assert_eq!(poller.poll(t0, fields).await.unwrap().requests, 1);
    for hours in [1, 2] {
        let r = poller
            .poll(t0 + TimeDelta::hours(hours), fields)
            .await
            .unwrap();
        assert_eq!(r.requests, 0, "{hours} h: {r:?}");
    }
    let r = poller.poll(t0 + TimeDelta::hours(3), fields).await.unwrap();
    assert_eq!((r.requests, r.not_modified), (1, 1), "{r:?}");
    // without Expires the poll interval rules again
    replay.lock().unwrap().expires = None;
    let r = poller.poll(t0 + TimeDelta::hours(6), fields).await.unwrap();
    assert_eq!(r.requests, 1, "{r:?}");
    let r = poller.poll(t0 + TimeDelta::hours(7), fields).await.unwrap();
    assert_eq!(r.requests, 1, "{r:?}");
}

fn state_of(store: &Store, spec: &SourceSpec) -> SourceState {
    serde_json::from_str(&store.forecast_source(&spec.key(2).id()).unwrap().unwrap()).unwrap()
}

#[tokio::test]
async fn a_provider_down_is_retried_with_exponential_backoff_and_goes_stale() {
    rootzone::service::install_tls();
    let (base, replay) = serve(json!({}), met_fixture()).await;
    let dir = tempfile::tempdir().unwrap();
    let store = Arc::new(Store::open(dir.path()).unwrap());
    let spec = source(Provider::MetNorway, &base, 60.0, 0.0);
    let f = field(&store, "f", 7200.0, spec.clone());
    let fields = [f.clone()];
    let poller = Poller::new(settings(), store.clone()).unwrap();
    let t0 = at("2026-06-01T00:00:00Z");
    assert_eq!(poller.poll(t0, &fields).await.unwrap().updated, 1);
    let good = state_of(&store, &spec).series.unwrap();
    // fresh: the provider's forecast, issued and fetched times recorded
    let (fc, flag, used) = for_cycle(
        Provider::MetNorway,
        Some(&state_of(&store, &spec)),
        7200.0,
        t0 + TimeDelta::hours(2),
        3.0 * 3600.0,
    );
    assert!(fc.is_some() && flag.is_none());
    assert_eq!(used.source, "met-norway");
    assert_eq!(used.issued_at, Some(at("2026-05-31T23:41:07Z")));
    assert_eq!(used.fetched_at, Some(t0));
    replay.lock().unwrap().mode = Mode::Down;
    // retries 60, 120, 240, … s after each failure (retry_s 60, capped at 3600)
    let mut t = t0 + TimeDelta::hours(1);
    let mut waits = Vec::new();
    for _ in 0..8 {
        // poll every 10 s until a request goes out
        let mut polls = 0;
        loop {
            let r = poller.poll(t, &fields).await.unwrap();
            if r.requests > 0 {
                assert_eq!(r.failed, 1);
                break;
            }
            polls += 1;
            assert!(polls < 1000);
            t += TimeDelta::seconds(10);
        }
        let s = state_of(&store, &spec);
        waits.push((s.next_poll_at.unwrap() - t).num_seconds());
        t += TimeDelta::seconds(10);
    }
    assert_eq!(waits, vec![60, 120, 240, 480, 960, 1920, 3600, 3600]);
    let s = state_of(&store, &spec);
    assert_eq!(s.failures, 8);
    assert_eq!(
        s.series.as_ref(),
        Some(&good),
        "the last good forecast is kept"
    );
    assert!(s.last_error.unwrap().contains("503"));
    // three hours after the last answer the source is stale: climatology, flagged
    let (fc, flag, used) = for_cycle(
        Provider::MetNorway,
        Some(&state_of(&store, &spec)),
        7200.0,
        t0 + TimeDelta::hours(3) + TimeDelta::seconds(1),
        3.0 * 3600.0,
    );
    assert!(fc.is_none());
    assert_eq!(flag, Some("stale-forecast"));
    assert_eq!(used.source, "climatology");
    // the provider back: the next due poll succeeds and resets the backoff
    replay.lock().unwrap().mode = Mode::Ok;
    t = s.next_poll_at.unwrap();
    let r = poller.poll(t, &fields).await.unwrap();
    assert_eq!(r.requests, 1);
    assert_eq!(state_of(&store, &spec).failures, 0);
}

#[tokio::test]
async fn malformed_truncated_or_wrong_units_answers_keep_the_last_good_forecast() {
    rootzone::service::install_tls();
    let times = local_hours("2026-06-01T00:00", 72);
    let om = open_meteo(0, "GMT", times, vec![json!(0.1); 72], vec![json!(0.2); 72]);
    let (base, replay) = serve(om, met_fixture()).await;
    let dir = tempfile::tempdir().unwrap();
    let store = Arc::new(Store::open(dir.path()).unwrap());
    let om_spec = source(Provider::OpenMeteo, &base, 52.52, 13.41);
    let met_spec = source(Provider::MetNorway, &base, 60.0, 0.0);
    let fields = [
        field(&store, "om", 7200.0, om_spec.clone()),
        field(&store, "met", 7200.0, met_spec.clone()),
    ];
    let poller = Poller::new(settings(), store.clone()).unwrap();
    let mut t = at("2026-06-01T00:00:00Z");
    assert_eq!(poller.poll(t, &fields).await.unwrap().updated, 2);
    let good = [
        state_of(&store, &om_spec).series,
        state_of(&store, &met_spec).series,
    ];
    let stored: Vec<Forecast> = fields
        .iter()
        .map(|f| store.latest_forecast(f.id).unwrap().unwrap())
        .collect();
    for (mode, needle) in [
        (Mode::Garbage, "malformed"),
        (Mode::Truncated, "malformed"),
        (Mode::WrongUnits, "units"),
    ] {
        replay.lock().unwrap().mode = mode;
        // a changed Last-Modified so the server answers with a body
        replay.lock().unwrap().last_modified = "Tue, 02 Jun 2026 00:00:00 GMT";
        t += TimeDelta::hours(2);
        let r = poller.poll(t, &fields).await.unwrap();
        assert_eq!(
            (r.requests, r.failed, r.fields_updated),
            (2, 2, 0),
            "{mode:?}: {r:?}"
        );
        for (spec, g) in [&om_spec, &met_spec].iter().zip(&good) {
            let s = state_of(&store, spec);
            assert_eq!(&s.series, g, "{mode:?}");
            let why = s.last_error.unwrap();
            assert!(why.contains(needle), "{mode:?}: {why}");
        }
        for (f, before) in fields.iter().zip(&stored) {
            assert_eq!(&store.latest_forecast(f.id).unwrap().unwrap(), before);
        }
        replay.lock().unwrap().last_modified = "Mon, 01 Jun 2026 00:00:00 GMT";
    }
}

#[test]
fn a_source_out_of_range_is_refused_naming_the_key() {
    let spec = |lat: f64, lon: f64, base: Option<&str>| FieldSpec {
        actuator: Actuator::None,
        simulation: None,
        forecast_source: Some(SourceSpec {
            provider: Provider::OpenMeteo,
            latitude: lat,
            longitude: lon,
            base_url: base.map(str::to_string),
        }),
        ..FieldSpec::demo()
    };
    assert_eq!(spec(52.5, 13.4, None).validate(), Ok(()));
    let e = spec(90.5, 13.4, None).validate().unwrap_err();
    assert!(
        e.contains("forecast_source.latitude") && e.contains("[-90, 90]"),
        "{e}"
    );
    let e = spec(52.5, -180.1, None).validate().unwrap_err();
    assert!(e.contains("forecast_source.longitude"), "{e}");
    let e = spec(52.5, 13.4, Some("ftp://x")).validate().unwrap_err();
    assert!(e.contains("forecast_source.base_url"), "{e}");
    // the spec as JSON
    let parsed: FieldSpec = serde_json::from_value(json!({
        "name": "x", "actuator": {"kind": "none"},
        "forecast_source": {"provider": "met-norway", "latitude": 59.9, "longitude": 10.7}
    }))
    .unwrap();
    assert_eq!(
        parsed.forecast_source.unwrap().provider,
        Provider::MetNorway
    );
}
