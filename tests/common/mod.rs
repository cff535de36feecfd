//! Helpers of the tests that drive the real daemon over HTTP with curl.
#![allow(dead_code)]

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};

use serde_json::Value;

pub mod postgres;

pub const TOKEN: &str = "test-token-0123456789";

pub struct Daemon {
    pub child: Child,
    pub base: String,
}

impl Daemon {
    /// Asks the daemon to stop (SIGTERM).
    pub fn sigterm(&self) {
        let pid = self.child.id().to_string();
        let sent = Command::new("kill").args(["-TERM", &pid]).status();
        assert!(sent.is_ok_and(|s| s.success()), "kill -TERM {pid}");
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Whether this test binary runs the daemons on PostgreSQL: the twins of
/// the service tests (`tests/*_on_postgres.rs`) include the SQLite ones.
pub fn on_postgres() -> bool {
    env!("CARGO_CRATE_NAME").ends_with("_on_postgres")
}

/// The database of the daemon in `dir` (on the test process's server): one
/// per folder, so a daemon restarted in it finds its data.
pub fn database_of(dir: &Path) -> String {
    use std::collections::HashMap;
    use std::sync::{Mutex, OnceLock};
    static DATABASES: OnceLock<Mutex<HashMap<std::path::PathBuf, String>>> = OnceLock::new();
    let mut map = DATABASES
        .get_or_init(Default::default)
        .lock()
        .unwrap_or_else(|p| p.into_inner());
    map.entry(dir.to_path_buf())
        .or_insert_with(|| postgres::Postgres::shared().fresh_database())
        .clone()
}

/// Starts the daemon with `config` (TOML) in `dir`; returns once it listens
/// (on PostgreSQL in the `_on_postgres` twins).
pub fn start(dir: &Path, config: &str) -> Daemon {
    start_with(dir, config, &[])
}

/// [`start`] with extra environment variables.
pub fn start_with(dir: &Path, config: &str, env: &[(&str, &str)]) -> Daemon {
    let file = dir.join("rootzone.toml");
    std::fs::write(&file, config).unwrap();
    let mut command = Command::new(env!("CARGO_BIN_EXE_rootzone"));
    if on_postgres() {
        command.env("ROOTZONE_STORAGE__URL", database_of(dir));
    }
    command.envs(env.iter().copied());
    let mut child = command
        .args(["serve", "--config"])
        .arg(&file)
        .env("ROOTZONE_LISTEN", "127.0.0.1:0")
        .env("ROOTZONE_DATA_DIR", dir.join("data"))
        .env("ROOTZONE_API_TOKEN", TOKEN)
        .env(
            "RUST_LOG",
            std::env::var("RUST_LOG").unwrap_or_else(|_| "warn".into()),
        )
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .unwrap();
    let mut line = String::new();
    let mut reader = BufReader::new(child.stdout.take().unwrap());
    reader.read_line(&mut line).unwrap();
    // keep draining what the daemon prints later
    std::thread::spawn(move || std::io::copy(&mut reader, &mut std::io::sink()));
    let base = line
        .split_whitespace()
        .find(|w| w.starts_with("http://"))
        .unwrap_or_else(|| panic!("no address in '{line}'"))
        .to_string();
    Daemon { child, base }
}

/// A curl request: method, path, optional JSON body, with or without the
/// token. Returns (status, content type, body).
pub fn curl(
    d: &Daemon,
    method: &str,
    path: &str,
    body: Option<&str>,
    token: Option<&str>,
) -> (u16, String, String) {
    curl_at(&d.base, method, path, body, token)
}

/// [`curl`] against the daemon at `base` (from another thread).
pub fn curl_at(
    base: &str,
    method: &str,
    path: &str,
    body: Option<&str>,
    token: Option<&str>,
) -> (u16, String, String) {
    let mut cmd = Command::new("curl");
    cmd.args(["-s", "-X", method, "-w", "\n%{http_code}\n%{content_type}"]);
    if let Some(t) = token {
        cmd.args(["-H", &format!("Authorization: Bearer {t}")]);
    }
    if body.is_some() {
        cmd.args([
            "-H",
            "Content-Type: application/json",
            "--data-binary",
            "@-",
        ]);
        cmd.stdin(Stdio::piped());
    }
    cmd.arg(format!("{base}{path}"));
    cmd.stdout(Stdio::piped());
    let mut child = cmd.spawn().expect("curl runs");
    if let Some(b) = body {
        use std::io::Write;
        child.stdin.take().unwrap().write_all(b.as_bytes()).unwrap();
    }
    let out = child.wait_with_output().unwrap();
    let text = String::from_utf8_lossy(&out.stdout).to_string();
    let mut parts = text.rsplitn(3, '\n');
    let ctype = parts.next().unwrap_or("").to_string();
    let status = parts.next().unwrap_or("0").parse().unwrap_or(0);
    let body = parts.next().unwrap_or("").to_string();
    (status, ctype, body)
}

/// POSTs a field `spec`, asserts 201 and returns its id.
pub fn create_field(d: &Daemon, spec: Value) -> i64 {
    let r = curl(
        d,
        "POST",
        "/v1/fields",
        Some(&spec.to_string()),
        Some(TOKEN),
    );
    assert_eq!(r.0, 201, "{}", r.2);
    json_of(&r.2)["id"].as_i64().unwrap()
}

pub fn json_of(body: &str) -> Value {
    serde_json::from_str(body).unwrap_or_else(|e| panic!("not JSON ({e}): {body}"))
}

/// Asserts a problem+json error with `status` whose detail contains `needle`.
pub fn problem(r: (u16, String, String), status: u16, needle: &str) {
    assert_eq!(r.0, status, "{}", r.2);
    assert!(r.1.starts_with("application/problem+json"), "{}", r.1);
    let v = json_of(&r.2);
    assert_eq!(v["status"], status);
    let detail = v["detail"].as_str().unwrap();
    assert!(detail.contains(needle), "'{detail}' should name '{needle}'");
}

pub fn config(extra: &str) -> String {
    format!(
        "fields = []\n{extra}\n[limits]\nmax_batch = 50\nmax_future_skew_s = 300.0\nworker_threads = 2\n"
    )
}

pub fn now_minus(minutes: i64) -> String {
    (chrono::Utc::now() - chrono::TimeDelta::minutes(minutes)).to_rfc3339()
}
