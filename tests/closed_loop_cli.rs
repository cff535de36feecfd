//! `rootzone closed-loop`, run as the real binary with few steps.

use std::process::{Command, Output};

fn rootzone(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_rootzone"))
        .arg("closed-loop")
        .args(args)
        .output()
        .expect("binary runs")
}

fn json(out: &Output) -> serde_json::Value {
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).expect("JSON on stdout")
}

#[test]
fn the_estimated_controller_reports_scores_estimates_and_a_trace() {
    let dir = tempfile::tempdir().unwrap();
    let trace = dir.path().join("trace.csv");
    let out = rootzone(&[
        "--plant",
        "ks=6.15e-6,alpha=9.75,n=1.89,theta_r=0.065,theta_s=0.41",
        "--controller",
        "richards",
        "--prior",
        "sandy-loam",
        "--steps",
        "4",
        "--process-noise",
        "0.02",
        "--measurement-noise",
        "0.02",
        "--forecast-error",
        "0.2",
        "--seed",
        "3",
        "--sensor-depths",
        "0.125,0.3",
        "--trace",
        trace.to_str().unwrap(),
    ]);
    let v = json(&out);
    for key in [
        "irrigation_mm",
        "dry_violation",
        "wet_violation_after_entry",
        "total_violation",
    ] {
        assert!(v[key].as_f64().is_some_and(f64::is_finite), "{key}: {v}");
    }
    for key in ["mean", "median", "p95"] {
        assert!(v["solve_ms"][key].as_f64().is_some(), "{v}");
    }
    // 4 steps are all inside the first day: nothing scored yet
    assert!(
        v["sensor_rmse"].is_null() && v["profile_rmse"].is_null(),
        "{v}"
    );
    let parameters = v["parameters"].as_array().unwrap();
    assert_eq!(parameters.len(), 5);
    let ks = &parameters[0];
    assert_eq!(ks["name"], "ks");
    assert!((ks["truth"].as_f64().unwrap() - 6.15e-6).abs() < 1e-12);
    assert!(ks["sd"].as_f64().unwrap() > 0.0);
    let text = std::fs::read_to_string(&trace).unwrap();
    assert_eq!(text.lines().count(), 5, "{text}");
    assert!(text.starts_with("step,irrigation_mm"));
}

#[test]
fn the_oracle_and_a_surrogate_run_on_sandy_loam() {
    for controller in ["oracle", "two-layer"] {
        let v = json(&rootzone(&[
            "--plant",
            "sandy-loam",
            "--controller",
            controller,
            "--steps",
            "3",
        ]));
        assert_eq!(v["controller"], controller);
        assert_eq!(v["steps"], 3);
        assert!(v["parameters"].as_array().unwrap().is_empty());
    }
}

#[test]
fn bad_arguments_exit_2_with_a_message() {
    let seventeen = ["0.1"; 17].join(",");
    let cases: [(&[&str], &str); 9] = [
        (
            &[
                "--plant",
                "loam",
                "--controller",
                "richards",
                "--sensor-depths",
                &seventeen,
            ],
            "at most 16 sensors, got 17",
        ),
        (
            &["--plant", "loam", "--controller", "oracle", "--steps", "0"],
            "1 … 10000, got 0",
        ),
        (
            &[
                "--plant",
                "loam",
                "--controller",
                "oracle",
                "--steps",
                "10001",
            ],
            "1 … 10000, got 10001",
        ),
        (&["--plant", "peat", "--controller", "oracle"], "peat"),
        (&["--plant", "sandy-loam", "--controller", "pid"], "pid"),
        (
            &["--plant", "loam", "--controller", "two-layer"],
            "sandy loam",
        ),
        (
            &[
                "--plant",
                "ks=1e-5,alpha=7,n=0.9,theta_r=0.05,theta_s=0.4",
                "--controller",
                "oracle",
            ],
            "n",
        ),
        (
            &[
                "--plant",
                "sand",
                "--controller",
                "richards",
                "--sensor-depths",
                "0.7",
            ],
            "0.7",
        ),
        (
            &[
                "--plant",
                "sand",
                "--controller",
                "richards",
                "--prior",
                "chalk",
            ],
            "chalk",
        ),
    ];
    for (args, needle) in cases {
        let out = rootzone(args);
        assert_eq!(out.status.code(), Some(2), "{args:?}");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(needle), "{args:?}: {err}");
    }
}
