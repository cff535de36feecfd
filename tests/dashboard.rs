//! The dashboard in a real headless browser (Debian's chromium; `.ci/run`
//! installs it): the page loads without console errors, lists every field,
//! and its chart has data, at a wide screen's and a phone's width.
//! Screenshots are written to `target/test-artefacts/dashboard.png` and
//! `dashboard-phone.png`.

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

struct Daemon(Child);

impl Drop for Daemon {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn chromium() -> String {
    for name in ["chromium", "chromium-browser", "google-chrome"] {
        if Command::new(name)
            .arg("--version")
            .output()
            .is_ok_and(|o| o.status.success())
        {
            return name.to_string();
        }
    }
    panic!("no chromium on this machine: .ci/run installs it (apt-get install chromium)");
}

#[test]
fn the_dashboard_shows_every_field_with_a_chart_in_a_real_browser() {
    let browser = chromium();
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("rootzone.toml");
    // two simulated fields, 2 h of clock time per real second
    std::fs::write(
        &config,
        r#"
[clock]
speedup = 7200.0
[[fields]]
name = "east plot"
actuator = { kind = "simulated" }
[fields.simulation]
seed = 3
[[fields]]
name = "west plot"
actuator = { kind = "simulated" }
[fields.simulation]
scenario = "rain"
seed = 4
"#,
    )
    .unwrap();
    let mut child = Command::new(env!("CARGO_BIN_EXE_rootzone"))
        .args(["serve", "--config"])
        .arg(&config)
        .env("ROOTZONE_LISTEN", "127.0.0.1:0")
        .env("ROOTZONE_DATA_DIR", dir.path().join("data"))
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut reader = BufReader::new(child.stdout.take().unwrap());
    let mut line = String::new();
    reader.read_line(&mut line).unwrap();
    std::thread::spawn(move || std::io::copy(&mut reader, &mut std::io::sink()));
    let _daemon = Daemon(child);
    let base = line
        .split_whitespace()
        .find(|w| w.starts_with("http://"))
        .unwrap()
        .to_string();
    // wait for a few control cycles
    let deadline = Instant::now() + Duration::from_secs(90);
    loop {
        let out = Command::new("curl")
            .args(["-s", &format!("{base}/v1/fields/2/setpoints")])
            .output()
            .unwrap();
        let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap_or_default();
        // the rain scenario rains from hour 38 of the field's first day: wait
        // until a cycle has planned with rain in its own period
        let rained = |a: &Vec<serde_json::Value>| {
            a.iter()
                .any(|s| s["rain_mm"][0].as_f64().is_some_and(|r| r > 0.0))
        };
        if v.as_array().is_some_and(|a| a.len() >= 3 && rained(a)) {
            break;
        }
        assert!(Instant::now() < deadline, "no control cycles");
        std::thread::sleep(Duration::from_millis(300));
    }
    // the chart has data
    let svg = Command::new("curl")
        .args(["-s", &format!("{base}/v1/fields/1/chart.svg?hours=24")])
        .output()
        .unwrap();
    let svg = String::from_utf8_lossy(&svg.stdout);
    assert!(svg.starts_with("<svg"), "{svg}");
    assert!(
        svg.matches("<circle").count() >= 10,
        "too few measured points"
    );
    assert!(svg.contains("<polyline"), "no lines");
    // the lower panel's legend: irrigation, past and forecast rain, ET0;
    // the upper one's: the prediction with and without the irrigation
    for label in [
        "irrigation",
        "rain (as forecast for its period)",
        "forecast rain",
        "ET0 (past and forecast)",
        "predicted θ (planned irrigation)",
        "predicted θ without irrigation",
        "measured θ",
        "true θ",
    ] {
        assert!(svg.contains(label), "legend '{label}' missing: {svg}");
    }
    // the rain scenario's field draws rain bars (past, in cyan)
    let svg = Command::new("curl")
        .args(["-s", &format!("{base}/v1/fields/2/chart.svg?hours=24")])
        .output()
        .unwrap();
    let svg = String::from_utf8_lossy(&svg.stdout);
    assert!(
        svg.to_ascii_uppercase().contains("FILL=\"#17BECF\""),
        "no past rain bars on the rain field: {svg}"
    );
    // the profile: the estimate's band and line, the simulated truth
    let svg = Command::new("curl")
        .args(["-s", &format!("{base}/v1/fields/1/profile.svg")])
        .output()
        .unwrap();
    let svg = String::from_utf8_lossy(&svg.stdout);
    assert!(svg.starts_with("<svg"), "{svg}");
    assert!(svg.contains("<polygon"), "no uncertainty band: {svg}");
    assert!(
        svg.contains("estimated θ") && svg.contains("true θ"),
        "{svg}"
    );
    assert!(svg.matches("<polyline").count() >= 2, "no profile lines");

    let profile = dir.path().join("chromium-profile");
    let run = |size: &str, extra: &[&str]| {
        Command::new(&browser)
            .args([
                "--headless",
                "--no-sandbox",
                "--disable-gpu",
                "--disable-background-networking",
                "--disable-component-update",
                "--disable-sync",
                "--no-first-run",
                "--enable-logging=stderr",
                "--v=0",
                "--virtual-time-budget=5000",
            ])
            .arg(format!("--window-size={size}"))
            .arg(format!("--user-data-dir={}", profile.display()))
            .args(extra)
            .arg(format!("{base}/"))
            .output()
            .unwrap()
    };
    let out_dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("target/test-artefacts");
    std::fs::create_dir_all(&out_dir).unwrap();
    // a wide screen and a phone
    for (size, name) in [
        ("1200,1400", "dashboard.png"),
        ("360,1400", "dashboard-phone.png"),
    ] {
        let dom = run(size, &["--dump-dom"]);
        let html = String::from_utf8_lossy(&dom.stdout);
        let log = String::from_utf8_lossy(&dom.stderr);
        for l in log.lines() {
            assert!(
                !(l.contains("CONSOLE") || l.contains("Uncaught")),
                "console message: {l}"
            );
        }
        assert!(html.contains("data-fields=\"2\""), "{html}");
        for name in ["east plot (#1)", "west plot (#2)"] {
            assert!(html.contains(name), "{name} missing: {html}");
        }
        // units, the zone in both forms, when the last reading came and
        // the next cycle is due (in the browser's zone: UTC here)
        for unit in [
            "θ [m³/m³]",
            "[mm / period]",
            "water today / week / season [mm]",
        ] {
            assert!(html.contains(unit), "{unit} missing: {html}");
        }
        assert!(html.contains("0.180–0.230 (h -0.43…-0.27 m)"), "{html}");
        assert_eq!(html.matches("class=\"due\"").count(), 2, "{html}");
        assert_eq!(html.matches("class=\"last\"").count(), 2, "{html}");
        assert_eq!(html.matches("class=\"water\"").count(), 2, "{html}");
        assert!(html.contains(" UTC (in "), "{html}");
        // every decision explained in words
        assert_eq!(html.matches("class=\"why\">Irrigate ").count(), 2, "{html}");
        assert!(html.contains("optimiser: "), "{html}");
        assert!(
            html.contains(" with this irrigation, ") && html.contains(" without"),
            "no prediction without irrigation in the explanation: {html}"
        );
        assert_eq!(
            html.matches("data-loaded=\"yes\"").count(),
            4,
            "charts not loaded: {html}"
        );
        // the screenshot, kept as a test artefact
        let shot = out_dir.join(name);
        let _ = std::fs::remove_file(&shot);
        let r = run(size, &[&format!("--screenshot={}", shot.display())]);
        assert!(r.status.success());
        let png = std::fs::read(&shot).unwrap();
        assert!(
            png.starts_with(b"\x89PNG") && png.len() > 10_000,
            "{} bytes",
            png.len()
        );
    }
}
