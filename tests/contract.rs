//! `openapi.yaml` is the truth: schemathesis (pinned in
//! `ci/requirements-schemathesis.txt`, installed into a venv under `target/`
//! on first use) runs every check it has against the real daemon, with a
//! bounded number of examples and a fixed seed, and must find nothing.

mod common;
use common::*;

use std::path::{Path, PathBuf};
use std::process::Command;

fn repo(path: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(path)
}

/// The venv's `st`, created (pip install of the pinned version) if missing.
fn schemathesis() -> PathBuf {
    let venv = Path::new(env!("CARGO_TARGET_TMPDIR")).join("schemathesis-venv");
    let st = venv.join("bin").join("st");
    let requirements = repo("ci/requirements-schemathesis.txt");
    let marker = venv.join("installed.txt");
    let wanted = std::fs::read_to_string(&requirements).unwrap();
    if std::fs::read_to_string(&marker).ok().as_deref() == Some(wanted.as_str()) && st.exists() {
        return st;
    }
    let ok = Command::new("python3")
        .args(["-m", "venv"])
        .arg(&venv)
        .status()
        .expect("python3 runs (the contract test needs it for schemathesis)")
        .success();
    assert!(ok, "python3 -m venv {} failed", venv.display());
    let ok = Command::new(venv.join("bin").join("pip"))
        .args(["install", "--quiet", "--disable-pip-version-check", "-r"])
        .arg(&requirements)
        .status()
        .unwrap()
        .success();
    assert!(ok, "pip install -r {} failed", requirements.display());
    std::fs::write(&marker, wanted).unwrap();
    st
}

#[test]
fn schemathesis_finds_nothing_with_every_check() {
    let st = schemathesis();
    let dir = tempfile::tempdir().unwrap();
    // the jobs schemathesis starts train a tiny plan (seconds, not minutes)
    let d = start(
        dir.path(),
        &config(
            "[training]\nimpulse_samples = 300\nsub_model_samples = 0\n\
             validation_samples = 120\nmax_epochs = 1\nhorizon = 5",
        ),
    );
    let out = Command::new(&st)
        .arg("--config-file")
        .arg(repo("ci/schemathesis.toml"))
        .arg("run")
        .arg(repo("openapi.yaml"))
        .args(["--url", &d.base, "--checks", "all"])
        .args(["-H", &format!("Authorization: Bearer {TOKEN}")])
        .args(["--max-examples", "25", "--seed", "1", "--no-color"])
        .env("SCHEMATHESIS_HOOKS", "")
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    let summary: String = text
        .lines()
        .skip_while(|l| !l.contains("SUMMARY"))
        .collect::<Vec<_>>()
        .join("\n");
    println!("{summary}");
    assert!(
        out.status.success(),
        "schemathesis found problems:\n{text}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(text.contains("passed"), "{text}");
}
