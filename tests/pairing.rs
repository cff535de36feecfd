//! The controller and the field simulator as two real processes, with the
//! arguments and variables of `deploy/docker-compose.yml`; and the compose
//! file checked against what the binary accepts.

use std::collections::BTreeSet;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use serde_json::Value;

const TOKEN: &str = "pairing-token-0123456789";

fn repo(path: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(path)
}

struct Process(Child);

impl Drop for Process {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Starts `rootzone args…` with `env`; waits for its first line of output.
fn spawn(args: &[&str], env: &[(&str, String)]) -> (Process, String) {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_rootzone"));
    cmd.args(args).stdout(Stdio::piped()).stderr(Stdio::null());
    for (k, v) in env {
        cmd.env(k, v);
    }
    let mut child = cmd.spawn().unwrap();
    let mut reader = BufReader::new(child.stdout.take().unwrap());
    let mut line = String::new();
    reader.read_line(&mut line).unwrap();
    std::thread::spawn(move || std::io::copy(&mut reader, &mut std::io::sink()));
    (Process(child), line)
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

fn get(url: &str) -> Option<Value> {
    let out = Command::new("curl").args(["-sf", url]).output().ok()?;
    serde_json::from_slice(&out.stdout).ok()
}

/// Polls `f` every 200 ms until it returns Some, for at most `secs`.
fn wait_for<T>(secs: u64, what: &str, mut f: impl FnMut() -> Option<T>) -> T {
    let deadline = Instant::now() + Duration::from_secs(secs);
    loop {
        if let Some(v) = f() {
            return v;
        }
        assert!(Instant::now() < deadline, "timed out waiting for {what}");
        std::thread::sleep(Duration::from_millis(200));
    }
}

struct Pair {
    dir: tempfile::TempDir,
    port: u16,
    epoch: String,
    speedup: String,
}

impl Pair {
    fn new(speedup: f64) -> Pair {
        Pair {
            dir: tempfile::tempdir().unwrap(),
            port: free_port(),
            epoch: chrono::Utc::now().to_rfc3339(),
            speedup: speedup.to_string(),
        }
    }

    fn clock_env(&self) -> Vec<(&'static str, String)> {
        vec![
            ("ROOTZONE_API_TOKEN", TOKEN.to_string()),
            ("ROOTZONE_CLOCK__SPEEDUP", self.speedup.clone()),
            ("ROOTZONE_CLOCK__EPOCH", self.epoch.clone()),
        ]
    }

    /// The compose file's controller, natively.
    fn controller(&self) -> Process {
        let mut env = self.clock_env();
        env.push(("ROOTZONE_LISTEN", format!("127.0.0.1:{}", self.port)));
        env.push((
            "ROOTZONE_DATA_DIR",
            self.dir.path().join("controller").display().to_string(),
        ));
        let config = repo("config/compose-controller.toml").display().to_string();
        let (p, line) = spawn(&["serve", "--config", &config], &env);
        assert!(line.contains(&self.port.to_string()), "{line}");
        p
    }

    /// The compose file's field simulator, natively, with `config`.
    fn field(&self, config: &Path) -> Process {
        let mut env = self.clock_env();
        env.push(("ROOTZONE_SIM_LISTEN", "127.0.0.1:0".into()));
        env.push((
            "ROOTZONE_SIM_DATA_DIR",
            self.dir.path().join("field").display().to_string(),
        ));
        let (p, line) = spawn(
            &[
                "field-sim",
                "--controller",
                &self.base(),
                "--config",
                &config.display().to_string(),
            ],
            &env,
        );
        assert!(line.contains("setpoints at"), "{line}");
        p
    }

    fn base(&self) -> String {
        format!("http://127.0.0.1:{}", self.port)
    }
}

fn times(measurements: &Value) -> Vec<chrono::DateTime<chrono::Utc>> {
    measurements
        .as_array()
        .unwrap()
        .iter()
        .map(|m| m["time"].as_str().unwrap().parse().unwrap())
        .collect()
}

#[test]
fn a_native_pair_runs_a_day_and_loses_nothing_while_the_controller_is_down() {
    // an hour of clock time per real second
    let pair = Pair::new(3600.0);
    let controller = pair.controller();
    let _field = pair.field(&repo("config/compose-field.toml"));
    let base = pair.base();
    // the simulator registers its field
    let id = wait_for(30, "registration", || {
        get(&format!("{base}/v1/fields"))?.as_array()?.first()?["id"].as_i64()
    });
    let fp = format!("{base}/v1/fields/{id}");
    // twelve hours, with setpoints delivered to the simulator
    wait_for(60, "12 h of setpoints", || {
        let sp = get(&format!("{fp}/setpoints?limit=1000"))?;
        (sp.as_array()?.len() >= 6).then_some(())
    });
    let field_file = pair.dir.path().join("field/field-compose_field.json");
    let saved: Value =
        serde_json::from_str(&std::fs::read_to_string(&field_file).unwrap()).unwrap();
    assert!(
        saved["setpoint"].is_array(),
        "no setpoint delivered: {saved}"
    );

    // the controller goes down for a few clock hours
    let before = times(&get(&format!("{fp}/measurements?limit=100000")).unwrap());
    drop(controller);
    std::thread::sleep(Duration::from_secs(4));
    let _controller = pair.controller();
    // a day has passed and the buffered measurements arrived
    let all = wait_for(60, "a day of measurements after the outage", || {
        let m = get(&format!("{fp}/measurements?limit=100000"))?;
        let t = times(&m);
        (t.len() >= before.len() + 40 && (*t.last()? - t[0]).num_hours() >= 24).then_some(t)
    });
    // every 15-min measurement is there once: no gap across the outage
    for w in all.windows(2) {
        assert_eq!(
            (w[1] - w[0]).num_seconds(),
            900,
            "gap or duplicate between {} and {}",
            w[0],
            w[1]
        );
    }
    // a cycle every 2 h, but none while the controller was down
    let setpoints = get(&format!("{fp}/setpoints?limit=1000")).unwrap();
    assert!(setpoints.as_array().unwrap().len() >= 8, "{setpoints}");
    for s in setpoints.as_array().unwrap() {
        let rate = s["rate"].as_f64().unwrap();
        assert!((0.0..=1e-5).contains(&rate), "{s}");
    }
}

#[test]
fn a_clock_mismatch_is_refused() {
    let pair = Pair::new(3600.0);
    let _controller = pair.controller();
    let mut env = pair.clock_env();
    env[1].1 = "720".into();
    env.push(("ROOTZONE_SIM_LISTEN", "127.0.0.1:0".into()));
    env.push((
        "ROOTZONE_SIM_DATA_DIR",
        pair.dir.path().join("field").display().to_string(),
    ));
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_rootzone"));
    cmd.args(["field-sim", "--controller", &pair.base()]);
    for (k, v) in &env {
        cmd.env(k, v);
    }
    let out = cmd.output().unwrap();
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("clock mismatch"), "{err}");
}

/// Checks the variables of a service without a command of its own; returns
/// no command.
fn continue_with_env(
    name: &str,
    service: &yaml_rust2::Yaml,
    allowed: &BTreeSet<String>,
) -> Vec<String> {
    for (k, _) in yaml_map(&service["environment"]) {
        assert!(allowed.contains(&k), "{name}: {k} is not read by rootzone");
    }
    Vec::new()
}

/// `key: value` pairs of a YAML mapping as strings.
fn yaml_map(y: &yaml_rust2::Yaml) -> Vec<(String, String)> {
    y.as_hash()
        .map(|h| {
            h.iter()
                .filter_map(|(k, v)| {
                    let value = match v {
                        yaml_rust2::Yaml::String(s) => s.clone(),
                        yaml_rust2::Yaml::Integer(i) => i.to_string(),
                        yaml_rust2::Yaml::Real(r) => r.clone(),
                        _ => return None,
                    };
                    Some((k.as_str()?.to_string(), value))
                })
                .collect()
        })
        .unwrap_or_default()
}

#[test]
fn the_compose_file_matches_what_the_binary_accepts() {
    use yaml_rust2::{Yaml, YamlLoader};
    let text = std::fs::read_to_string(repo("deploy/docker-compose.yml")).unwrap();
    let doc = &YamlLoader::load_from_str(&text).unwrap()[0];
    let allowed: BTreeSet<String> = rootzone::service::settings::ENV_KEYS
        .iter()
        .chain(rootzone::fieldsim::ENV_KEYS)
        .map(|k| rootzone::service::settings::env_name(k))
        .collect();
    let shared = yaml_map(&doc["x-env"]);
    assert!(
        !shared.is_empty(),
        "the x-env anchor holds the shared token"
    );
    let services = doc["services"].as_hash().unwrap();
    assert!(services.len() >= 2);
    for (name, service) in services {
        let name = name.as_str().unwrap();
        // the command: a subcommand and flags the binary knows
        let command: Vec<String> = match &service["command"] {
            Yaml::Array(a) => a.iter().map(|v| v.as_str().unwrap().to_string()).collect(),
            // a service extending another inherits its command
            Yaml::BadValue if !service["extends"].is_badvalue() => {
                continue_with_env(name, service, &allowed)
            }
            other => panic!("{name}: command must be a list, got {other:?}"),
        };
        if command.is_empty() {
            continue;
        }
        let help = Command::new(env!("CARGO_BIN_EXE_rootzone"))
            .args([command[0].as_str(), "--help"])
            .output()
            .unwrap();
        assert!(
            help.status.success(),
            "{name}: unknown subcommand {}",
            command[0]
        );
        let help = String::from_utf8_lossy(&help.stdout);
        for flag in command.iter().filter(|a| a.starts_with("--")) {
            assert!(
                help.contains(flag.as_str()),
                "{name}: {flag} is not an option of {}",
                command[0]
            );
        }
        // the configuration file it names exists in config/ and loads
        if let Some(i) = command.iter().position(|a| a == "--config") {
            let file = command[i + 1].strip_prefix("/etc/rootzone/").unwrap();
            let local = repo(&format!("config/{file}"));
            assert!(local.is_file(), "{name}: {file} is not in config/");
            match command[0].as_str() {
                "serve" => {
                    rootzone::service::Settings::load(Some(&local)).unwrap();
                }
                _ => {
                    rootzone::fieldsim::FieldSimSettings::load(
                        Some(&local),
                        Some("http://controller:8080"),
                    )
                    .unwrap();
                }
            }
        }
        // every variable is one the binary reads
        let env = yaml_map(&service["environment"]);
        for (k, _) in env.iter().chain(&shared) {
            assert!(allowed.contains(k), "{name}: {k} is not read by rootzone");
        }
        // ports: the published port is the one the process listens on, and
        // the healthcheck asks that port
        let listen = env
            .iter()
            .find(|(k, _)| k == "ROOTZONE_LISTEN" || k == "ROOTZONE_SIM_LISTEN")
            .map(|(_, v)| v.rsplit(':').next().unwrap().to_string());
        if let (Some(port), Yaml::Array(ports)) = (&listen, &service["ports"]) {
            for p in ports {
                let inner = p.as_str().unwrap().rsplit(':').next().unwrap();
                assert_eq!(inner, port, "{name}: published {p:?} but listens on {port}");
            }
        }
        if let (Some(port), Yaml::Array(test)) = (&listen, &service["healthcheck"]["test"]) {
            let url = test
                .iter()
                .filter_map(|v| v.as_str())
                .find(|v| v.starts_with("http"))
                .unwrap();
            assert!(
                url.contains(&format!(":{port}/healthz")),
                "{name}: healthcheck {url}"
            );
        }
    }
    // profiles: every service has one (a plain `up` starts no stray
    // controller); in each, one controller and one simulator, the host port
    // published once, its own volumes; the simulator reaches its own
    // controller and is reached at its own name
    let dockerfile = std::fs::read_to_string(repo("deploy/Dockerfile")).unwrap();
    let mut profiles: std::collections::BTreeMap<String, Vec<String>> = Default::default();
    for (name, service) in services {
        let name = name.as_str().unwrap().to_string();
        let p = service["profiles"]
            .as_vec()
            .unwrap_or_else(|| panic!("{name} has no profile"));
        assert_eq!(p.len(), 1, "{name}: one profile");
        profiles
            .entry(p[0].as_str().unwrap().to_string())
            .or_default()
            .push(name);
    }
    let mut volumes_seen = BTreeSet::new();
    for (profile, names) in &profiles {
        let of = |sub: &str| -> &str {
            names
                .iter()
                .find(|n| doc["services"][n.as_str()]["command"][0].as_str() == Some(sub))
                .unwrap_or_else(|| panic!("profile {profile} has no {sub}"))
        };
        let (controller, field) = (of("serve"), of("field-sim"));
        let mut ports = BTreeSet::new();
        for n in names {
            let s = &doc["services"][n.as_str()];
            for p in s["ports"].as_vec().into_iter().flatten() {
                let host = p.as_str().unwrap().split(':').next().unwrap().to_string();
                assert!(ports.insert(host), "{profile}: port {p:?} published twice");
            }
            for v in s["volumes"].as_vec().into_iter().flatten() {
                let (volume, target) = v.as_str().unwrap().split_once(':').unwrap();
                assert!(volumes_seen.insert(volume.to_string()), "{volume} shared");
                assert!(
                    !doc["volumes"][volume].is_badvalue(),
                    "{volume} is not declared"
                );
                // the image makes the mount point, owned by its user
                assert!(
                    dockerfile.contains(target),
                    "{n}: {target} not made in the image"
                );
                assert!(
                    dockerfile.contains("chown -R rootzone"),
                    "mount points not owned"
                );
                let dir = yaml_map(&s["environment"])
                    .into_iter()
                    .find(|(k, _)| k.ends_with("DATA_DIR"))
                    .unwrap()
                    .1;
                assert_eq!(dir, target, "{n}: data folder is not the volume");
            }
        }
        let cmd: Vec<&str> = doc["services"][field]["command"]
            .as_vec()
            .unwrap()
            .iter()
            .filter_map(|v| v.as_str())
            .collect();
        let url = cmd[cmd.iter().position(|a| *a == "--controller").unwrap() + 1];
        assert_eq!(url, format!("http://{controller}:8080"));
        let env = yaml_map(&doc["services"][field]["environment"]);
        let public = &env
            .iter()
            .find(|(k, _)| k == "ROOTZONE_PUBLIC_URL")
            .unwrap()
            .1;
        assert_eq!(public, &format!("http://{field}:9090"));
        // both sides on one clock
        let clock = |n: &str| {
            yaml_map(&doc["services"][n]["environment"])
                .into_iter()
                .filter(|(k, _)| k.starts_with("ROOTZONE_CLOCK__"))
                .collect::<Vec<_>>()
        };
        assert_eq!(clock(controller), clock(field), "{profile}: clocks differ");
    }
    assert_eq!(
        profiles.keys().cloned().collect::<Vec<_>>(),
        ["demo", "live"]
    );
}

#[test]
fn a_five_day_pairing_run_matches_the_in_process_closed_loop() {
    use rootzone::experiment::ExperimentOptions;
    use rootzone::experiment::closed_loop::{ControllerKind, Models, Scenario, run};
    // two clock hours per real second: five days in a minute
    let pair = Pair::new(7_200.0);
    // the field starts at a clock midnight 3–15 s ahead, as the in-process
    // loop starts at the scenario's hour 0
    let epoch: chrono::DateTime<chrono::Utc> = pair.epoch.parse().unwrap();
    let start = (epoch + chrono::TimeDelta::hours(30))
        .date_naive()
        .and_hms_opt(0, 0, 0)
        .unwrap()
        .and_utc();
    let config = pair.dir.path().join("field.toml");
    std::fs::write(
        &config,
        format!(
            r#"
[[fields]]
name = "five-day"
model = "two-layer"
# 167 ms of real time for the boundary's measurement to arrive
measurement_wait_s = 1200.0
[fields.simulation]
scenario = "dry"
process_noise = 0.0
measurement_noise = 0.0
forecast_error = 0.0
seed = 7
measurement_interval_s = 900.0
initial_head = -0.2
start = "{}"
"#,
            start.to_rfc3339()
        ),
    )
    .unwrap();
    let _controller = pair.controller();
    let _field = pair.field(&config);
    let base = pair.base();
    let id = wait_for(30, "registration", || {
        get(&format!("{base}/v1/fields"))?.as_array()?.first()?["id"].as_i64()
    });
    let fp = format!("{base}/v1/fields/{id}");
    // the cycles from the start on (the earlier ones had no measurement)
    let from_start = |sp: &Value| -> Vec<Value> {
        sp.as_array()
            .unwrap()
            .iter()
            .filter(|s| {
                s["time"]
                    .as_str()
                    .unwrap()
                    .parse::<chrono::DateTime<chrono::Utc>>()
                    .unwrap()
                    >= start
            })
            .cloned()
            .collect()
    };
    let setpoints = wait_for(200, "60 control cycles", || {
        let sp = from_start(&get(&format!("{fp}/setpoints?limit=1000"))?);
        (sp.len() >= 61).then_some(sp)
    });
    let cycles = &setpoints[..60];
    // the cycles ran on the measurement of their own boundary (a process
    // starved for a sixth of a second on a loaded machine misses one)
    let on_time = cycles
        .iter()
        .filter(|c| c["measured_at"] == c["time"])
        .count();
    assert!(
        on_time >= 54,
        "{on_time} of 60 cycles on their boundary's measurement"
    );
    let paired: f64 = cycles
        .iter()
        .map(|s| s["amount_mm"].as_f64().unwrap())
        .sum();
    let last_cycle: chrono::DateTime<chrono::Utc> =
        cycles[59]["valid_until"].as_str().unwrap().parse().unwrap();
    let theta = wait_for(30, "the last measurement", || {
        let m = get(&format!("{fp}/measurements?limit=100000"))?;
        m.as_array()?
            .iter()
            .rev()
            .find(|m| {
                m["time"]
                    .as_str()
                    .and_then(|t| t.parse::<chrono::DateTime<chrono::Utc>>().ok())
                    <= Some(last_cycle)
            })
            .and_then(|m| m["theta"].as_f64())
            .filter(|_| true)
    });
    // the same field, weather and controller in process
    let options = ExperimentOptions {
        models: repo("models"),
        out: pair.dir.path().join("reports"),
        seed: 7,
        cache: pair.dir.path().join("cache"),
        samples: 1000,
        seeds: 1,
    };
    let models = Models::load(&options).unwrap();
    let scenario = Scenario {
        process_noise: 0.0,
        ..Scenario::e4()
    };
    let in_process = run(ControllerKind::TwoLayer, &models, &scenario, 7)
        .unwrap()
        .total_irrigation_mm();
    eprintln!(
        "I_T paired {paired:.2} mm, in process {in_process:.2} mm; final θ {theta:.4}; \
         {on_time} of 60 cycles on time"
    );
    assert!(
        (paired - in_process).abs() <= 0.05 * in_process,
        "I_T paired {paired} vs in process {in_process}"
    );
    assert!(
        (0.18..=0.23).contains(&theta),
        "final θ {theta} outside the zone"
    );
}

/// curl POST of a setpoint body to `url` with extra headers; the status.
fn post_setpoint(url: &str, headers: &[String], body: &str) -> u16 {
    let mut cmd = Command::new("curl");
    cmd.args(["-s", "-o", "/dev/null", "-w", "%{http_code}", "-X", "POST"]);
    cmd.args(["-H", "Content-Type: application/json"]);
    for h in headers {
        cmd.args(["-H", h]);
    }
    let out = cmd.args(["--data", body, url]).output().unwrap();
    String::from_utf8_lossy(&out.stdout).parse().unwrap_or(0)
}

#[test]
fn the_simulator_refuses_forged_setpoints_and_says_when_its_token_is_rejected() {
    let pair = Pair::new(1.0);
    let _controller = pair.controller();
    let sim_port = free_port();
    let mut env = pair.clock_env();
    env.push(("ROOTZONE_SIM_LISTEN", format!("127.0.0.1:{sim_port}")));
    env.push((
        "ROOTZONE_SIM_DATA_DIR",
        pair.dir.path().join("field").display().to_string(),
    ));
    let config = repo("config/compose-field.toml").display().to_string();
    let (_field, line) = spawn(
        &[
            "field-sim",
            "--controller",
            &pair.base(),
            "--config",
            &config,
        ],
        &env,
    );
    assert!(line.contains("setpoints at"), "{line}");
    let url = format!("http://127.0.0.1:{sim_port}/fields/compose-field/setpoint");
    let now = chrono::Utc::now();
    let body = |rate: f64| {
        serde_json::json!({
            "field_id": 1, "time": now, "valid_from": now,
            "valid_until": now + chrono::TimeDelta::hours(2), "rate": rate,
            "amount_mm": rate * 7.2e6, "plan": [], "predicted_theta": [], "zone": [],
            "model": "two-layer", "status": "converged", "iterations": 1,
            "solve_ms": 1.0, "degraded": [], "bias": 0.0
        })
        .to_string()
    };
    // no credentials, a made-up signature, a wrong token
    assert_eq!(post_setpoint(&url, &[], &body(1.0)), 401);
    let ts = now.timestamp().to_string();
    let forged = [
        format!("X-Rootzone-Timestamp: {ts}"),
        "X-Rootzone-Signature: sha256=00ff".to_string(),
        "X-Rootzone-Delivery: 5b0c3d0e-0000-4000-8000-000000000000".to_string(),
    ];
    assert_eq!(post_setpoint(&url, &forged, &body(1e-6)), 401);
    let wrong = ["Authorization: Bearer not-the-simulator-token".to_string()];
    assert_eq!(post_setpoint(&url, &wrong, &body(1e-6)), 403);
    // the operator's token: a rate beyond the field's irrigation_max is
    // refused, one within it applied
    let token = std::fs::read_to_string(pair.dir.path().join("field/sim-token")).unwrap();
    let operator = [format!("Authorization: Bearer {}", token.trim())];
    assert_eq!(post_setpoint(&url, &operator, &body(1.0)), 422);
    assert_eq!(post_setpoint(&url, &operator, &body(1e-6)), 204);

    // a simulator with the wrong controller token says so
    let mut env = pair.clock_env();
    env[0].1 = "not-the-controller-token".into();
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_rootzone"));
    cmd.args([
        "field-sim",
        "--controller",
        &pair.base(),
        "--config",
        &config,
    ])
    .env("ROOTZONE_SIM_LISTEN", "127.0.0.1:0")
    .env(
        "ROOTZONE_SIM_DATA_DIR",
        pair.dir.path().join("other").display().to_string(),
    )
    .env("RUST_LOG", "warn")
    .stdout(Stdio::null())
    .stderr(Stdio::piped());
    for (k, v) in &env {
        cmd.env(k, v);
    }
    // it stops at once (exit 2), saying what to set
    let out = cmd.output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(
        err.contains("token was rejected") && err.contains("ROOTZONE_API_TOKEN"),
        "{err}"
    );
}
