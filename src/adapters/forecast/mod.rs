//! Forecast providers: a field may name a source (`forecast_source` in its
//! spec) instead of being sent forecasts. The poller fetches each distinct
//! (provider, base URL, rounded location) once per poll, however many
//! fields share it, honours `Last-Modified` / `If-Modified-Since` and does
//! not come back before an answer's `Expires`, backs off
//! exponentially on failure, and keeps the last good forecast when a
//! response is refused (malformed, truncated, wrong units). A provider's
//! answer becomes a [`Series`] of UTC intervals with ET0 and precipitation
//! amounts, aggregated into each field's control periods ([`to_forecast`]).
//!
//! - [`open_meteo`]: Open-Meteo's hourly ET0 (FAO-56 Penman-Monteith) and
//!   precipitation, columnar JSON.
//! - [`met_norway`]: MET Norway's locationforecast 2.0 compact, with ET0 by
//!   [`hargreaves`] from its temperatures.

pub mod hargreaves;
pub mod met_norway;
pub mod open_meteo;

use std::collections::BTreeMap;
use std::sync::Arc;

use chrono::{DateTime, TimeDelta, Utc};
use serde::{Deserialize, Serialize};

use crate::service::clock::boundary_at_or_before;
use crate::service::store::{Store, StoreError};
use crate::service::wire::{
    FORECAST_SPAN_S, Field, Forecast, ForecastUsed, MAX_ET0_MM_PER_H, MAX_PRECIP_MM_PER_H,
    check_range,
};

/// A forecast provider.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Provider {
    OpenMeteo,
    MetNorway,
}

impl Provider {
    pub fn name(self) -> &'static str {
        match self {
            Provider::OpenMeteo => "open-meteo",
            Provider::MetNorway => "met-norway",
        }
    }

    /// The public service.
    pub fn default_base_url(self) -> &'static str {
        match self {
            Provider::OpenMeteo => "https://api.open-meteo.com",
            Provider::MetNorway => "https://api.met.no",
        }
    }

    /// The path below the base URL.
    pub fn path(self) -> &'static str {
        match self {
            Provider::OpenMeteo => "/v1/forecast",
            Provider::MetNorway => "/weatherapi/locationforecast/2.0/compact",
        }
    }
}

/// Latitude range [°, north positive].
pub const LATITUDE: (f64, f64) = (-90.0, 90.0);
/// Longitude range [°, east positive].
pub const LONGITUDE: (f64, f64) = (-180.0, 180.0);

/// A field's forecast source.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SourceSpec {
    pub provider: Provider,
    /// [°] in [-90, 90].
    pub latitude: f64,
    /// [°] in [-180, 180].
    pub longitude: f64,
    /// The service's base URL (http or https); unset: the public one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub base_url: Option<String>,
}

impl SourceSpec {
    /// What is wrong with it, naming the key.
    pub fn validate(&self) -> Result<(), String> {
        check_range("forecast_source.latitude", self.latitude, LATITUDE)?;
        check_range("forecast_source.longitude", self.longitude, LONGITUDE)?;
        if let Some(url) = &self.base_url {
            let bad = |why: &str| Err(format!("forecast_source.base_url = '{url}' {why}"));
            if url.len() > 2000 {
                return bad("must have at most 2000 characters");
            }
            let Ok(parsed) = reqwest::Url::parse(url) else {
                return bad("is not a URL");
            };
            if !matches!(parsed.scheme(), "http" | "https") {
                return bad("must be an http(s) URL");
            }
            if parsed.host_str().is_none_or(str::is_empty) {
                return bad("has no host");
            }
            if !parsed.username().is_empty() || parsed.password().is_some() {
                return bad("must not carry credentials");
            }
            if parsed.query().is_some() || parsed.fragment().is_some() {
                return bad("must have no query or fragment");
            }
        }
        Ok(())
    }

    /// The source this spec shares with every field at the same rounded
    /// location of the same provider and base URL.
    pub fn key(&self, decimals: u32) -> SourceKey {
        let scale = 10f64.powi(decimals as i32);
        let base = self
            .base_url
            .as_deref()
            .unwrap_or(self.provider.default_base_url())
            .trim_end_matches('/')
            .to_string();
        SourceKey {
            provider: self.provider,
            base_url: base,
            lat: (self.latitude * scale).round() as i64,
            lon: (self.longitude * scale).round() as i64,
            decimals,
        }
    }
}

/// One request's worth of fields.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct SourceKey {
    pub provider: Provider,
    pub base_url: String,
    /// Latitude and longitude × 10^decimals, rounded.
    pub lat: i64,
    pub lon: i64,
    pub decimals: u32,
}

impl SourceKey {
    pub fn latitude(&self) -> f64 {
        self.lat as f64 / 10f64.powi(self.decimals as i32)
    }

    pub fn longitude(&self) -> f64 {
        self.lon as f64 / 10f64.powi(self.decimals as i32)
    }

    /// Its name in storage and logs.
    pub fn id(&self) -> String {
        let d = self.decimals as usize;
        format!(
            "{} {} {:.d$},{:.d$}",
            self.provider.name(),
            self.base_url,
            self.latitude(),
            self.longitude()
        )
    }

    /// The request URL.
    pub fn url(&self) -> Result<reqwest::Url, String> {
        let mut url = reqwest::Url::parse(&format!("{}{}", self.base_url, self.provider.path()))
            .map_err(|e| format!("{}: {e}", self.id()))?;
        let (lat, lon) = (self.latitude(), self.longitude());
        let query = match self.provider {
            Provider::OpenMeteo => open_meteo::query(lat, lon),
            Provider::MetNorway => met_norway::query(lat, lon),
        };
        url.query_pairs_mut()
            .extend_pairs(query.iter().map(|(k, v)| (*k, v.as_str())));
        Ok(url)
    }
}

/// Amounts over one UTC interval.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Interval {
    pub start: DateTime<Utc>,
    pub end: DateTime<Utc>,
    pub et0_mm: f64,
    pub precip_mm: f64,
}

/// A provider's forecast: non-overlapping intervals in time order (a gap
/// is time without data).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Series {
    /// When the provider issued it (MET Norway's `updated_at`), else when
    /// it was fetched.
    pub issued_at: DateTime<Utc>,
    pub intervals: Vec<Interval>,
}

/// A provider's answer refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ProviderError {
    #[error("malformed response: {0}")]
    Malformed(String),
    #[error("wrong units or values: {0}")]
    Units(String),
    #[error("{0}")]
    Http(String),
}

/// `v` mm over `hours` checked against the documented rates (ET0 ≤ 2 mm/h,
/// precipitation ≤ 400 mm/h; a slightly negative hourly ET0, dew, counts
/// as 0).
pub(crate) fn check_amount(
    what: &str,
    i: usize,
    v: f64,
    hours: f64,
    et0: bool,
) -> Result<f64, ProviderError> {
    let (rate, floor) = if et0 {
        (MAX_ET0_MM_PER_H, -0.05 * hours)
    } else {
        (MAX_PRECIP_MM_PER_H, 0.0)
    };
    let most = rate * hours;
    if v.is_finite() && v >= floor && v <= most {
        Ok(v.max(0.0))
    } else {
        Err(ProviderError::Units(format!(
            "{what}[{i}] = {v} mm must lie in [0, {most}] mm over {hours} h (wrong units?)"
        )))
    }
}

/// The control periods of `period` s from the boundary at or before `now`
/// that the series covers, as a [`Forecast`]: each period's amounts are the
/// overlapping intervals' in proportion to the overlap. The first period
/// may be covered in part (at least half; its amounts are scaled to the
/// whole period, the rate kept); the forecast ends before the first later
/// period with a gap (a null, the end of the data). None when nothing is
/// covered.
pub fn to_forecast(series: &Series, period: f64, now: DateTime<Utc>) -> Option<Forecast> {
    let p = TimeDelta::milliseconds((period * 1000.0).round() as i64);
    let most = (FORECAST_SPAN_S / period).floor() as usize;
    let mut t = boundary_at_or_before(now, period);
    let mut start = None;
    let (mut et0, mut precip) = (Vec::new(), Vec::new());
    let ivs = &series.intervals;
    let mut first = 0;
    for k in 0..most {
        let end = t + p;
        while first < ivs.len() && ivs[first].end <= t {
            first += 1;
        }
        let (mut covered, mut e, mut r) = (0.0, 0.0, 0.0);
        for iv in ivs[first..].iter().take_while(|iv| iv.start < end) {
            let lo = iv.start.max(t);
            let hi = iv.end.min(end);
            let whole = (iv.end - iv.start).num_milliseconds() as f64;
            let part = (hi - lo).num_milliseconds() as f64;
            if part > 0.0 && whole > 0.0 {
                covered += part;
                e += iv.et0_mm * part / whole;
                r += iv.precip_mm * part / whole;
            }
        }
        let full = p.num_milliseconds() as f64;
        if covered >= full - 1.0 {
            start.get_or_insert(t);
            et0.push(e);
            precip.push(r);
        } else if start.is_none() && k == 0 && covered >= full / 2.0 {
            start = Some(t);
            et0.push(e * full / covered);
            precip.push(r * full / covered);
        } else if start.is_some() {
            break;
        } else if k > 0 {
            return None;
        }
        t = end;
    }
    let forecast = Forecast {
        issued_at: series.issued_at,
        start: start?,
        step_s: period,
        et0_mm: et0,
        precip_mm: precip,
    };
    forecast.validate().ok().map(|()| forecast)
}

/// The poller's settings (`[forecasts]`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ForecastSettings {
    /// Seconds (clock time) between polls of a source, in [60, 86400].
    #[serde(deserialize_with = "crate::service::settings::lenient_f64")]
    pub poll_interval_s: f64,
    /// First retry after a failure [s], doubled per failure, in [1, 3600].
    #[serde(deserialize_with = "crate::service::settings::lenient_f64")]
    pub retry_s: f64,
    /// Longest wait between retries [s], in [retry_s, 86400].
    #[serde(deserialize_with = "crate::service::settings::lenient_f64")]
    pub max_backoff_s: f64,
    /// A source not heard from (200 or 304) for this long [s] is stale: its
    /// fields fall back on the climatology, flagged `stale-forecast`; in
    /// [60, 604800].
    #[serde(deserialize_with = "crate::service::settings::lenient_f64")]
    pub stale_after_s: f64,
    /// Request timeout [s], in [1, 300].
    #[serde(deserialize_with = "crate::service::settings::lenient_f64")]
    pub timeout_s: f64,
    /// Contact in the User-Agent (`rootzone/<version> <contact>`), an email
    /// address or a URL; MET Norway requires one.
    pub contact: String,
    /// Decimals the location is rounded to before the request, 0 … 4
    /// (2: about 1 km; MET Norway takes at most 4).
    pub location_decimals: u32,
}

impl Default for ForecastSettings {
    fn default() -> Self {
        ForecastSettings {
            poll_interval_s: 3600.0,
            retry_s: 60.0,
            max_backoff_s: 3600.0,
            stale_after_s: 3.0 * 3600.0,
            timeout_s: 20.0,
            contact: String::new(),
            location_decimals: 2,
        }
    }
}

impl ForecastSettings {
    pub fn validate(&self) -> Result<(), String> {
        check_range(
            "forecasts.poll_interval_s",
            self.poll_interval_s,
            (60.0, 86_400.0),
        )?;
        check_range("forecasts.retry_s", self.retry_s, (1.0, 3600.0))?;
        check_range(
            "forecasts.max_backoff_s",
            self.max_backoff_s,
            (self.retry_s, 86_400.0),
        )?;
        check_range(
            "forecasts.stale_after_s",
            self.stale_after_s,
            (60.0, 7.0 * 86_400.0),
        )?;
        check_range("forecasts.timeout_s", self.timeout_s, (1.0, 300.0))?;
        if self.location_decimals > 4 {
            return Err(format!(
                "forecasts.location_decimals = {} must lie in [0, 4]",
                self.location_decimals
            ));
        }
        if self.contact.len() > 200 || self.contact.chars().any(|c| c.is_control()) {
            return Err(
                "forecasts.contact must have at most 200 characters, none a control character"
                    .into(),
            );
        }
        Ok(())
    }

    /// `rootzone/<version> <contact>`.
    pub fn user_agent(&self) -> String {
        let version = env!("CARGO_PKG_VERSION");
        match self.contact.trim() {
            "" => format!("rootzone/{version}"),
            c => format!("rootzone/{version} {c}"),
        }
    }
}

/// What the daemon keeps of a source (table `forecast_sources`, JSON).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct SourceState {
    /// The last good forecast.
    pub series: Option<Series>,
    pub last_modified: Option<String>,
    /// The last answer with a forecast (200).
    pub fetched_at: Option<DateTime<Utc>>,
    /// The last answer at all (200 or 304).
    pub checked_at: Option<DateTime<Utc>>,
    /// Failures in a row.
    pub failures: u32,
    pub next_poll_at: Option<DateTime<Utc>>,
    pub last_error: Option<String>,
}

/// What a cycle of a field with a source uses: the forecast, when the
/// source is fresh (heard from within `stale_after_s`), aggregated into its
/// periods from the period boundary at or before `now` and given as issued
/// at `now` (the cycle's own staleness rule is for forecasts that are sent;
/// here the source's rule stands); else none and the flag
/// `stale-forecast`. And the record of it for the setpoint.
pub fn for_cycle(
    provider: Provider,
    state: Option<&SourceState>,
    period: f64,
    now: DateTime<Utc>,
    stale_after_s: f64,
) -> (Option<Forecast>, Option<&'static str>, ForecastUsed) {
    let fresh = state.filter(|s| {
        s.checked_at.is_some_and(|c| {
            (now - c).num_milliseconds() as f64 <= stale_after_s * 1e3
                && c <= now + TimeDelta::hours(1)
        })
    });
    let built = fresh.and_then(|s| {
        let series = s.series.as_ref()?;
        let mut f = to_forecast(series, period, now)?;
        f.issued_at = now;
        Some((f, series.issued_at, s.fetched_at))
    });
    match built {
        Some((f, issued, fetched)) => (
            Some(f),
            None,
            ForecastUsed {
                source: provider.name().into(),
                issued_at: Some(issued),
                fetched_at: fetched,
            },
        ),
        None => (
            None,
            Some("stale-forecast"),
            ForecastUsed {
                source: "climatology".into(),
                issued_at: None,
                fetched_at: None,
            },
        ),
    }
}

/// What one poll did.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct PollReport {
    /// Distinct sources of the fields.
    pub sources: usize,
    pub requests: usize,
    pub updated: usize,
    pub not_modified: usize,
    pub failed: usize,
    /// Field forecasts stored.
    pub fields_updated: usize,
}

/// A source's new state and the field forecasts it brings.
type SourceWrite = (String, SourceState, Vec<(i64, Forecast)>);

enum Outcome {
    /// A new forecast, its `Last-Modified` and how long it is valid (its
    /// `Expires` less its `Date`) [s].
    Fresh(Series, Option<String>, Option<f64>),
    /// Unchanged (304), with how long it stays valid [s].
    NotModified(Option<f64>),
    Failed(String),
}

/// Seconds until the answer expires (`Expires` less the answer's `Date`,
/// or less the real time when it has no `Date`), in [0, 86400]; None
/// without a readable `Expires`. Counted from the answer's own `Date`, so
/// an accelerated clock waits the same number of its own seconds.
fn expires_in(headers: &reqwest::header::HeaderMap) -> Option<f64> {
    let date = |name: reqwest::header::HeaderName| {
        headers
            .get(name)?
            .to_str()
            .ok()
            .and_then(|v| DateTime::parse_from_rfc2822(v.trim()).ok())
            .map(|d| d.to_utc())
    };
    let expires = date(reqwest::header::EXPIRES)?;
    let base = date(reqwest::header::DATE).unwrap_or_else(Utc::now);
    let s = (expires - base).num_milliseconds() as f64 / 1e3;
    Some(s.clamp(0.0, 86_400.0))
}

/// Largest response accepted [bytes].
const MAX_BODY: usize = 8 << 20;

/// Fetches the due sources of a set of fields.
pub struct Poller {
    client: reqwest::Client,
    settings: ForecastSettings,
    store: Arc<Store>,
}

impl Poller {
    pub fn new(settings: ForecastSettings, store: Arc<Store>) -> Result<Poller, String> {
        let client = reqwest::Client::builder()
            .user_agent(settings.user_agent())
            .timeout(std::time::Duration::from_secs_f64(settings.timeout_s))
            .build()
            .map_err(|e| format!("forecast client: {e}"))?;
        Ok(Poller {
            client,
            settings,
            store,
        })
    }

    pub fn settings(&self) -> &ForecastSettings {
        &self.settings
    }

    async fn blocking<T: Send + 'static>(
        &self,
        f: impl FnOnce(&Store) -> Result<T, StoreError> + Send + 'static,
    ) -> Result<T, String> {
        let store = self.store.clone();
        tokio::task::spawn_blocking(move || f(&store))
            .await
            .map_err(|e| e.to_string())?
            .map_err(|e| e.to_string())
    }

    /// One poll at clock time `now`: every source of `fields` that is due
    /// is requested once; a new forecast is stored for each of its fields.
    pub async fn poll(&self, now: DateTime<Utc>, fields: &[Field]) -> Result<PollReport, String> {
        // (field id, control period) by source
        let mut groups: BTreeMap<SourceKey, Vec<(i64, f64)>> = BTreeMap::new();
        for f in fields {
            if let Some(src) = &f.spec.forecast_source {
                groups
                    .entry(src.key(self.settings.location_decimals))
                    .or_default()
                    .push((f.id, f.spec.control_period_s));
            }
        }
        let mut report = PollReport {
            sources: groups.len(),
            ..PollReport::default()
        };
        let ids: Vec<String> = groups.keys().map(SourceKey::id).collect();
        let states = self
            .blocking(move |s| {
                ids.iter()
                    .map(|id| s.forecast_source(id))
                    .collect::<Result<Vec<_>, _>>()
            })
            .await?;
        let mut due = Vec::new();
        for ((key, members), body) in groups.into_iter().zip(states) {
            let state: SourceState = body
                .and_then(|b| serde_json::from_str(&b).ok())
                .unwrap_or_default();
            if state.next_poll_at.is_none_or(|t| t <= now) {
                due.push((key, members, state));
            }
        }
        use futures_util::StreamExt;
        let requests: Vec<_> = due
            .into_iter()
            .map(|(key, members, state)| async move {
                let outcome = self.fetch(&key, &state, now).await;
                (key, members, state, outcome)
            })
            .collect();
        let outcomes: Vec<_> = futures_util::stream::iter(requests)
            .buffer_unordered(4)
            .collect()
            .await;
        report.requests = outcomes.len();
        let mut writes: Vec<SourceWrite> = Vec::new();
        for (key, members, mut state, outcome) in outcomes {
            let mut forecasts = Vec::new();
            match outcome {
                Outcome::Fresh(series, last_modified, expires) => {
                    report.updated += 1;
                    for &(id, period) in &members {
                        if let Some(fc) = to_forecast(&series, period, now) {
                            forecasts.push((id, fc));
                        }
                    }
                    state.series = Some(series);
                    state.last_modified = last_modified;
                    state.fetched_at = Some(now);
                    state.checked_at = Some(now);
                    state.failures = 0;
                    state.last_error = None;
                    state.next_poll_at = Some(now + secs(self.next_wait(expires)));
                }
                Outcome::NotModified(expires) => {
                    report.not_modified += 1;
                    state.checked_at = Some(now);
                    state.failures = 0;
                    state.last_error = None;
                    state.next_poll_at = Some(now + secs(self.next_wait(expires)));
                }
                Outcome::Failed(reason) => {
                    report.failed += 1;
                    state.failures = state.failures.saturating_add(1);
                    let wait = self.backoff(state.failures);
                    tracing::warn!(source = %key.id(), failures = state.failures,
                        retry_in_s = wait, reason = %reason,
                        "forecast refused or provider down; the last good forecast stays in use");
                    state.last_error = Some(reason);
                    state.next_poll_at = Some(now + secs(wait));
                }
            }
            report.fields_updated += forecasts.len();
            writes.push((key.id(), state, forecasts));
        }
        self.blocking(move |s| {
            for (id, state, forecasts) in &writes {
                s.put_forecast_source(id, &serde_json::to_string(state)?)?;
                for (field, f) in forecasts {
                    s.put_forecast(*field, f)?;
                }
            }
            Ok(())
        })
        .await?;
        Ok(report)
    }

    /// The wait after a good answer [s]: the poll interval, or longer when
    /// the answer says it stays valid longer (MET Norway asks clients not
    /// to come back before `Expires`).
    fn next_wait(&self, expires_in: Option<f64>) -> f64 {
        self.settings.poll_interval_s.max(expires_in.unwrap_or(0.0))
    }

    /// The wait after `failures` failures in a row [s]: retry_s doubled per
    /// failure after the first, at most max_backoff_s.
    pub fn backoff(&self, failures: u32) -> f64 {
        let doubled = self.settings.retry_s * 2f64.powi(failures.saturating_sub(1).min(30) as i32);
        doubled.min(self.settings.max_backoff_s)
    }

    async fn fetch(&self, key: &SourceKey, state: &SourceState, now: DateTime<Utc>) -> Outcome {
        let url = match key.url() {
            Ok(u) => u,
            Err(e) => return Outcome::Failed(e),
        };
        let mut req = self
            .client
            .get(url)
            .header(reqwest::header::ACCEPT, "application/json");
        if let Some(lm) = &state.last_modified
            && state.series.is_some()
        {
            req = req.header(reqwest::header::IF_MODIFIED_SINCE, lm);
        }
        let resp = match req.send().await {
            Ok(r) => r,
            Err(e) => return Outcome::Failed(format!("request failed: {e}")),
        };
        let status = resp.status();
        let expires = expires_in(resp.headers());
        if status == reqwest::StatusCode::NOT_MODIFIED {
            return if state.series.is_some() {
                Outcome::NotModified(expires)
            } else {
                Outcome::Failed("304 Not Modified without a forecast kept".into())
            };
        }
        if status.as_u16() == 203 {
            tracing::warn!(source = %key.id(), "the provider marks this product deprecated (203)");
        }
        if !status.is_success() {
            return Outcome::Failed(format!("HTTP {status}"));
        }
        let last_modified = resp
            .headers()
            .get(reqwest::header::LAST_MODIFIED)
            .and_then(|v| v.to_str().ok())
            .map(str::to_string);
        if resp.content_length().is_some_and(|n| n as usize > MAX_BODY) {
            return Outcome::Failed(format!("response larger than {MAX_BODY} bytes"));
        }
        let body = match resp.bytes().await {
            Ok(b) if b.len() > MAX_BODY => {
                return Outcome::Failed(format!("response larger than {MAX_BODY} bytes"));
            }
            Ok(b) => b,
            Err(e) => return Outcome::Failed(format!("reading the response: {e}")),
        };
        let parsed = match key.provider {
            Provider::OpenMeteo => open_meteo::parse(&body, now),
            Provider::MetNorway => met_norway::parse(&body, key.latitude(), key.longitude(), now),
        };
        match parsed {
            Ok(series) if series.intervals.is_empty() => {
                Outcome::Failed("the response holds no complete hour".into())
            }
            Ok(series) => Outcome::Fresh(series, last_modified, expires),
            Err(e) => Outcome::Failed(e.to_string()),
        }
    }
}

fn secs(s: f64) -> TimeDelta {
    TimeDelta::milliseconds((s * 1000.0).round() as i64)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at(s: &str) -> DateTime<Utc> {
        DateTime::parse_from_rfc3339(s).unwrap().to_utc()
    }

    fn hourly(from: &str, values: &[(f64, f64)]) -> Vec<Interval> {
        let t0 = at(from);
        values
            .iter()
            .enumerate()
            .map(|(i, &(e, p))| Interval {
                start: t0 + TimeDelta::hours(i as i64),
                end: t0 + TimeDelta::hours(i as i64 + 1),
                et0_mm: e,
                precip_mm: p,
            })
            .collect()
    }

    #[test]
    fn periods_sum_their_hours_and_the_forecast_stops_at_a_gap() {
        // 3-h periods from 00:00; hours 00–08 then a gap (hour 09 missing)
        let mut ivs = hourly(
            "2026-06-01T00:00:00Z",
            &[
                (0.1, 0.0),
                (0.2, 1.0),
                (0.3, 0.0),
                (0.1, 0.5),
                (0.1, 0.5),
                (0.1, 0.5),
            ],
        );
        ivs.extend(hourly("2026-06-01T06:00:00Z", &[(0.0, 2.0); 3]));
        ivs.extend(hourly("2026-06-01T10:00:00Z", &[(0.0, 0.0); 5]));
        let s = Series {
            issued_at: at("2026-06-01T00:00:00Z"),
            intervals: ivs,
        };
        let f = to_forecast(&s, 3.0 * 3600.0, at("2026-06-01T01:10:00Z")).unwrap();
        assert_eq!(f.start, at("2026-06-01T00:00:00Z"));
        assert_eq!(f.et0_mm.len(), 3, "00–09; 09–12 has a gap");
        for (got, want) in f.et0_mm.iter().zip([0.6, 0.3, 0.0]) {
            assert!((got - want).abs() < 1e-12, "{:?}", f.et0_mm);
        }
        assert_eq!(f.precip_mm, vec![1.0, 1.5, 6.0]);
    }

    #[test]
    fn a_first_period_covered_half_keeps_its_rate_and_less_moves_the_start() {
        // data from 01:00: the period 00:00–02:00 is covered half
        let s = Series {
            issued_at: at("2026-06-01T00:00:00Z"),
            intervals: hourly("2026-06-01T01:00:00Z", &[(0.1, 0.4); 5]),
        };
        let f = to_forecast(&s, 7200.0, at("2026-06-01T01:30:00Z")).unwrap();
        assert_eq!(f.start, at("2026-06-01T00:00:00Z"));
        assert_eq!(f.precip_mm, vec![0.8, 0.8, 0.8]);
        // data from 01:30: less than half; the forecast starts at 02:00
        let mut late = s.clone();
        for iv in &mut late.intervals {
            iv.start += TimeDelta::minutes(30);
            iv.end += TimeDelta::minutes(30);
        }
        let f = to_forecast(&late, 7200.0, at("2026-06-01T01:40:00Z")).unwrap();
        assert_eq!(f.start, at("2026-06-01T02:00:00Z"));
        // and nothing when the data lie beyond the first two periods
        assert!(to_forecast(&late, 3600.0, at("2026-05-31T20:00:00Z")).is_none());
    }

    #[test]
    fn nearby_fields_share_a_source_and_distant_ones_do_not() {
        let spec = |lat: f64, lon: f64| SourceSpec {
            provider: Provider::MetNorway,
            latitude: lat,
            longitude: lon,
            base_url: None,
        };
        assert_eq!(spec(59.9139, 10.7522).key(2), spec(59.9101, 10.7549).key(2));
        assert_ne!(spec(59.9139, 10.7522).key(2), spec(59.9239, 10.7522).key(2));
        assert_ne!(spec(59.9139, 10.7522).key(4), spec(59.9138, 10.7522).key(4));
        let key = spec(59.9139, 10.7522).key(2);
        assert_eq!(
            key.url().unwrap().as_str(),
            "https://api.met.no/weatherapi/locationforecast/2.0/compact?lat=59.9100&lon=10.7500"
        );
        let om = SourceSpec {
            provider: Provider::OpenMeteo,
            base_url: Some("http://127.0.0.1:9/".into()),
            ..spec(1.0, 2.0)
        };
        assert!(
            om.key(2)
                .url()
                .unwrap()
                .as_str()
                .starts_with("http://127.0.0.1:9/v1/forecast?latitude=1&longitude=2&hourly=")
        );
    }

    #[test]
    fn open_meteo_answers_that_do_not_add_up_are_refused() {
        let t = at("2026-06-01T00:00:00Z");
        let doc = |times: &str, et0: &str, unit: &str| {
            format!(
                r#"{{"utc_offset_seconds":0,"hourly_units":{{"time":"iso8601","et0_fao_evapotranspiration":"{unit}","precipitation":"mm"}},
                "hourly":{{"time":{times},"et0_fao_evapotranspiration":{et0},"precipitation":[0.0,0.0]}}}}"#
            )
        };
        let ok = doc(
            r#"["2026-06-01T01:00","2026-06-01T02:00"]"#,
            "[0.1,null]",
            "mm",
        );
        let s = open_meteo::parse(ok.as_bytes(), t).unwrap();
        assert_eq!(s.intervals.len(), 1, "the null hour is left out");
        assert_eq!(s.intervals[0].start, t);
        let cases = [
            (doc(r#"["2026-06-01T01:00"]"#, "[0.1,0.1]", "mm"), "length"),
            (
                doc(
                    r#"["2026-06-01T02:00","2026-06-01T01:00"]"#,
                    "[0.1,0.1]",
                    "mm",
                ),
                "follow",
            ),
            (
                doc(
                    r#"["2026-06-01T01:00","2026-06-01T02:00"]"#,
                    "[0.1,0.1]",
                    "inch",
                ),
                "'inch'",
            ),
            (
                doc(
                    r#"["2026-06-01T01:00","2026-06-01T02:00"]"#,
                    "[25.0,0.1]",
                    "mm",
                ),
                "wrong units",
            ),
            (
                doc(
                    r#"["2026-06-01 01:00","2026-06-01T02:00"]"#,
                    "[0.1,0.1]",
                    "mm",
                ),
                "time[0]",
            ),
        ];
        for (body, needle) in cases {
            let e = open_meteo::parse(body.as_bytes(), t)
                .unwrap_err()
                .to_string();
            assert!(e.contains(needle), "{needle}: {e}");
        }
    }
}
