//! The HTTP API (JSON, versioned under `/v1`; see `openapi.yaml`). Errors are
//! `application/problem+json` (RFC 9457); mutating requests need the bearer
//! token.

use std::sync::Arc;

use axum::body::Bytes;
use axum::extract::rejection::{BytesRejection, QueryRejection};
use axum::extract::{DefaultBodyLimit, Path, Query, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use chrono::{DateTime, TimeDelta, Utc};
use serde::Deserialize;
use serde::de::DeserializeOwned;

use super::wire::{Actuator, Field, FieldSpec, Forecast, Measurement};
use super::{AppState, run_cycle, start_field, stop_field};

/// Largest request body.
pub const MAX_BODY: usize = 1 << 20;

/// An API error, rendered as problem+json.
#[derive(Debug)]
pub struct ApiError {
    pub status: StatusCode,
    pub detail: String,
}

impl ApiError {
    pub fn new(status: StatusCode, detail: impl Into<String>) -> ApiError {
        ApiError {
            status,
            detail: detail.into(),
        }
    }

    fn bad(detail: impl Into<String>) -> ApiError {
        ApiError::new(StatusCode::UNPROCESSABLE_ENTITY, detail)
    }

    /// A failure of the daemon, not of the request: logged with its detail
    /// (in the request's span), answered without it.
    /// A lost database is no internal error: 503, try again later.
    pub(crate) fn internal(e: impl std::fmt::Display) -> ApiError {
        let text = e.to_string();
        if text.contains(crate::store::UNAVAILABLE) {
            tracing::warn!(error = %text, "database unavailable");
            return ApiError::new(
                StatusCode::SERVICE_UNAVAILABLE,
                "the database is unavailable; nothing was stored. Try again shortly",
            );
        }
        tracing::error!(error = %e, "internal error");
        ApiError::new(
            StatusCode::INTERNAL_SERVER_ERROR,
            "internal error; the daemon's log has it under this request_id",
        )
    }

    fn conflict(detail: impl Into<String>) -> ApiError {
        ApiError::new(StatusCode::CONFLICT, detail)
    }
}

tokio::task_local! {
    /// The id of the request being answered (`x-request-id`).
    static REQUEST_ID: String;
}

/// The current request's id, if inside one.
fn request_id() -> Option<String> {
    REQUEST_ID.try_with(Clone::clone).ok()
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let mut body = serde_json::json!({
            "type": "about:blank",
            "title": self.status.canonical_reason().unwrap_or("Error"),
            "status": self.status.as_u16(),
            "detail": self.detail,
        });
        if let Some(id) = request_id() {
            body["request_id"] = serde_json::Value::String(id);
        }
        let mut response = (self.status, body.to_string()).into_response();
        response.headers_mut().insert(
            header::CONTENT_TYPE,
            HeaderValue::from_static("application/problem+json"),
        );
        if self.status == StatusCode::SERVICE_UNAVAILABLE {
            response
                .headers_mut()
                .insert(header::RETRY_AFTER, HeaderValue::from_static("5"));
        }
        if self.status == StatusCode::UNAUTHORIZED {
            response
                .headers_mut()
                .insert(header::WWW_AUTHENTICATE, HeaderValue::from_static("Bearer"));
        }
        response
    }
}

pub(crate) type ApiResult<T> = Result<T, ApiError>;

/// A storage failure: a conflict is the client's (409), a lost database
/// 503, the rest the daemon's.
fn store_error(e: super::store::StoreError) -> ApiError {
    match e {
        super::store::StoreError::Conflict(m) => ApiError::conflict(m),
        e => ApiError::internal(e),
    }
}

/// The router of the whole API, with a request id, a span and a panic
/// guard around every request.
pub fn router(state: Arc<AppState>) -> Router {
    let request_header = header::HeaderName::from_static("x-request-id");
    Router::new()
        .route("/", get(dashboard))
        .route("/healthz", get(healthz))
        .route("/readyz", get(ready))
        .route("/metrics", get(metrics))
        .route("/v1/clock", get(clock))
        .route("/v1/fields", post(create_field).get(list_fields))
        .route(
            "/v1/fields/{id}",
            get(get_field).patch(patch_field).delete(delete_field),
        )
        .route(
            "/v1/fields/{id}/measurements",
            post(post_measurements).get(get_measurements),
        )
        .route(
            "/v1/fields/{id}/forecast",
            get(get_forecast).put(put_forecast),
        )
        .route("/v1/fields/{id}/setpoint", get(get_setpoint))
        .route("/v1/fields/{id}/setpoints", get(get_setpoints))
        .route("/v1/fields/{id}/control", post(post_control))
        .route("/v1/fields/{id}/simulation", get(get_simulation))
        .route("/v1/fields/{id}/estimate", get(get_estimate))
        .route("/v1/fields/{id}/chart.svg", get(get_chart))
        .route("/v1/fields/{id}/profile.svg", get(get_profile_chart))
        .route("/v1/fields/{id}/water", get(get_water))
        .route("/v1/fields/{id}/history.csv", get(get_history))
        .merge(super::training::routes())
        .fallback(|| async { ApiError::new(StatusCode::NOT_FOUND, "no such endpoint") })
        .method_not_allowed_fallback(|| async {
            ApiError::new(
                StatusCode::METHOD_NOT_ALLOWED,
                "this endpoint does not take that method (see openapi.yaml)",
            )
        })
        .layer(DefaultBodyLimit::max(MAX_BODY))
        .layer(axum::middleware::from_fn(guard))
        .layer(
            tower_http::trace::TraceLayer::new_for_http()
                .on_response(
                    tower_http::trace::DefaultOnResponse::new().level(tracing::Level::INFO),
                )
                .make_span_with(|req: &axum::http::Request<axum::body::Body>| {
                    let id = req
                        .headers()
                        .get("x-request-id")
                        .and_then(|v| v.to_str().ok())
                        .unwrap_or("");
                    tracing::info_span!(
                        "request",
                        method = %req.method(),
                        path = %req.uri().path(),
                        request_id = %id,
                    )
                }),
        )
        .layer(tower_http::request_id::PropagateRequestIdLayer::new(
            request_header.clone(),
        ))
        .layer(tower_http::request_id::SetRequestIdLayer::new(
            request_header,
            tower_http::request_id::MakeRequestUuid,
        ))
        .with_state(state)
}

/// Runs a request with its id in scope; a panic in the handler becomes a
/// generic 500 problem+json (logged in the request's span, its text never
/// sent).
async fn guard(req: axum::extract::Request, next: axum::middleware::Next) -> Response {
    use futures_util::FutureExt;
    let id = req
        .headers()
        .get("x-request-id")
        .and_then(|v| v.to_str().ok())
        .unwrap_or("")
        .to_string();
    REQUEST_ID
        .scope(id, async move {
            match std::panic::AssertUnwindSafe(next.run(req))
                .catch_unwind()
                .await
            {
                Ok(response) => response,
                Err(panic) => {
                    let text = panic
                        .downcast_ref::<&str>()
                        .map(|s| s.to_string())
                        .or_else(|| panic.downcast_ref::<String>().cloned())
                        .unwrap_or_default();
                    ApiError::internal(format!("handler panicked: {text}")).into_response()
                }
            }
        })
        .await
}

/// The credentials of an `Authorization` header, if its scheme is
/// `Bearer` (compared case-insensitively, RFC 9110 §11.1).
pub(crate) fn bearer(headers: &HeaderMap) -> Option<&str> {
    let value = headers.get(header::AUTHORIZATION)?.to_str().ok()?.trim();
    let (scheme, token) = value.split_once(' ')?;
    scheme
        .eq_ignore_ascii_case("bearer")
        .then(|| token.trim_start())
}

/// Whether the request carries the token.
fn has_token(state: &AppState, headers: &HeaderMap) -> bool {
    bearer(headers).is_some_and(|given| same_secret(given, &state.token))
}

/// Equal secrets, compared without an early exit on the first differing
/// byte.
pub(crate) fn same_secret(a: &str, b: &str) -> bool {
    let (a, b) = (a.as_bytes(), b.as_bytes());
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |d, (x, y)| d | (x ^ y)) == 0
}

/// Checks the bearer token of a mutating request: no credentials, or
/// credentials of another scheme, are 401 (with a `WWW-Authenticate`
/// challenge); a bearer token that is not the daemon's is 403.
pub(crate) fn authorize(state: &AppState, headers: &HeaderMap) -> ApiResult<()> {
    if bearer(headers).is_none() {
        return Err(ApiError::new(
            StatusCode::UNAUTHORIZED,
            "this request needs 'Authorization: Bearer <token>'",
        ));
    }
    if has_token(state, headers) {
        Ok(())
    } else {
        Err(ApiError::new(
            StatusCode::FORBIDDEN,
            "the bearer token is not valid",
        ))
    }
}

/// The body's bytes (within the size limit).
pub(crate) fn raw_body(body: Result<Bytes, BytesRejection>) -> ApiResult<Bytes> {
    body.map_err(|r| {
        let status = r.status();
        if status == StatusCode::PAYLOAD_TOO_LARGE {
            ApiError::new(status, format!("the body exceeds {MAX_BODY} bytes"))
        } else {
            ApiError::new(status, r.body_text())
        }
    })
}

/// Parses a JSON body (within the size limit) into `T`.
fn json_body<T: DeserializeOwned>(body: Result<Bytes, BytesRejection>) -> ApiResult<T> {
    parse_json(&raw_body(body)?)
}

/// Parses JSON into `T`; a value of the wrong type or range names its path
/// (`zone.low: invalid type …`).
pub(crate) fn parse_json<T: DeserializeOwned>(bytes: &[u8]) -> ApiResult<T> {
    let mut de = serde_json::Deserializer::from_slice(bytes);
    let value: Result<T, _> = serde_path_to_error::deserialize(&mut de);
    if value.is_ok() {
        de.end().map_err(|e| {
            ApiError::new(StatusCode::BAD_REQUEST, format!("invalid JSON body: {e}"))
        })?;
    }
    value.map_err(|e| {
        let path = e.path().to_string();
        let inner = e.into_inner();
        let status = if inner.is_data() {
            StatusCode::UNPROCESSABLE_ENTITY
        } else {
            StatusCode::BAD_REQUEST
        };
        let detail = if path.is_empty() || path == "." {
            format!("invalid JSON body: {inner}")
        } else {
            format!("invalid JSON body at '{path}': {inner}")
        };
        ApiError::new(status, detail)
    })
}

fn field_id(raw: &str) -> ApiResult<i64> {
    raw.parse::<i64>()
        .map_err(|_| ApiError::new(StatusCode::NOT_FOUND, format!("no field '{raw}'")))
}

async fn blocking<T: Send + 'static>(
    f: impl FnOnce() -> ApiResult<T> + Send + 'static,
) -> ApiResult<T> {
    tokio::task::spawn_blocking(f)
        .await
        .map_err(ApiError::internal)?
}

pub(crate) async fn load_field(state: &Arc<AppState>, raw: &str) -> ApiResult<Field> {
    let id = field_id(raw)?;
    let engine = state.engine.clone();
    blocking(move || {
        engine
            .store
            .field(id)
            .map_err(ApiError::internal)?
            .ok_or_else(|| ApiError::new(StatusCode::NOT_FOUND, format!("no field {id}")))
    })
    .await
}

/// Liveness, and who this replica is: its id, its storage, whether the
/// database answers and, on PostgreSQL, its leases (how many, how long
/// since they were renewed, whether they are valid).
async fn healthz(State(state): State<Arc<AppState>>) -> Json<serde_json::Value> {
    // on PostgreSQL the lease loop's last tick tells (no wait on a lost server)
    let up = match &state.leases {
        Some(_) => state.metrics.database_up.get() == 1,
        None => {
            let engine = state.engine.clone();
            blocking(move || engine.store.ping().map_err(ApiError::internal))
                .await
                .is_ok()
        }
    };
    Json(serde_json::json!({
        "status": "ok",
        "replica": state.replica,
        "storage": state.engine.store.kind(),
        "database": if up { "up" } else { "unavailable" },
        "leases": state.leases.as_ref().map(|l| l.status()),
    }))
}

async fn ready(State(state): State<Arc<AppState>>) -> ApiResult<&'static str> {
    let engine = state.engine.clone();
    blocking(move || {
        engine
            .store
            .meta("ready-check")
            .map_err(|e| ApiError::new(StatusCode::SERVICE_UNAVAILABLE, e.to_string()))
    })
    .await?;
    Ok("ready\n")
}

async fn metrics(State(state): State<Arc<AppState>>) -> impl IntoResponse {
    (
        [(header::CONTENT_TYPE, "text/plain; version=0.0.4")],
        state.metrics.render(),
    )
}

/// The daemon's clock, for processes that must agree with it.
async fn clock(State(state): State<Arc<AppState>>) -> Json<serde_json::Value> {
    Json(serde_json::json!({
        "now": state.clock.now(),
        "speedup": state.clock.speedup(),
        "epoch": state.settings.clock.epoch,
    }))
}

async fn create_field(
    State(state): State<Arc<AppState>>,
    headers: HeaderMap,
    body: Result<Bytes, BytesRejection>,
) -> ApiResult<(
    StatusCode,
    [(header::HeaderName, String); 1],
    Json<serde_json::Value>,
)> {
    authorize(&state, &headers)?;
    let bytes = raw_body(body)?;
    let mut spec = field_spec(&bytes)?;
    spec.validate().map_err(ApiError::bad)?;
    check_target(&state, &spec)?;
    // a webhook without a secret gets one, shown once in this answer
    let generated = super::give_secret(&mut spec).map_err(ApiError::internal)?;
    let engine = state.engine.clone();
    let now = state.clock.now();
    let field =
        blocking(move || engine.store.create_field(&spec, now).map_err(store_error)).await?;
    // the first cycle runs now, so the field has a setpoint at once
    super::first_cycle(&state, &field).await;
    start_field(&state, &field);
    let mut doc = field.public(true);
    show_once(&mut doc, generated);
    let location = format!("/v1/fields/{}", field.id);
    Ok((
        StatusCode::CREATED,
        [(header::LOCATION, location)],
        Json(doc),
    ))
}

/// Puts a secret just generated into the answer, the one time it is shown.
fn show_once(doc: &mut serde_json::Value, generated: Option<String>) {
    if let (Some(secret), Some(actuator)) = (generated, doc.get_mut("actuator")) {
        actuator["secret"] = serde_json::Value::String(secret);
    }
}

/// A webhook at a literal address the daemon does not call is refused now.
fn check_target(state: &AppState, spec: &FieldSpec) -> ApiResult<()> {
    if let Actuator::Webhook { url, .. } = &spec.actuator {
        super::webhook::check_literal_target(url, state.settings.webhooks.allow_link_local)
            .map_err(ApiError::bad)?;
    }
    Ok(())
}

async fn list_fields(
    State(state): State<Arc<AppState>>,
    headers: HeaderMap,
) -> ApiResult<Json<Vec<serde_json::Value>>> {
    let engine = state.engine.clone();
    let reveal = has_token(&state, &headers);
    let fields = blocking(move || engine.store.fields().map_err(ApiError::internal)).await?;
    Ok(Json(fields.iter().map(|f| f.public(reveal)).collect()))
}

async fn get_field(
    State(state): State<Arc<AppState>>,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> ApiResult<Json<serde_json::Value>> {
    let field = load_field(&state, &id).await?;
    Ok(Json(field.public(has_token(&state, &headers))))
}

/// Merges a JSON object into the field's spec (RFC 7396 merge patch).
async fn patch_field(
    State(state): State<Arc<AppState>>,
    Path(id): Path<String>,
    headers: HeaderMap,
    body: Result<Bytes, BytesRejection>,
) -> ApiResult<Json<serde_json::Value>> {
    authorize(&state, &headers)?;
    let field = load_field(&state, &id).await?;
    let patch: serde_json::Value = json_body(body)?;
    let Some(keys) = patch.as_object() else {
        return Err(ApiError::bad("a patch must be a JSON object"));
    };
    // even `{"x": null}`, which would change nothing, names no key a
    // field has (openapi.yaml, FieldPatch)
    if let Some(key) = keys.keys().find(|k| !FIELD_KEYS.contains(&k.as_str())) {
        return Err(ApiError::bad(format!(
            "invalid JSON body at '{key}': a field has no such key (expected one of {})",
            FIELD_KEYS.join(", ")
        )));
    }
    let mut doc = serde_json::to_value(&field.spec).map_err(ApiError::internal)?;
    merge(&mut doc, patch);
    let text = serde_json::to_vec(&doc).map_err(ApiError::internal)?;
    let spec: FieldSpec = field_spec(&text)
        .map_err(|e| ApiError::bad(format!("invalid field after the patch: {}", e.detail)))?;
    let mut spec = spec;
    // a field with its own validated surrogate may switch to it
    let own = state.engine.own_models.has_current(field.id);
    spec.validate_for(own).map_err(ApiError::bad)?;
    check_target(&state, &spec)?;
    let generated = super::give_secret(&mut spec).map_err(ApiError::internal)?;
    let engine = state.engine.clone();
    let s = spec.clone();
    let id = field.id;
    blocking(move || engine.store.update_field(id, &s).map_err(store_error)).await?;
    let field = Field { spec, ..field };
    stop_field(&state, field.id);
    start_field(&state, &field);
    let mut doc = field.public(true);
    show_once(&mut doc, generated);
    Ok(Json(doc))
}

/// RFC 7396: an object patch merges key by key into an object (a target
/// that is not one starts empty), null removes a key, anything else
/// replaces.
fn merge(doc: &mut serde_json::Value, patch: serde_json::Value) {
    match patch {
        serde_json::Value::Object(p) => {
            if !doc.is_object() {
                *doc = serde_json::Value::Object(Default::default());
            }
            if let serde_json::Value::Object(d) = doc {
                for (k, v) in p {
                    if v.is_null() {
                        d.remove(&k);
                    } else {
                        merge(d.entry(k).or_insert(serde_json::Value::Null), v);
                    }
                }
            }
        }
        p => *doc = p,
    }
}

/// serde reads a struct from a JSON array of its fields too; the API takes
/// objects only: `value` must be an object, and so must each of `keys` that
/// it holds (or null).
fn objects_only(value: &serde_json::Value, what: &str, keys: &[&str]) -> ApiResult<()> {
    let Some(obj) = value.as_object() else {
        return Err(ApiError::bad(format!("{what} must be a JSON object")));
    };
    for key in keys {
        if let Some(v) = obj.get(*key)
            && !(v.is_object() || v.is_null() || (*key == "soil" && v.is_string()))
        {
            return Err(ApiError::bad(format!(
                "invalid JSON body at '{key}': expected an object{}",
                if *key == "soil" {
                    " or a texture name"
                } else {
                    ""
                }
            )));
        }
    }
    Ok(())
}

/// The keys of a field spec (`wire::FieldSpec`, openapi.yaml's FieldPatch).
const FIELD_KEYS: &[&str] = &[
    "name",
    "soil",
    "crop",
    "zone",
    "model",
    "irrigation_max",
    "control_period_s",
    "measurement_wait_s",
    "actuator",
    "sensors",
    "simulation",
    "irrigation_system",
    "forecast_source",
];

/// The keys of a field spec that hold objects.
const FIELD_OBJECTS: &[&str] = &[
    "soil",
    "crop",
    "zone",
    "actuator",
    "simulation",
    "forecast_source",
];

/// A field spec from JSON, objects checked.
fn field_spec(bytes: &[u8]) -> ApiResult<FieldSpec> {
    let value: serde_json::Value = parse_json(bytes)?;
    objects_only(&value, "a field", FIELD_OBJECTS)?;
    actuator_keys(&value)?;
    parse_json(bytes)
}

/// An actuator of kind `none` or `simulated` has no other key. serde's
/// `deny_unknown_fields` does not reach the unit variants of an internally
/// tagged enum: `{"kind": "none", "url": ""}` (a merge patch of `url` onto
/// a field without a webhook, found by schemathesis) parsed as `none` and
/// dropped the url without a word.
fn actuator_keys(field: &serde_json::Value) -> ApiResult<()> {
    let Some(actuator) = field.get("actuator").and_then(|a| a.as_object()) else {
        return Ok(());
    };
    let kind = actuator.get("kind").and_then(|k| k.as_str());
    if matches!(kind, Some("none" | "simulated"))
        && let Some(extra) = actuator.keys().find(|k| *k != "kind")
    {
        return Err(ApiError::bad(format!(
            "invalid JSON body at 'actuator.{extra}': an actuator of kind '{}' has no '{extra}'",
            kind.unwrap_or_default()
        )));
    }
    Ok(())
}

async fn delete_field(
    State(state): State<Arc<AppState>>,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> ApiResult<StatusCode> {
    authorize(&state, &headers)?;
    let field = load_field(&state, &id).await?;
    stop_field(&state, field.id);
    if let Some(mqtt) = &state.mqtt {
        mqtt.withdraw(&state, field.id);
    }
    let engine = state.engine.clone();
    blocking(move || {
        engine
            .store
            .delete_field(field.id)
            .map_err(ApiError::internal)
    })
    .await?;
    state.training.forget_field(field.id);
    state.engine.own_models.forget(field.id);
    Ok(StatusCode::NO_CONTENT)
}

/// A measurement as sent: the time is parsed here so a bad one is named.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawMeasurement {
    time: String,
    #[serde(default, deserialize_with = "number")]
    theta: Option<f64>,
    #[serde(default, deserialize_with = "number")]
    raw: Option<f64>,
    #[serde(default)]
    sensor: Option<String>,
}

/// A number that may be left out but not given as null.
fn number<'de, D: serde::Deserializer<'de>>(d: D) -> Result<Option<f64>, D::Error> {
    f64::deserialize(d).map(Some)
}

#[derive(Deserialize)]
#[serde(untagged)]
enum RawMeasurements {
    One(RawMeasurement),
    Many(Vec<RawMeasurement>),
}

fn parse_time(what: &str, raw: &str) -> ApiResult<DateTime<Utc>> {
    DateTime::parse_from_rfc3339(raw)
        .map(|t| t.to_utc())
        .map_err(|e| {
            ApiError::bad(format!(
                "{what} = '{raw}' is not an RFC 3339 timestamp ({e})"
            ))
        })
}

async fn post_measurements(
    State(state): State<Arc<AppState>>,
    Path(id): Path<String>,
    headers: HeaderMap,
    body: Result<Bytes, BytesRejection>,
) -> ApiResult<(StatusCode, Json<serde_json::Value>)> {
    authorize(&state, &headers)?;
    let bytes = raw_body(body)?;
    let value: serde_json::Value = parse_json(&bytes)?;
    let shape_ok = match &value {
        serde_json::Value::Object(_) => true,
        serde_json::Value::Array(items) => items.iter().all(serde_json::Value::is_object),
        _ => false,
    };
    if !shape_ok {
        return Err(ApiError::bad(
            "a body must be one measurement {time, theta, sensor?} or an array of them",
        ));
    }
    let raw: RawMeasurements = parse_json(&bytes).map_err(|e| {
        if e.status == StatusCode::UNPROCESSABLE_ENTITY {
            ApiError::bad(
                "a body must be one measurement {time, theta, sensor?} or an array of them, \
                 with no other keys",
            )
        } else {
            e
        }
    })?;
    let batch = match raw {
        RawMeasurements::One(m) => vec![m],
        RawMeasurements::Many(v) => v,
    };
    let limit = state.settings.limits.max_batch;
    if batch.is_empty() {
        return Err(ApiError::bad("the array holds no measurement"));
    }
    if batch.len() > limit {
        return Err(ApiError::new(
            StatusCode::PAYLOAD_TOO_LARGE,
            format!(
                "{} measurements in one request; at most {limit}",
                batch.len()
            ),
        ));
    }
    let field = load_field(&state, &id).await?;
    let now = state.clock.now();
    let skew = state.settings.limits.max_future_skew_s;
    let mut parsed = Vec::with_capacity(batch.len());
    for (i, m) in batch.into_iter().enumerate() {
        let key = format!("measurements[{i}]");
        let time = parse_time(&format!("{key}.time"), &m.time)?;
        let reading = super::wire::ReadingIn {
            time,
            theta: m.theta,
            raw: m.raw,
            sensor: m.sensor.as_deref(),
        };
        let checked = super::wire::check_reading(&key, reading, &field, now, skew)
            .map_err(|e| ApiError::bad(e.message))?;
        parsed.push(checked);
    }
    let engine = state.engine.clone();
    let n = parsed.len();
    let last = parsed.last().map(|m| m.theta);
    let new = blocking(move || {
        engine
            .store
            .add_measurements(field.id, &parsed)
            .map_err(store_error)
    })
    .await?;
    state.metrics.measurements.inc_by(new as u64);
    if new > 0 {
        state.measured(field.id).notify_waiters();
    }
    if let Some(theta) = last {
        state
            .metrics
            .theta
            .with_label_values(&[field.id.to_string().as_str()])
            .set(theta);
    }
    Ok((
        StatusCode::CREATED,
        Json(serde_json::json!({ "stored": new, "duplicates": n - new })),
    ))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct Range {
    from: Option<String>,
    to: Option<String>,
    limit: Option<usize>,
}

/// A time window and a row limit.
type Window = (Option<DateTime<Utc>>, Option<DateTime<Utc>>, usize);

fn range(q: Result<Query<Range>, QueryRejection>) -> ApiResult<Window> {
    let Query(q) = q.map_err(|e| ApiError::new(StatusCode::BAD_REQUEST, e.body_text()))?;
    let from = q
        .from
        .as_deref()
        .map(|t| parse_time("from", t))
        .transpose()?;
    let to = q.to.as_deref().map(|t| parse_time("to", t)).transpose()?;
    let limit = q.limit.unwrap_or(1000);
    if limit == 0 || limit > 100_000 {
        return Err(ApiError::bad(format!(
            "limit = {limit} must be in 1..=100000"
        )));
    }
    Ok((from, to, limit))
}

async fn get_measurements(
    State(state): State<Arc<AppState>>,
    Path(id): Path<String>,
    query: Result<Query<Range>, QueryRejection>,
) -> ApiResult<Json<Vec<Measurement>>> {
    let (from, to, limit) = range(query)?;
    let field = load_field(&state, &id).await?;
    let engine = state.engine.clone();
    Ok(Json(
        blocking(move || {
            engine
                .store
                .measurements(field.id, from, to, limit, super::store::Sensors::All)
                .map_err(ApiError::internal)
        })
        .await?,
    ))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawForecast {
    issued_at: String,
    start: String,
    step_s: f64,
    et0_mm: Vec<f64>,
    precip_mm: Vec<f64>,
}

async fn put_forecast(
    State(state): State<Arc<AppState>>,
    Path(id): Path<String>,
    headers: HeaderMap,
    body: Result<Bytes, BytesRejection>,
) -> ApiResult<Json<Forecast>> {
    authorize(&state, &headers)?;
    let bytes = raw_body(body)?;
    objects_only(&parse_json(&bytes)?, "a forecast", &[])?;
    let raw: RawForecast = parse_json(&bytes)?;
    let forecast = Forecast {
        issued_at: parse_time("issued_at", &raw.issued_at)?,
        start: parse_time("start", &raw.start)?,
        step_s: raw.step_s,
        et0_mm: raw.et0_mm,
        precip_mm: raw.precip_mm,
    };
    forecast.validate().map_err(ApiError::bad)?;
    let field = load_field(&state, &id).await?;
    let engine = state.engine.clone();
    let f = forecast.clone();
    blocking(move || {
        engine
            .store
            .put_forecast(field.id, &f)
            .map_err(ApiError::internal)
    })
    .await?;
    Ok(Json(forecast))
}

/// The latest posted forecast, or (none posted yet) the climatology the
/// controller falls back on, marked by `source`.
async fn get_forecast(
    State(state): State<Arc<AppState>>,
    Path(id): Path<String>,
) -> ApiResult<Json<serde_json::Value>> {
    let field = load_field(&state, &id).await?;
    let engine = state.engine.clone();
    let now = state.clock.now();
    blocking(move || {
        let (forecast, source) = match engine
            .store
            .latest_forecast(field.id)
            .map_err(ApiError::internal)?
        {
            // a polled source's latest forecast is named after it
            Some(f) => (
                f,
                field
                    .spec
                    .forecast_source
                    .as_ref()
                    .map_or("posted", |s| s.provider.name()),
            ),
            None => (engine.climatology_forecast(&field, now), "climatology"),
        };
        let mut doc = serde_json::to_value(forecast).map_err(ApiError::internal)?;
        doc["source"] = serde_json::Value::String(source.into());
        Ok(Json(doc))
    })
    .await
}

async fn get_setpoint(
    State(state): State<Arc<AppState>>,
    Path(id): Path<String>,
) -> ApiResult<Json<super::wire::Setpoint>> {
    let field = load_field(&state, &id).await?;
    let engine = state.engine.clone();
    blocking(move || {
        engine
            .store
            .recent_setpoints(field.id, 1)
            .map_err(ApiError::internal)?
            .into_iter()
            .next()
            .map(Json)
            .ok_or_else(|| {
                ApiError::new(
                    StatusCode::NOT_FOUND,
                    format!(
                        "field {} has no setpoint yet (POST .../control runs a cycle)",
                        field.id
                    ),
                )
            })
    })
    .await
}

async fn get_setpoints(
    State(state): State<Arc<AppState>>,
    Path(id): Path<String>,
    query: Result<Query<Range>, QueryRejection>,
) -> ApiResult<Json<Vec<super::wire::Setpoint>>> {
    let (from, to, limit) = range(query)?;
    let field = load_field(&state, &id).await?;
    let engine = state.engine.clone();
    Ok(Json(
        blocking(move || {
            engine
                .store
                .setpoints(field.id, from, to, limit)
                .map_err(ApiError::internal)
        })
        .await?,
    ))
}

async fn post_control(
    State(state): State<Arc<AppState>>,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> ApiResult<Json<super::wire::Setpoint>> {
    authorize(&state, &headers)?;
    let field = load_field(&state, &id).await?;
    let now = state.clock.now();
    match run_cycle(&state, field, now, false).await {
        Ok(Some(setpoint)) => Ok(Json(setpoint)),
        Ok(None) => Err(ApiError::internal("an unscheduled cycle was refused")),
        Err(e) => Err(ApiError::internal(e)),
    }
}

/// The true state of a simulated field (`simulated: true` and the state), or
/// `simulated: false` for a field without a simulated plant.
async fn get_simulation(
    State(state): State<Arc<AppState>>,
    Path(id): Path<String>,
) -> ApiResult<Json<serde_json::Value>> {
    let field = load_field(&state, &id).await?;
    let engine = state.engine.clone();
    blocking(move || {
        let plant = engine
            .simulation_state(&field)
            .map_err(ApiError::internal)?;
        let mut doc = match plant {
            Some(p) => serde_json::to_value(p).map_err(ApiError::internal)?,
            None => serde_json::json!({}),
        };
        doc["simulated"] = serde_json::Value::Bool(doc.get("time").is_some());
        Ok(Json(doc))
    })
    .await
}

/// The field's state estimate as last updated (by its latest cycle): the θ
/// profile with its band, the parameters with their standard deviations,
/// the innovations of the last update; `estimated: false` before the first.
async fn get_estimate(
    State(state): State<Arc<AppState>>,
    Path(id): Path<String>,
) -> ApiResult<Json<serde_json::Value>> {
    let field = load_field(&state, &id).await?;
    let engine = state.engine.clone();
    blocking(move || {
        let Some((stored, est)) = engine
            .current_estimate(&field)
            .map_err(ApiError::internal)?
        else {
            return Ok(Json(serde_json::json!({ "estimated": false })));
        };
        let profile: Vec<serde_json::Value> = est
            .profile()
            .iter()
            .map(|p| {
                serde_json::json!({
                    "depth": p.depth,
                    "theta": p.theta_mean,
                    "theta_sd": p.theta_sd,
                    "low": p.theta_mean - 2.0 * p.theta_sd,
                    "high": p.theta_mean + 2.0 * p.theta_sd,
                })
            })
            .collect();
        let parameters: Vec<serde_json::Value> = est
            .parameters()
            .iter()
            .map(
                |p| serde_json::json!({"name": p.name, "unit": p.unit, "mean": p.mean, "sd": p.sd}),
            )
            .collect();
        Ok(Json(serde_json::json!({
            "estimated": true,
            "time": stored.time,
            "prior": est.prior().describe(),
            "profile": profile,
            "parameters": parameters,
            "innovations": est.last_update().map(|u| u.innovations.clone()).unwrap_or_default(),
            "resets": stored.resets,
            "reselections": est.statistics().reselections,
            "selected_texture": est.selected_texture().map(|t| t.name()),
            "members": est.settings().members,
        })))
    })
    .await
}

/// The dashboard page (no external resources; it reads the JSON API).
async fn dashboard() -> impl IntoResponse {
    (
        [(header::CONTENT_TYPE, "text/html; charset=utf-8")],
        include_str!("dashboard.html"),
    )
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct ChartQuery {
    hours: Option<f64>,
    /// Ignored: lets a page defeat caching.
    #[allow(dead_code)]
    t: Option<String>,
}

/// A field's chart over the last `hours` (default 48) as SVG.
async fn get_chart(
    State(state): State<Arc<AppState>>,
    Path(id): Path<String>,
    query: Result<Query<ChartQuery>, QueryRejection>,
) -> ApiResult<Response> {
    let Query(q) = query.map_err(|e| ApiError::new(StatusCode::BAD_REQUEST, e.body_text()))?;
    let hours = q.hours.unwrap_or(48.0);
    if !(hours.is_finite() && hours > 0.0 && hours <= 24.0 * 60.0) {
        return Err(ApiError::bad(format!(
            "hours = {hours} must be in (0, 1440]"
        )));
    }
    let field = load_field(&state, &id).await?;
    let engine = state.engine.clone();
    let now = state.clock.now();
    let svg = blocking(move || {
        let from = super::chart::window(now, hours);
        let store = &engine.store;
        let measurements = store
            .measurements(
                field.id,
                Some(from),
                Some(now),
                100_000,
                super::store::Sensors::Primary,
            )
            .map_err(ApiError::internal)?;
        let setpoints = store
            .setpoints(field.id, Some(from), None, 100_000)
            .map_err(ApiError::internal)?;
        let forecast = store
            .latest_forecast(field.id)
            .map_err(ApiError::internal)?;
        super::chart::render(&super::chart::ChartData {
            title: &field.spec.name,
            now,
            hours,
            measurements: &measurements,
            setpoints: &setpoints,
            forecast: forecast.as_ref(),
        })
        .map_err(ApiError::internal)
    })
    .await?;
    Ok(([(header::CONTENT_TYPE, "image/svg+xml")], svg).into_response())
}

/// A field's θ profile as SVG: the state estimate with its band against
/// depth, and the true profile of a simulated field.
async fn get_profile_chart(
    State(state): State<Arc<AppState>>,
    Path(id): Path<String>,
) -> ApiResult<Response> {
    let field = load_field(&state, &id).await?;
    let engine = state.engine.clone();
    let svg = blocking(move || {
        let estimate: Vec<(f64, f64, f64)> = match engine
            .current_estimate(&field)
            .map_err(ApiError::internal)?
        {
            Some((_, est)) => est
                .profile()
                .iter()
                .map(|p| (p.depth, p.theta_mean, p.theta_sd))
                .collect(),
            None => Vec::new(),
        };
        let truth: Vec<(f64, f64)> = match engine
            .simulation_state(&field)
            .map_err(ApiError::internal)?
        {
            Some(p) => {
                let n = p.theta_profile.len().max(1) as f64;
                let dz = crate::soil::FieldSettings::default().depth / n;
                p.theta_profile
                    .iter()
                    .enumerate()
                    .map(|(i, t)| ((i as f64 + 0.5) * dz, *t))
                    .collect()
            }
            None => Vec::new(),
        };
        let sensors: Vec<(String, f64)> = field
            .spec
            .effective_sensors()
            .into_iter()
            .map(|s| (s.id, s.depth))
            .collect();
        let zone = engine
            .store
            .recent_setpoints(field.id, 1)
            .map_err(ApiError::internal)?
            .first()
            .and_then(|s| s.zone.first().copied())
            .map(|z| (z[0], z[1], field.spec.crop.rooting_depth));
        let title = format!("{}: θ profile", field.spec.name);
        super::chart::render_profile(&super::chart::ProfileData {
            title: &title,
            estimate: &estimate,
            truth: &truth,
            sensors: &sensors,
            zone,
        })
        .map_err(ApiError::internal)
    })
    .await?;
    Ok(([(header::CONTENT_TYPE, "image/svg+xml")], svg).into_response())
}

#[cfg(test)]
mod tests {
    use super::*;
    use tower::ServiceExt;

    #[tokio::test]
    async fn a_panicking_handler_gives_a_generic_500_with_the_request_id() {
        let app = Router::new()
            .route(
                "/boom",
                get(|| async {
                    if true {
                        panic!("secret internal detail");
                    }
                    "never"
                }),
            )
            .layer(axum::middleware::from_fn(guard));
        let request = axum::http::Request::builder()
            .uri("/boom")
            .header("x-request-id", "req-42")
            .body(axum::body::Body::empty())
            .unwrap();
        let response = app.oneshot(request).await.unwrap();
        assert_eq!(response.status(), StatusCode::INTERNAL_SERVER_ERROR);
        assert_eq!(
            response.headers()[header::CONTENT_TYPE],
            "application/problem+json"
        );
        let body = axum::body::to_bytes(response.into_body(), 1 << 16)
            .await
            .unwrap();
        let v: serde_json::Value = serde_json::from_slice(&body).unwrap();
        assert_eq!(v["status"], 500);
        assert_eq!(v["request_id"], "req-42");
        assert!(!String::from_utf8_lossy(&body).contains("secret"), "{v}");
    }

    #[test]
    fn an_actuator_without_a_webhook_takes_no_other_key() {
        for (body, ok) in [
            (r#"{"name": "a", "actuator": {"kind": "none"}}"#, true),
            (r#"{"name": "a", "actuator": {"kind": "simulated"}}"#, true),
            (
                r#"{"name": "a", "actuator": {"kind": "webhook", "url": "http://example.org/x"}}"#,
                true,
            ),
            (
                r#"{"name": "a", "actuator": {"kind": "none", "url": ""}}"#,
                false,
            ),
            (
                r#"{"name": "a", "actuator": {"kind": "simulated", "secret": "0123456789abcdef"}}"#,
                false,
            ),
        ] {
            match field_spec(body.as_bytes()) {
                Ok(_) => assert!(ok, "{body} was accepted"),
                Err(e) => {
                    assert!(!ok, "{body}: {}", e.detail);
                    assert!(e.detail.contains("actuator."), "{}", e.detail);
                }
            }
        }
    }

    #[test]
    fn the_patchable_keys_are_the_field_specs() {
        // every key a spec serialises is patchable
        let doc = serde_json::to_value(FieldSpec::demo()).unwrap();
        for key in doc.as_object().unwrap().keys() {
            assert!(FIELD_KEYS.contains(&key.as_str()), "{key} is not patchable");
        }
        // and every patchable key is one of the spec's (the spec refuses
        // unknown keys; those left out above are optional)
        for key in FIELD_KEYS {
            let empty = ["null", "[]"].iter().any(|v| {
                let body = format!(r#"{{"name": "a", "{key}": {v}}}"#);
                serde_json::from_str::<FieldSpec>(&body).is_ok()
            });
            assert!(
                empty || doc.get(*key).is_some(),
                "{key} is no key of a field"
            );
        }
        assert!(serde_json::from_str::<FieldSpec>(r#"{"name": "a", "colour": null}"#).is_err());
    }

    #[test]
    fn a_merge_patch_follows_rfc_7396() {
        // RFC 7396 appendix A, a few of its cases
        let cases = [
            (r#"{"a":"b"}"#, r#"{"a":"c"}"#, r#"{"a":"c"}"#),
            (r#"{"a":"b"}"#, r#"{"a":null}"#, r#"{}"#),
            (r#"{"a":["b"]}"#, r#"{"a":"c"}"#, r#"{"a":"c"}"#),
            (
                r#"{"a":"foo"}"#,
                r#"{"a":{"b":"c","d":null}}"#,
                r#"{"a":{"b":"c"}}"#,
            ),
            (r#"{"e":null}"#, r#"{"a":1}"#, r#"{"e":null,"a":1}"#),
        ];
        for (doc, patch, want) in cases {
            let mut d: serde_json::Value = serde_json::from_str(doc).unwrap();
            merge(&mut d, serde_json::from_str(patch).unwrap());
            assert_eq!(d, serde_json::from_str::<serde_json::Value>(want).unwrap());
        }
    }
}

/// The field's water accounts: day, week and season in mm (and m³ with an
/// area), from its setpoints ([`super::water`]).
async fn get_water(
    State(state): State<Arc<AppState>>,
    Path(id): Path<String>,
) -> ApiResult<Json<super::water::WaterAccounts>> {
    let field = load_field(&state, &id).await?;
    let engine = state.engine.clone();
    let now = state.clock.now();
    Ok(Json(
        blocking(move || water_accounts(&engine.store, &field, now)).await?,
    ))
}

/// The accounts of `field` at `now` (the season's setpoints, at most one per
/// minute of the year).
pub(crate) fn water_accounts(
    store: &super::store::Store,
    field: &Field,
    now: DateTime<Utc>,
) -> ApiResult<super::water::WaterAccounts> {
    let [_, _, season] = super::water::windows(now);
    let setpoints = store
        .setpoints(field.id, Some(season), Some(now), 600_000)
        .map_err(ApiError::internal)?;
    Ok(super::water::accounts(
        field.id,
        &setpoints,
        field.spec.irrigation_system.as_ref(),
        now,
    ))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct HistoryQuery {
    from: Option<String>,
    to: Option<String>,
}

/// Measurements, setpoints and forecasts as CSV, streamed page by page
/// ([`super::history`]). Default range: the last 7 days up to now.
async fn get_history(
    State(state): State<Arc<AppState>>,
    Path(id): Path<String>,
    query: Result<Query<HistoryQuery>, QueryRejection>,
) -> ApiResult<Response> {
    let Query(q) = query.map_err(|e| ApiError::new(StatusCode::BAD_REQUEST, e.body_text()))?;
    let now = state.clock.now();
    let to = q.to.as_deref().map(|t| parse_time("to", t)).transpose()?;
    let to = to.unwrap_or(now);
    let from = q
        .from
        .as_deref()
        .map(|t| parse_time("from", t))
        .transpose()?;
    let from = from.unwrap_or(to - TimeDelta::days(7));
    // a range that ends before it starts holds nothing (as the JSON lists)
    let field = load_field(&state, &id).await?;
    let engine = state.engine.clone();
    let cursor = super::history::Cursor::new(from, to);
    let pages = futures_util::stream::unfold(Some(cursor), move |cursor| {
        let engine = engine.clone();
        async move {
            let mut cursor = cursor?;
            let id = field.id;
            let page = tokio::task::spawn_blocking(move || {
                let chunk = cursor.next_chunk(&engine.store, id);
                (cursor, chunk)
            })
            .await;
            match page {
                Ok((cursor, Ok(Some(chunk)))) => Some((Ok(Bytes::from(chunk)), Some(cursor))),
                Ok((_, Ok(None))) => None,
                Ok((_, Err(e))) => {
                    tracing::error!(error = %e, "history export failed");
                    Some((Err(std::io::Error::other(e.to_string())), None))
                }
                Err(e) => Some((Err(std::io::Error::other(e.to_string())), None)),
            }
        }
    });
    Ok((
        [
            (header::CONTENT_TYPE, "text/csv; charset=utf-8"),
            (
                header::CONTENT_DISPOSITION,
                "attachment; filename=\"history.csv\"",
            ),
        ],
        axum::body::Body::from_stream(pages),
    )
        .into_response())
}
