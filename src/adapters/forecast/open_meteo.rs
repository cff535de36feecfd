//! Open-Meteo's forecast API (`/v1/forecast`): columnar JSON, hourly
//! `et0_fao_evapotranspiration` and `precipitation` [mm], each a sum over
//! the hour *before* its time stamp.
//!
//! The time stamps are local times without an offset; the response gives
//! one `utc_offset_seconds`, the offset in force when the request was
//! served, and applies it to the whole series (Open-Meteo does not switch
//! offsets at a daylight-saving change inside a forecast: the stamps stay
//! one hour apart and are that constant offset from UTC). So UTC is
//! stamp − utc_offset_seconds for every entry. rootzone asks for
//! `timezone=GMT` (offset 0); an offset in the answer is honoured all the
//! same. Nulls (hours a model does not cover) are hours without data.

use chrono::{DateTime, NaiveDateTime, TimeDelta, Utc};
use serde::Deserialize;

use super::{Interval, ProviderError, Series, check_amount};

#[derive(Deserialize)]
struct Response {
    utc_offset_seconds: i64,
    hourly_units: Units,
    hourly: Hourly,
}

#[derive(Deserialize)]
struct Units {
    #[serde(default)]
    time: Option<String>,
    et0_fao_evapotranspiration: String,
    precipitation: String,
}

#[derive(Deserialize)]
struct Hourly {
    time: Vec<String>,
    et0_fao_evapotranspiration: Vec<Option<f64>>,
    precipitation: Vec<Option<f64>>,
}

/// The query of a location (the path is `base_url` + `/v1/forecast`).
pub fn query(latitude: f64, longitude: f64) -> Vec<(&'static str, String)> {
    vec![
        ("latitude", format!("{latitude}")),
        ("longitude", format!("{longitude}")),
        ("hourly", "et0_fao_evapotranspiration,precipitation".into()),
        ("timezone", "GMT".into()),
        ("forecast_days", "16".into()),
    ]
}

/// Parses a response body into hourly intervals (UTC).
pub fn parse(body: &[u8], fetched_at: DateTime<Utc>) -> Result<Series, ProviderError> {
    let r: Response = serde_json::from_slice(body)
        .map_err(|e| ProviderError::Malformed(format!("open-meteo: {e}")))?;
    if let Some(t) = &r.hourly_units.time
        && t != "iso8601"
    {
        return Err(ProviderError::Units(format!(
            "open-meteo: hourly_units.time = '{t}', expected 'iso8601'"
        )));
    }
    for (name, unit) in [
        (
            "et0_fao_evapotranspiration",
            &r.hourly_units.et0_fao_evapotranspiration,
        ),
        ("precipitation", &r.hourly_units.precipitation),
    ] {
        if unit != "mm" {
            return Err(ProviderError::Units(format!(
                "open-meteo: hourly_units.{name} = '{unit}', expected 'mm'"
            )));
        }
    }
    if !(-18 * 3600..=18 * 3600).contains(&r.utc_offset_seconds) {
        return Err(ProviderError::Malformed(format!(
            "open-meteo: utc_offset_seconds = {} is not an offset",
            r.utc_offset_seconds
        )));
    }
    let h = &r.hourly;
    let n = h.time.len();
    if h.et0_fao_evapotranspiration.len() != n || h.precipitation.len() != n {
        return Err(ProviderError::Malformed(format!(
            "open-meteo: hourly arrays differ in length (time {n}, et0 {}, precipitation {})",
            h.et0_fao_evapotranspiration.len(),
            h.precipitation.len()
        )));
    }
    if n == 0 {
        return Err(ProviderError::Malformed(
            "open-meteo: no hourly data".into(),
        ));
    }
    let offset = TimeDelta::seconds(r.utc_offset_seconds);
    let mut intervals = Vec::with_capacity(n);
    let mut previous: Option<DateTime<Utc>> = None;
    for (i, stamp) in h.time.iter().enumerate() {
        let local = NaiveDateTime::parse_from_str(stamp, "%Y-%m-%dT%H:%M").map_err(|e| {
            ProviderError::Malformed(format!("open-meteo: hourly.time[{i}] = '{stamp}': {e}"))
        })?;
        let end = local.and_utc() - offset;
        if previous.is_some_and(|p| end <= p) {
            return Err(ProviderError::Malformed(format!(
                "open-meteo: hourly.time[{i}] = '{stamp}' does not follow the one before"
            )));
        }
        previous = Some(end);
        let (Some(et0), Some(precip)) = (h.et0_fao_evapotranspiration[i], h.precipitation[i])
        else {
            continue;
        };
        let et0 = check_amount("open-meteo et0_fao_evapotranspiration", i, et0, 1.0, true)?;
        let precip = check_amount("open-meteo precipitation", i, precip, 1.0, false)?;
        intervals.push(Interval {
            start: end - TimeDelta::hours(1),
            end,
            et0_mm: et0,
            precip_mm: precip,
        });
    }
    Ok(Series {
        issued_at: fetched_at,
        intervals,
    })
}
