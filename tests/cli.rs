//! The `rootzone simulate` command, run as the real binary.

use std::path::Path;
use std::process::{Command, Output};

fn rootzone(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_rootzone"))
        .args(args)
        .output()
        .expect("binary runs")
}

fn data(name: &str) -> String {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("data")
        .join(name)
        .display()
        .to_string()
}

fn write(dir: &Path, name: &str, text: &str) -> String {
    let path = dir.join(name);
    std::fs::write(&path, text).unwrap();
    path.display().to_string()
}

fn schedule(steps: usize, rate: f64) -> String {
    let mut text = String::from("step,irrigation_m_per_s\n");
    for k in 0..steps {
        text.push_str(&format!("{k},{rate}\n"));
    }
    text
}

const COLUMNS: &str = "step,hour,irrigation_m_per_s,et0_mm,precip_mm,theta,theta_measured,\
storage_mm,infiltration_mm,runoff_mm,drainage_mm,uptake_mm";

#[test]
fn simulate_writes_one_row_per_step_with_a_closed_balance() {
    let dir = tempfile::tempdir().unwrap();
    let irrigation = write(dir.path(), "irr.csv", &schedule(96, 2e-7));
    let out = dir.path().join("out.csv");
    let result = rootzone(&[
        "simulate",
        "--weather",
        &data("weather-rain.csv"),
        "--irrigation",
        &irrigation,
        "--steps",
        "24",
        "--measurement-noise",
        "0.05",
        "--seed",
        "4",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(
        result.status.success(),
        "{}",
        String::from_utf8_lossy(&result.stderr)
    );
    let text = std::fs::read_to_string(&out).unwrap();
    let mut lines = text.lines();
    assert_eq!(lines.next().unwrap(), COLUMNS);
    let rows: Vec<Vec<f64>> = lines
        .map(|l| l.split(',').map(|v| v.parse().unwrap()).collect())
        .collect();
    assert_eq!(rows.len(), 24);
    let initial_storage =
        26.0 * (0.5 / 26.0) * rootzone::soil::VanGenuchten::SANDY_LOAM.storage(-0.2) * 1e3;
    for (k, r) in rows.iter().enumerate() {
        assert_eq!(r[0], k as f64);
        assert_eq!(r[1], 2.0 * (k + 1) as f64);
        assert!((r[6] / r[5] - 1.0).abs() <= 0.05 + 1e-6);
        // storage − initial = infiltration − drainage − uptake (mm, printed to 1e-6)
        let balance = r[7] - initial_storage - (r[8] - r[10] - r[11]);
        assert!(balance.abs() < 1e-5, "row {k}: {balance}");
        // 2e-7 m/s over 2 h is 1.44 mm per step; with the rain, all of it infiltrates.
        let supplied: f64 = rows[..=k].iter().map(|r| 1.44 + r[4]).sum();
        assert!(
            (r[8] - supplied).abs() < 1e-5,
            "row {k}: {} vs {supplied}",
            r[8]
        );
        assert_eq!(r[9], 0.0);
    }
}

/// `rootzone simulate` of a loam under the dry weather, with more arguments.
fn simulate_loam(irrigation: &str, more: &[&str]) -> Output {
    let weather = data("weather-dry.csv");
    let mut args = vec![
        "simulate",
        "--weather",
        &weather,
        "--irrigation",
        irrigation,
        "--soil",
        "loam",
    ];
    args.extend_from_slice(more);
    rootzone(&args)
}

#[test]
fn simulate_without_out_writes_to_stdout() {
    let dir = tempfile::tempdir().unwrap();
    let irrigation = write(dir.path(), "irr.csv", &schedule(3, 0.0));
    let result = simulate_loam(&irrigation, &[]);
    assert!(result.status.success());
    let text = String::from_utf8(result.stdout).unwrap();
    assert_eq!(text.lines().count(), 4);
    assert_eq!(text.lines().next().unwrap(), COLUMNS);
}

/// An output that is not a regular file (here a named pipe; `/dev/null` is
/// the common case) is written in place. The atomic write renamed its
/// temporary file over it, which replaced `/dev/null` with a regular file
/// when run as root.
#[test]
fn simulate_writes_into_a_named_pipe_without_replacing_it() {
    use std::os::unix::fs::FileTypeExt;
    let dir = tempfile::tempdir().unwrap();
    let irrigation = write(dir.path(), "irr.csv", &schedule(3, 0.0));
    let fifo = dir.path().join("out.fifo");
    let made = std::process::Command::new("mkfifo")
        .arg(&fifo)
        .status()
        .unwrap();
    assert!(made.success());
    let reader = {
        let fifo = fifo.clone();
        std::thread::spawn(move || std::fs::read_to_string(fifo).unwrap())
    };
    let result = simulate_loam(&irrigation, &["--out", fifo.to_str().unwrap()]);
    assert!(result.status.success(), "{result:?}");
    let kind = std::fs::symlink_metadata(&fifo).unwrap().file_type();
    assert!(kind.is_fifo(), "the pipe was replaced: {kind:?}");
    let text = reader.join().unwrap();
    assert_eq!(text.lines().count(), 4);
    assert_eq!(text.lines().next().unwrap(), COLUMNS);
}

/// A soil given by its parameters simulates exactly as the texture of the
/// same parameters, and another soil gives another run.
#[test]
fn simulate_takes_a_soil_by_its_parameters() {
    let dir = tempfile::tempdir().unwrap();
    let irrigation = write(dir.path(), "irr.csv", &schedule(12, 2e-6));
    let run = |soil: &str| {
        let result = rootzone(&[
            "simulate",
            "--weather",
            &data("weather-rain.csv"),
            "--irrigation",
            &irrigation,
            "--soil",
            soil,
        ]);
        assert!(result.status.success(), "{soil}: {result:?}");
        String::from_utf8(result.stdout).unwrap()
    };
    let loam = rootzone::soil::Texture::Loam.parameters();
    let by_parameters = format!(
        "ks={:e},alpha={:e},n={:e},theta_r={:e},theta_s={:e}",
        loam.saturated_conductivity,
        loam.alpha,
        loam.n,
        loam.residual_water_content,
        loam.saturated_water_content
    );
    assert_eq!(run("loam"), run(&by_parameters));
    assert_ne!(
        run("loam"),
        run(&by_parameters.replace("alpha=", "alpha=1"))
    );
}

/// A weather file's amounts have the API's ranges: 4 mm of ET0 in a 2-h
/// step is 2 mm/h, the most, and 4.5 is refused, naming the file, the line
/// and the value, with no output file.
#[test]
fn a_weather_file_beyond_the_documented_rates_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let irrigation = write(dir.path(), "irr.csv", &schedule(2, 1e-7));
    let out = dir.path().join("out.csv");
    let run = |weather: &str| {
        let hot = write(dir.path(), "hot.csv", weather);
        let result = rootzone(&[
            "simulate",
            "--weather",
            &hot,
            "--irrigation",
            &irrigation,
            "--out",
            out.to_str().unwrap(),
        ]);
        (hot, result)
    };
    let (_, ok) = run("step,start_hour,et0_mm,precip_mm\n0,0,4,800\n1,2,4,0\n");
    assert_eq!(ok.status.code(), Some(0), "{ok:?}");
    std::fs::remove_file(&out).unwrap();
    let (hot, refused) = run("step,start_hour,et0_mm,precip_mm\n0,0,4,0\n1,2,4.5,0\n");
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert_eq!(refused.status.code(), Some(2), "{stderr}");
    assert!(
        stderr.contains(&format!("{hot}:3")) && stderr.contains("et0_mm = 4.5 exceeds 4 mm"),
        "{stderr}"
    );
    assert!(!out.exists());
}

/// Each bad input: exit code 2, one line naming the file (and line and value
/// where there is one), and no output file.
#[test]
fn bad_input_exits_2_with_a_clear_message_and_no_output() {
    let dir = tempfile::tempdir().unwrap();
    let good = write(dir.path(), "good.csv", &schedule(96, 1e-7));
    let negative = write(
        dir.path(),
        "neg.csv",
        "step,irrigation_m_per_s\n0,1e-7\n1,-2e-7\n",
    );
    let text = write(dir.path(), "text.csv", "step,irrigation_m_per_s\n0,abc\n");
    let nan = write(
        dir.path(),
        "nan.csv",
        "step,irrigation_m_per_s\n0,1e-7\n1,1e-7\n2,NaN\n",
    );
    // the largest rate a field may be given is 1e-4 m/s
    let flood = write(
        dir.path(),
        "flood.csv",
        "step,irrigation_m_per_s\n0,1e-4\n1,1.5e-4\n",
    );
    let ragged = write(
        dir.path(),
        "ragged.csv",
        "step,irrigation_m_per_s\n0,1e-7,3\n",
    );
    let long = write(dir.path(), "long.csv", &schedule(200, 1e-7));
    let weather = data("weather-dry.csv");
    let missing = dir.path().join("nope.csv").display().to_string();
    let cases: Vec<(Vec<&str>, Vec<String>)> = vec![
        (
            vec!["--irrigation", &negative],
            vec![format!("{negative}:3"), "-2e-7".into()],
        ),
        (
            vec!["--irrigation", &text],
            vec![format!("{text}:2"), "'abc'".into()],
        ),
        (
            vec!["--irrigation", &nan],
            vec![format!("{nan}:4"), "NaN".into()],
        ),
        (vec!["--irrigation", &ragged], vec![format!("{ragged}:2")]),
        (
            vec!["--irrigation", &flood],
            vec![format!("{flood}:3"), "1.5e-4".into(), "0.0001 m/s".into()],
        ),
        (vec!["--irrigation", &missing], vec![missing.clone()]),
        (
            vec!["--irrigation", &long],
            vec![format!("{weather}:98"), "96 steps, 200".into()],
        ),
        (
            vec!["--irrigation", &long, "--steps", "97"],
            vec![weather.clone(), "97".into()],
        ),
        (
            vec!["--irrigation", &good, "--steps", "97"],
            vec![format!("{good}:98"), "97".into()],
        ),
        (
            vec!["--irrigation", &good, "--soil", "peat"],
            vec!["peat".into()],
        ),
        (
            vec![
                "--irrigation",
                &good,
                "--soil",
                "ks=1e-6,alpha=2,n=1,theta_r=0.05,theta_s=0.4",
            ],
            vec!["--soil".into(), "n must be > 1".into()],
        ),
        (
            vec!["--irrigation", &good, "--process-noise=-1"],
            vec!["process noise".into()],
        ),
    ];
    for (extra, needles) in cases {
        let out = dir.path().join("out.csv");
        let mut args = vec![
            "simulate",
            "--weather",
            &weather,
            "--out",
            out.to_str().unwrap(),
        ];
        args.extend(extra.iter().copied());
        let result = rootzone(&args);
        let stderr = String::from_utf8_lossy(&result.stderr);
        assert_eq!(result.status.code(), Some(2), "{args:?}: {stderr}");
        assert_eq!(stderr.trim().lines().count(), 1, "{stderr}");
        for needle in &needles {
            assert!(
                stderr.contains(needle.as_str()),
                "{args:?}: '{stderr}' lacks '{needle}'"
            );
        }
        assert!(!out.exists(), "{args:?} left an output file");
    }
}
