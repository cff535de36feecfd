//! Per-field surrogate training jobs against the real daemon over HTTP
//! (issue 17, part 3), with a tiny training plan: a job runs, reports
//! progress and succeeds; the next cycle plans on the field's own model;
//! rollback; 409 on a second job, 422 on a bad soil; cancel; a validation
//! gate set impossibly tight fails and keeps the model in use; a tampered
//! model file is refused at load.

mod common;

use std::time::{Duration, Instant};

use common::{Daemon, TOKEN, create_field, curl, json_of, problem, start};
use serde_json::{Value, json};

/// The daemon's configuration with a tiny plan and the given gate.
fn config(gate: f64) -> String {
    format!(
        "fields = []\n\
         [training]\n\
         impulse_samples = 300\n\
         sub_model_samples = 0\n\
         validation_samples = 120\n\
         max_epochs = 2\n\
         patience = 2\n\
         horizon = 5\n\
         nrmse_gate = {gate}\n\
         [limits]\n\
         max_batch = 50\n\
         max_future_skew_s = 300.0\n\
         worker_threads = 2\n\
         training_jobs = 1\n"
    )
}

/// Polls a job until it has finished; returns its last view.
fn wait_job(d: &Daemon, field: i64, job: &str) -> Value {
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let r = curl(
            d,
            "GET",
            &format!("/v1/fields/{field}/surrogate/jobs/{job}"),
            None,
            None,
        );
        assert_eq!(r.0, 200, "{}", r.2);
        let v = json_of(&r.2);
        let state = v["state"].as_str().unwrap().to_string();
        if ["succeeded", "failed", "cancelled"].contains(&state.as_str()) {
            return v;
        }
        assert!(Instant::now() < deadline, "job still {state}: {v}");
        std::thread::sleep(Duration::from_millis(100));
    }
}

fn start_job(d: &Daemon, field: i64, body: Option<&str>) -> (u16, String, String) {
    curl(
        d,
        "POST",
        &format!("/v1/fields/{field}/surrogate"),
        body,
        Some(TOKEN),
    )
}

fn cycle(d: &Daemon, field: i64) -> Value {
    let r = curl(
        d,
        "POST",
        &format!("/v1/fields/{field}/control"),
        None,
        Some(TOKEN),
    );
    assert_eq!(r.0, 200, "{}", r.2);
    json_of(&r.2)
}

#[test]
fn a_field_trains_uses_rolls_back_and_refuses_its_own_surrogate() {
    let dir = tempfile::tempdir().unwrap();
    let d = start(dir.path(), &config(1.0));
    // a loam field may not plan on the shipped sandy-loam networks
    let two_layer = json!({"name": "loam", "soil": "loam", "model": "two-layer"}).to_string();
    problem(
        curl(&d, "POST", "/v1/fields", Some(&two_layer), Some(TOKEN)),
        422,
        "sandy-loam",
    );
    let id = create_field(
        &d,
        json!({"name": "loam", "soil": "loam", "model": "richards"}),
    );
    let fp = format!("/v1/fields/{id}");
    let patch = json!({"model": "two-layer"}).to_string();
    problem(
        curl(&d, "PATCH", &fp, Some(&patch), Some(TOKEN)),
        422,
        "sandy-loam",
    );

    // bad soils: 422 naming the parameter; auth first
    problem(
        curl(&d, "POST", &format!("{fp}/surrogate"), None, None),
        401,
        "Bearer",
    );
    let bad =
        json!({"soil": {"ks": 1e-5, "alpha": 3.0, "n": 0.9, "theta_r": 0.05, "theta_s": 0.4}});
    problem(
        start_job(&d, id, Some(&bad.to_string())),
        422,
        "n must be > 1",
    );
    let bad =
        json!({"soil": {"ks": -1.0, "alpha": 3.0, "n": 1.5, "theta_r": 0.05, "theta_s": 0.4}});
    problem(start_job(&d, id, Some(&bad.to_string())), 422, "ks");
    let bad = json!({"soil": {"ks": 1e-5, "alpha": 3.0, "n": 1.5, "theta_r": 0.3, "theta_s": 0.2}});
    problem(start_job(&d, id, Some(&bad.to_string())), 422, "theta_s");
    problem(
        start_job(&d, id, Some(r#"{"soil": {"ks": 1e-5}}"#)),
        422,
        "soil",
    );
    // a body that is no JSON object: not even the form feed that is
    // whitespace to Rust but not to JSON starts a job
    for body in ["\x0c", " \x0c\n", "[]", "null"] {
        problem(start_job(&d, id, Some(body)), 422, "JSON object");
    }

    // a job for the configured soil: 202, then progress, then success
    let r = start_job(&d, id, None);
    assert_eq!(r.0, 202, "{}", r.2);
    let job = json_of(&r.2);
    assert_eq!(job["soil_source"], "configured");
    assert!((job["soil"]["alpha"].as_f64().unwrap() - 3.6).abs() < 1e-12);
    let first = job["id"].as_str().unwrap().to_string();
    // a second job while the first runs: 409
    problem(start_job(&d, id, None), 409, "already has training job");
    let done = wait_job(&d, id, &first);
    assert_eq!(done["state"], "succeeded", "{done}");
    assert_eq!(done["progress"], 1.0);
    assert_eq!(done["epoch"], 2, "{done}");
    assert!(done["validation_mse"].as_f64().unwrap() > 0.0);
    assert!(done["scores"]["nrmse_20"].as_f64().unwrap() > 0.0);
    assert_eq!(done["model"], first.as_str());
    let s = json_of(&curl(&d, "GET", &format!("{fp}/surrogate"), None, None).2);
    assert_eq!(s["in_use"], first.as_str(), "{s}");
    assert_eq!(s["current"]["data_seed"], 1);
    assert_eq!(
        s["current"]["base_model"],
        "(built-in) models/two-layer.json"
    );
    assert_eq!(s["current"]["soil"]["n"], 1.56);
    assert!(s["previous"].is_null());
    // the sidecar next to the model file
    let model_dir = dir
        .path()
        .join(format!("data/surrogates/field-{id}/{first}"));
    assert!(model_dir.join("two-layer.json").is_file());
    assert!(model_dir.join("metadata.json").is_file());

    // now the field may switch to the two-layer model, and the next cycle
    // plans on its own networks
    let r = curl(&d, "PATCH", &fp, Some(&patch), Some(TOKEN));
    assert_eq!(r.0, 200, "{}", r.2);
    let sp = cycle(&d, id);
    assert_eq!(sp["model"], "two-layer");
    assert_eq!(sp["surrogate"], first.as_str(), "{sp}");

    // a second job, queued behind another field's (one job at a time) and
    // cancelled (POST …/surrogate/cancel); then a third one that succeeds
    let other = create_field(&d, json!({"name": "sandy", "model": "richards"}));
    let r = start_job(&d, other, Some(r#"{"seed": 5}"#));
    assert_eq!(r.0, 202, "{}", r.2);
    let other_job = json_of(&r.2)["id"].as_str().unwrap().to_string();
    let r = start_job(&d, id, Some(r#"{"seed": 2}"#));
    assert_eq!(r.0, 202, "{}", r.2);
    assert_eq!(json_of(&r.2)["state"], "queued");
    let second = json_of(&r.2)["id"].as_str().unwrap().to_string();
    let r = curl(
        &d,
        "POST",
        &format!("{fp}/surrogate/cancel"),
        None,
        Some(TOKEN),
    );
    assert_eq!(r.0, 202, "{}", r.2);
    let done = wait_job(&d, id, &second);
    assert_eq!(done["state"], "cancelled", "{done}");
    problem(
        curl(
            &d,
            "POST",
            &format!("{fp}/surrogate/jobs/{second}/cancel"),
            None,
            Some(TOKEN),
        ),
        409,
        "already cancelled",
    );
    assert_eq!(wait_job(&d, other, &other_job)["state"], "succeeded");
    let r = start_job(&d, id, Some(r#"{"seed": 3}"#));
    assert_eq!(r.0, 202, "{}", r.2);
    let third = json_of(&r.2)["id"].as_str().unwrap().to_string();
    assert_eq!(wait_job(&d, id, &third)["state"], "succeeded");
    assert_eq!(cycle(&d, id)["surrogate"], third.as_str());
    let s = json_of(&curl(&d, "GET", &format!("{fp}/surrogate"), None, None).2);
    assert_eq!(s["previous"]["id"], first.as_str(), "{s}");
    assert_eq!(s["jobs"].as_array().unwrap().len(), 3);

    // rollback: the previous model is used from the next cycle
    let r = curl(
        &d,
        "POST",
        &format!("{fp}/surrogate/rollback"),
        None,
        Some(TOKEN),
    );
    assert_eq!(r.0, 200, "{}", r.2);
    assert_eq!(json_of(&r.2)["current"]["id"], first.as_str());
    assert_eq!(cycle(&d, id)["surrogate"], first.as_str());
    d.sigterm();
    drop(d);

    // the model in use tampered with: refused at load, naming the path
    let file = model_dir.join("two-layer.json");
    let text = std::fs::read_to_string(&file).unwrap();
    std::fs::write(&file, text.replacen("\"0.", "\"1.", 1)).unwrap();
    // and a gate no model meets
    let d = start(dir.path(), &config(1e-9));
    let s = json_of(&curl(&d, "GET", &format!("{fp}/surrogate"), None, None).2);
    let error = s["load_error"].as_str().unwrap_or_default();
    assert!(
        error.contains(&file.display().to_string()) && error.contains("SHA-256"),
        "{s}"
    );
    assert!(s["in_use"].is_null(), "{s}");
    let sp = cycle(&d, id);
    assert!(sp["surrogate"].is_null(), "{sp}");
    let flags: Vec<&str> = sp["degraded"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(|f| f.as_str())
        .collect();
    assert!(flags.contains(&"surrogate-refused"), "{sp}");

    // the job fails validation and reports why; the models stay as they were
    let r = start_job(&d, id, Some(r#"{"seed": 4}"#));
    assert_eq!(r.0, 202, "{}", r.2);
    let fourth = json_of(&r.2)["id"].as_str().unwrap().to_string();
    let done = wait_job(&d, id, &fourth);
    assert_eq!(done["state"], "failed", "{done}");
    let why = done["error"].as_str().unwrap();
    assert!(
        why.contains("validation failed") && why.contains("unchanged"),
        "{why}"
    );
    let s = json_of(&curl(&d, "GET", &format!("{fp}/surrogate"), None, None).2);
    assert_eq!(s["current"]["id"], first.as_str(), "{s}");
    assert_eq!(s["previous"]["id"], third.as_str(), "{s}");

    // a deleted field's models go with it
    let r = curl(&d, "DELETE", &fp, None, Some(TOKEN));
    assert_eq!(r.0, 204, "{}", r.2);
    assert!(!model_dir.exists());
}
