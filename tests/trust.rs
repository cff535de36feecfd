//! The daemon as a service people can trust (issue 15), end to end: the real
//! binary over HTTP with curl. Bounds, the error contract, authentication,
//! signed webhooks, secrets, file modes, the first cycle and bad settings.

mod common;
use common::*;

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpListener;
use std::process::Command;
use std::time::Duration;

use hmac::{KeyInit, Mac};
use serde_json::{Value, json};

fn post(d: &Daemon, path: &str, body: &Value) -> (u16, String, String) {
    curl(d, "POST", path, Some(&body.to_string()), Some(TOKEN))
}

#[test]
fn out_of_range_input_is_refused_naming_the_key_and_its_range() {
    let dir = tempfile::tempdir().unwrap();
    let d = start(dir.path(), &config(""));
    for (body, needle) in [
        (
            json!({"name": "a", "control_period_s": 1e300}),
            "control_period_s",
        ),
        (json!({"name": "a", "control_period_s": 3.4e16}), "86400"),
        (
            json!({"name": "a", "irrigation_max": 1e300}),
            "irrigation_max",
        ),
        (
            json!({"name": "a", "measurement_wait_s": 1e9}),
            "measurement_wait_s",
        ),
        (
            json!({"name": "a", "crop": {"crop_coefficient": 50}}),
            "crop_coefficient",
        ),
        (
            json!({"name": "a", "actuator": {"kind": "simulated"},
                   "simulation": {"start": "0001-01-01T00:00:00Z"}}),
            "simulation.start",
        ),
        (
            json!({"name": "a", "model": "richards", "soil": {"residual_water_content": 0.1,
                   "saturated_water_content": 0.4, "alpha": 2.0, "n": 1.0,
                   "saturated_conductivity": 1e-6}}),
            "n",
        ),
        // a type error names the key it is in
        (json!({"name": "a", "zone": {"low": "dry"}}), "zone.low"),
        (
            json!({"name": "a", "zone": {"low": 0.2, "low_head": -0.4}}),
            "both",
        ),
        (json!({"name": "a", "zone": {"up_head": 3.0}}), "up_head"),
        (json!({"name": "é".repeat(201)}), "200 characters"),
    ] {
        problem(post(&d, "/v1/fields", &body), 422, needle);
    }
    // 200 characters of two bytes each are fine
    let r = post(&d, "/v1/fields", &json!({"name": "é".repeat(200)}));
    assert_eq!(r.0, 201, "{}", r.2);

    let id = create_field(&d, json!({"name": "north"}));
    let forecast = |precip: f64| {
        json!({"issued_at": now_minus(1), "start": now_minus(1), "step_s": 3600.0,
               "et0_mm": [0.1, 0.2], "precip_mm": [0.0, precip]})
        .to_string()
    };
    let path = format!("/v1/fields/{id}/forecast");
    problem(
        curl(&d, "PUT", &path, Some(&forecast(1e308)), Some(TOKEN)),
        422,
        "precip_mm[1]",
    );
    let r = curl(&d, "PUT", &path, Some(&forecast(3.0)), Some(TOKEN));
    assert_eq!(r.0, 200, "{}", r.2);
    let old = json!({"time": "1970-01-01T00:00:00Z", "theta": 0.2});
    problem(
        post(&d, &format!("/v1/fields/{id}/measurements"), &old),
        422,
        "2000",
    );
}

#[test]
fn zones_take_per_key_defaults_and_either_form() {
    let dir = tempfile::tempdir().unwrap();
    let d = start(dir.path(), &config(""));
    // one key given: the others default
    let r = post(
        &d,
        "/v1/fields",
        &json!({"name": "a", "zone": {"low": 0.2}}),
    );
    assert_eq!(r.0, 201, "{}", r.2);
    let z = &json_of(&r.2)["effective_zone"];
    assert_eq!(
        (z["low"].as_f64(), z["up"].as_f64()),
        (Some(0.2), Some(0.23))
    );
    assert_eq!(z["terminal_low"], 0.2);
    // another soil: the default is the θ band of the heads −0.43 … −0.27 m;
    // given in heads it is the same band. Loam (Carsel & Parrish 1988):
    // θr 0.078, θs 0.43, α 3.6 1/m, n 1.56
    let theta = |h: f64| {
        let (r, s, a, n) = (0.078, 0.43, 3.6_f64, 1.56_f64);
        r + (s - r) * (1.0 + (a * h.abs()).powf(n)).powf(-(1.0 - 1.0 / n))
    };
    for (name, zone) in [
        ("b", json!({})),
        ("c", json!({"low_head": -0.43, "up_head": -0.27})),
    ] {
        let r = post(
            &d,
            "/v1/fields",
            &json!({"name": name, "soil": "loam", "model": "richards", "zone": zone}),
        );
        assert_eq!(r.0, 201, "{}", r.2);
        let z = &json_of(&r.2)["effective_zone"];
        assert!(
            (z["low"].as_f64().unwrap() - theta(-0.43)).abs() < 1e-9,
            "{z}"
        );
        assert!(
            (z["up"].as_f64().unwrap() - theta(-0.27)).abs() < 1e-9,
            "{z}"
        );
        assert!((z["low_head"].as_f64().unwrap() + 0.43).abs() < 1e-9, "{z}");
    }
}

#[test]
fn errors_are_problem_json_with_a_request_id_and_auth_follows_rfc_9110() {
    let dir = tempfile::tempdir().unwrap();
    let d = start(dir.path(), &config(""));
    // 404 and 405 are problem+json too
    problem(curl(&d, "GET", "/v1/nothing", None, None), 404, "no such");
    let r = curl(&d, "DELETE", "/v1/fields", None, Some(TOKEN));
    problem(r.clone(), 405, "method");
    assert!(
        json_of(&r.2)["request_id"]
            .as_str()
            .is_some_and(|s| s.len() >= 32),
        "{}",
        r.2
    );
    // the scheme is case-insensitive; another scheme is 401, a wrong token 403
    let with_header = |h: &str| {
        let out = Command::new("curl")
            .args([
                "-s",
                "-i",
                "-X",
                "POST",
                "-H",
                h,
                "-H",
                "Content-Type: application/json",
            ])
            .args(["--data", r#"{"name": "auth"}"#])
            .arg(format!("{}/v1/fields", d.base))
            .output()
            .unwrap();
        String::from_utf8_lossy(&out.stdout).to_string()
    };
    let lower = with_header(&format!("Authorization: bearer {TOKEN}"));
    assert!(lower.starts_with("HTTP/1.1 201"), "{lower}");
    let basic = with_header("Authorization: Basic dXNlcjpwYXNz");
    assert!(basic.starts_with("HTTP/1.1 401"), "{basic}");
    assert!(
        basic.to_lowercase().contains("www-authenticate: bearer"),
        "{basic}"
    );
    assert!(basic.to_lowercase().contains("x-request-id:"), "{basic}");
    let wrong = with_header("Authorization: Bearer not-the-token-at-all");
    assert!(wrong.starts_with("HTTP/1.1 403"), "{wrong}");
    // duplicate names are refused
    problem(
        post(&d, "/v1/fields", &json!({"name": "auth"})),
        409,
        "auth",
    );
}

#[test]
fn a_conflicting_resend_is_refused_and_the_stored_value_kept() {
    let dir = tempfile::tempdir().unwrap();
    let d = start(dir.path(), &config(""));
    let sensors = json!([{"id": "s1", "depth": 0.13}, {"id": "s2", "depth": 0.3}]);
    let id = json_of(&post(&d, "/v1/fields", &json!({"name": "m", "sensors": sensors})).2)["id"]
        .as_i64()
        .unwrap();
    let path = format!("/v1/fields/{id}/measurements");
    let t = now_minus(5);
    let r = post(&d, &path, &json!({"time": t, "theta": 0.2, "sensor": "s1"}));
    assert_eq!(r.0, 201, "{}", r.2);
    // the same again: a duplicate; another θ: 409 naming both values
    let r = post(&d, &path, &json!({"time": t, "theta": 0.2, "sensor": "s1"}));
    assert_eq!(json_of(&r.2)["duplicates"], 1, "{}", r.2);
    let r = post(
        &d,
        &path,
        &json!([{"time": now_minus(4), "theta": 0.21, "sensor": "s1"},
                {"time": t, "theta": 0.25, "sensor": "s1"}]),
    );
    problem(r.clone(), 409, "0.25");
    assert!(r.2.contains("0.2 "), "{}", r.2);
    // nothing of the refused batch was stored
    let stored = json_of(&curl(&d, "GET", &path, None, None).2);
    assert_eq!(stored.as_array().unwrap().len(), 1, "{stored}");
    assert_eq!(stored[0]["theta"], 0.2);
    // another sensor at the same time is another measurement
    let r = post(
        &d,
        &path,
        &json!({"time": t, "theta": 0.25, "sensor": "s2"}),
    );
    assert_eq!(json_of(&r.2)["stored"], 1, "{}", r.2);
}

/// Accepts one HTTP request; returns its head (lowercased names) and body.
fn receive_one(listener: &TcpListener) -> (Vec<(String, String)>, Vec<u8>) {
    let (mut stream, _) = listener.accept().unwrap();
    stream
        .set_read_timeout(Some(Duration::from_secs(10)))
        .unwrap();
    let mut reader = BufReader::new(stream.try_clone().unwrap());
    let mut headers = Vec::new();
    let mut line = String::new();
    reader.read_line(&mut line).unwrap(); // request line
    loop {
        line.clear();
        reader.read_line(&mut line).unwrap();
        let l = line.trim_end();
        if l.is_empty() {
            break;
        }
        if let Some((k, v)) = l.split_once(':') {
            headers.push((k.trim().to_lowercase(), v.trim().to_string()));
        }
    }
    let length: usize = headers
        .iter()
        .find(|(k, _)| k == "content-length")
        .map(|(_, v)| v.parse().unwrap())
        .unwrap_or(0);
    let mut body = vec![0; length];
    reader.read_exact(&mut body).unwrap();
    stream
        .write_all(b"HTTP/1.1 204 No Content\r\ncontent-length: 0\r\n\r\n")
        .unwrap();
    (headers, body)
}

#[test]
fn webhooks_are_signed_and_their_secrets_and_targets_guarded() {
    let dir = tempfile::tempdir().unwrap();
    let d = start(dir.path(), &config(""));
    // the metadata address is refused
    let metadata = json!({"name": "meta", "actuator": {"kind": "webhook",
        "url": "http://169.254.169.254/latest/meta-data"}});
    problem(post(&d, "/v1/fields", &metadata), 422, "169.254.169.254");

    let receiver = TcpListener::bind("127.0.0.1:0").unwrap();
    let url = format!("http://{}/hook", receiver.local_addr().unwrap());
    let r = post(
        &d,
        "/v1/fields",
        &json!({"name": "valve", "actuator": {"kind": "webhook", "url": url}}),
    );
    assert_eq!(r.0, 201, "{}", r.2);
    let created = json_of(&r.2);
    let secret = created["actuator"]["secret"].as_str().unwrap().to_string();
    assert!(secret.len() >= 32);
    // the first cycle ran at creation: its setpoint arrives, signed
    let (headers, body) = receive_one(&receiver);
    let header = |name: &str| {
        headers
            .iter()
            .find(|(k, _)| k == name)
            .map(|(_, v)| v.clone())
            .unwrap_or_else(|| panic!("no {name} in {headers:?}"))
    };
    let timestamp = header("x-rootzone-timestamp");
    let mut mac = hmac::Hmac::<sha2::Sha256>::new_from_slice(secret.as_bytes()).unwrap();
    mac.update(format!("{timestamp}.").as_bytes());
    mac.update(&body);
    let expected = format!("sha256={}", hex::encode(mac.finalize().into_bytes()));
    assert_eq!(header("x-rootzone-signature"), expected);
    assert_eq!(header("x-rootzone-delivery").len(), 36);
    let now = chrono::Utc::now().timestamp();
    assert!((now - timestamp.parse::<i64>().unwrap()).abs() < 60);
    assert_eq!(
        json_of(&String::from_utf8_lossy(&body))["field_id"],
        created["id"]
    );

    // no GET returns the secret; the URL only to a request with the token
    let id = created["id"].as_i64().unwrap();
    for path in ["/v1/fields".to_string(), format!("/v1/fields/{id}")] {
        let open = curl(&d, "GET", &path, None, None).2;
        assert!(!open.contains(&secret) && !open.contains(&url), "{open}");
        let authorized = curl(&d, "GET", &path, None, Some(TOKEN)).2;
        assert!(
            !authorized.contains(&secret) && authorized.contains(&url),
            "{authorized}"
        );
    }
}

#[cfg(unix)]
#[test]
fn the_data_folder_is_private() {
    use std::os::unix::fs::PermissionsExt;
    let dir = tempfile::tempdir().unwrap();
    let _d = start(dir.path(), &config(""));
    let mode = |p: &std::path::Path| std::fs::metadata(p).unwrap().permissions().mode() & 0o777;
    let data = dir.path().join("data");
    if on_postgres() {
        // the data live in the server; no database file here
        assert!(!data.join("rootzone.sqlite3").exists());
        return;
    }
    assert_eq!(mode(&data), 0o700);
    assert_eq!(mode(&data.join("rootzone.sqlite3")), 0o600);
}

#[test]
fn an_unusable_database_stops_the_start_with_the_reason() {
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let unreachable = format!("postgres://rootzone:hidden@127.0.0.1:{port}/rootzone");
    let (code, stderr) = serve_with(
        &[("ROOTZONE_STORAGE__URL", unreachable.as_str())],
        Duration::from_secs(20),
    );
    assert_eq!(code, Some(2), "{stderr}");
    assert!(
        stderr.contains("cannot connect") && stderr.contains(&port.to_string()),
        "{stderr}"
    );
    assert!(
        !stderr.contains("hidden"),
        "the password is not shown: {stderr}"
    );
    let (code, stderr) = serve_with(
        &[("ROOTZONE_STORAGE__URL", "mysql://db/rootzone")],
        Duration::from_secs(10),
    );
    assert_eq!(code, Some(2), "{stderr}");
    assert!(stderr.contains("storage.url"), "{stderr}");
}

/// `rootzone serve` with extra environment: its exit code (None if it kept
/// running for `wait` and was stopped) and its stderr.
fn serve_with(env: &[(&str, &str)], wait: Duration) -> (Option<i32>, String) {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("rootzone.toml");
    std::fs::write(&file, config("")).unwrap();
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_rootzone"));
    cmd.args(["serve", "--config"])
        .arg(&file)
        .env("ROOTZONE_LISTEN", "127.0.0.1:0")
        .env("ROOTZONE_DATA_DIR", dir.path().join("data"))
        .env("ROOTZONE_API_TOKEN", TOKEN)
        .env_remove("RUST_LOG")
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped());
    for (k, v) in env {
        cmd.env(k, v);
    }
    let mut child = cmd.spawn().unwrap();
    let deadline = std::time::Instant::now() + wait;
    let mut code = None;
    while std::time::Instant::now() < deadline {
        if let Some(status) = child.try_wait().unwrap() {
            code = Some(status.code().unwrap_or(-1));
            break;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    if code.is_none() {
        let _ = child.kill();
    }
    let _ = child.wait();
    let mut err = String::new();
    child
        .stderr
        .take()
        .unwrap()
        .read_to_string(&mut err)
        .unwrap();
    (code, err)
}

#[test]
fn bad_settings_exit_2_naming_the_key_and_usual_notations_are_accepted() {
    for (key, value) in [
        ("ROOTZONE_CLOCK__EPOCH", "1000-01-01T00:00:00Z"),
        ("ROOTZONE_CLOCK__SPEEDUP", "1000000000000"),
        ("ROOTZONE_LIMITS__MAX_CATCH_UP_S", "1e12"),
        ("ROOTZONE_LISTEN", "localhost"),
        ("ROOTZONE_LOG__FORMAT", "xml"),
    ] {
        let env = [(key, value), ("ROOTZONE_CLOCK__SPEEDUP", "100")];
        let env: &[(&str, &str)] = if key == "ROOTZONE_CLOCK__SPEEDUP" {
            &env[..1]
        } else {
            &env
        };
        let (code, err) = serve_with(env, Duration::from_secs(10));
        assert_eq!(code, Some(2), "{key}={value}: {err}");
        let name = key
            .trim_start_matches("ROOTZONE_")
            .replace("__", ".")
            .to_lowercase();
        assert!(err.to_lowercase().contains(&name), "{key}={value}: {err}");
    }
    // a host name and exponent notation, as people write them
    let (code, err) = serve_with(
        &[
            ("ROOTZONE_LISTEN", "localhost:0"),
            ("ROOTZONE_CLOCK__SPEEDUP", "1e3"),
        ],
        Duration::from_secs(3),
    );
    assert_eq!(code, None, "{err}");
}

#[test]
fn json_logs_by_a_setting_and_a_warning_beyond_loopback() {
    let (code, err) = serve_with(
        &[
            ("ROOTZONE_LISTEN", "0.0.0.0:0"),
            ("ROOTZONE_LOG__FORMAT", "json"),
        ],
        Duration::from_secs(3),
    );
    assert_eq!(code, None, "{err}");
    let lines: Vec<Value> = err
        .lines()
        .map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("not JSON ({e}): {l}")))
        .collect();
    assert!(
        lines.iter().any(|l| l["level"] == "WARN"
            && l["fields"]["message"]
                .as_str()
                .is_some_and(|m| m.contains("beyond loopback"))),
        "{err}"
    );
}

#[test]
fn help_shows_the_defaults() {
    for (sub, needles) in [
        (
            "serve",
            [
                "127.0.0.1:8080",
                "ROOTZONE_CLOCK__SPEEDUP",
                "max_catch_up_s",
            ],
        ),
        (
            "field-sim",
            ["127.0.0.1:9090", "ROOTZONE_SIM_TOKEN", "field-data"],
        ),
    ] {
        let out = Command::new(env!("CARGO_BIN_EXE_rootzone"))
            .args([sub, "--help"])
            .output()
            .unwrap();
        let text = String::from_utf8_lossy(&out.stdout);
        for n in needles {
            assert!(text.contains(n), "{sub} --help lacks {n}: {text}");
        }
    }
}

#[test]
fn sigterm_stops_webhook_retries_at_once() {
    let dir = tempfile::tempdir().unwrap();
    let mut d = start(dir.path(), &config(""));
    // a receiver that fails every delivery (the daemon retries 1, 2, 4 s apart)
    let receiver = TcpListener::bind("127.0.0.1:0").unwrap();
    let url = format!("http://{}/hook", receiver.local_addr().unwrap());
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for stream in receiver.incoming() {
            let Ok(mut stream) = stream else { return };
            let mut buf = [0u8; 4096];
            let _ = stream.read(&mut buf);
            let _ = stream.write_all(
                b"HTTP/1.1 500 Internal Server Error\r\ncontent-length: 0\r\nconnection: close\r\n\r\n",
            );
            let _ = tx.send(());
        }
    });
    let r = post(
        &d,
        "/v1/fields",
        &json!({"name": "valve", "actuator": {"kind": "webhook", "url": url}}),
    );
    assert_eq!(r.0, 201, "{}", r.2);
    rx.recv_timeout(Duration::from_secs(10))
        .expect("a first attempt");
    let started = std::time::Instant::now();
    d.sigterm();
    let status = d.child.wait().unwrap();
    let took = started.elapsed();
    assert!(status.success(), "{status:?}");
    // the retries would hold it 7 s; the shutdown grace is 5 s
    assert!(took < Duration::from_secs(3), "shutdown took {took:?}");
}

#[test]
fn the_documented_configuration_files_load() {
    let repo = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    rootzone::service::Settings::load(Some(&repo.join("config/default.toml"))).unwrap();
    rootzone::fieldsim::FieldSimSettings::load(Some(&repo.join("config/field-sim.toml")), None)
        .unwrap();
}

#[test]
fn a_plant_started_long_ago_replays_only_the_catch_up_span() {
    let dir = tempfile::tempdir().unwrap();
    let d = start(dir.path(), &config(""));
    // 26 years behind the clock: at most 2 days (192 intervals of 900 s)
    // are simulated, the rest skipped
    let id = create_field(
        &d,
        json!({"name": "old", "actuator": {"kind": "simulated"},
                "simulation": {"start": "2000-01-01T00:00:00Z"}}),
    );
    let state = json_of(
        &curl(
            &d,
            "GET",
            &format!("/v1/fields/{id}/simulation"),
            None,
            None,
        )
        .2,
    );
    let steps = state["steps"].as_u64().unwrap();
    assert!((1..=193).contains(&steps), "{state}");
    let time = chrono::DateTime::parse_from_rfc3339(state["time"].as_str().unwrap()).unwrap();
    assert!(
        (chrono::Utc::now() - time.to_utc()).num_minutes() < 20,
        "{state}"
    );
    let stored = json_of(
        &curl(
            &d,
            "GET",
            &format!("/v1/fields/{id}/measurements?limit=100000"),
            None,
            None,
        )
        .2,
    );
    assert!(
        stored.as_array().unwrap().len() <= 194,
        "{}",
        stored.as_array().unwrap().len()
    );
}
