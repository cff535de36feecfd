//! MET Norway's `locationforecast/2.0/compact`: GeoJSON whose
//! `properties.timeseries[]` holds, per UTC time, the instant air
//! temperature and the precipitation of the next hour (`next_1_hours`, the
//! first ~2.5 days) or of the next six hours (`next_6_hours`, with the
//! six hours' air temperature extremes; the tail has only these). Where
//! the series is hourly its instants give a day's extremes; in the tail
//! the six-hour extremes are used too.
//!
//! It forecasts no ET0: rootzone computes FAO-56 Hargreaves ET0
//! ([`super::hargreaves`]) per solar day from the day's extreme
//! temperatures and the site's latitude, and spreads it over the day's
//! hours in proportion to the extraterrestrial irradiance (zero at night),
//! so a day's intervals add up to that day's Hargreaves ET0. A day the
//! forecast covers only in part (its first and last) takes its extremes
//! from the 24 hours of forecast nearest to it.

use chrono::{DateTime, Datelike, TimeDelta, Utc};
use serde::Deserialize;

use super::hargreaves::{earth_sun, extraterrestrial_radiation, hargreaves_et0, radiation_share};
use super::{Interval, ProviderError, Series, check_amount};

#[derive(Deserialize)]
struct Response {
    properties: Properties,
}

#[derive(Deserialize)]
struct Properties {
    meta: Meta,
    timeseries: Vec<Entry>,
}

#[derive(Deserialize)]
struct Meta {
    #[serde(default)]
    updated_at: Option<DateTime<Utc>>,
    units: MetUnits,
}

#[derive(Deserialize)]
struct MetUnits {
    air_temperature: String,
    precipitation_amount: String,
}

#[derive(Deserialize)]
struct Entry {
    time: DateTime<Utc>,
    data: Data,
}

#[derive(Deserialize)]
struct Data {
    instant: Instant,
    #[serde(default)]
    next_1_hours: Option<Next>,
    #[serde(default)]
    next_6_hours: Option<Next>,
}

#[derive(Deserialize)]
struct Instant {
    details: InstantDetails,
}

#[derive(Deserialize)]
struct InstantDetails {
    #[serde(default)]
    air_temperature: Option<f64>,
}

#[derive(Deserialize)]
struct Next {
    #[serde(default)]
    details: NextDetails,
}

#[derive(Deserialize, Default)]
struct NextDetails {
    #[serde(default)]
    precipitation_amount: Option<f64>,
    #[serde(default)]
    air_temperature_max: Option<f64>,
    #[serde(default)]
    air_temperature_min: Option<f64>,
}

/// The query of a location: MET Norway takes at most 4 decimals.
pub fn query(latitude: f64, longitude: f64) -> Vec<(&'static str, String)> {
    vec![
        ("lat", format!("{:.4}", latitude)),
        ("lon", format!("{:.4}", longitude)),
    ]
}

/// The plausible air temperatures [°C].
const TEMPERATURE: (f64, f64) = (-90.0, 60.0);

fn temperature(what: &str, i: usize, t: f64) -> Result<f64, ProviderError> {
    if t.is_finite() && (TEMPERATURE.0..=TEMPERATURE.1).contains(&t) {
        Ok(t)
    } else {
        Err(ProviderError::Units(format!(
            "met-norway: timeseries[{i}] {what} = {t} °C is outside [{}, {}] (wrong units?)",
            TEMPERATURE.0, TEMPERATURE.1
        )))
    }
}

/// Parses a response for the site at (`latitude`, `longitude`).
pub fn parse(
    body: &[u8],
    latitude: f64,
    longitude: f64,
    fetched_at: DateTime<Utc>,
) -> Result<Series, ProviderError> {
    let r: Response = serde_json::from_slice(body)
        .map_err(|e| ProviderError::Malformed(format!("met-norway: {e}")))?;
    let units = &r.properties.meta.units;
    if units.air_temperature != "celsius" {
        return Err(ProviderError::Units(format!(
            "met-norway: units.air_temperature = '{}', expected 'celsius'",
            units.air_temperature
        )));
    }
    if units.precipitation_amount != "mm" {
        return Err(ProviderError::Units(format!(
            "met-norway: units.precipitation_amount = '{}', expected 'mm'",
            units.precipitation_amount
        )));
    }
    let ts = &r.properties.timeseries;
    if ts.is_empty() {
        return Err(ProviderError::Malformed("met-norway: no timeseries".into()));
    }
    // temperatures: instants and six-hour extremes, as (from, to, max, min)
    let mut temps: Vec<(DateTime<Utc>, DateTime<Utc>, f64, f64)> = Vec::new();
    // precipitation intervals, not yet with ET0
    let mut rain: Vec<(DateTime<Utc>, DateTime<Utc>, f64)> = Vec::new();
    for (i, e) in ts.iter().enumerate() {
        if i > 0 && e.time <= ts[i - 1].time {
            return Err(ProviderError::Malformed(format!(
                "met-norway: timeseries[{i}].time = {} does not follow the one before",
                e.time.to_rfc3339()
            )));
        }
        if let Some(t) = e.data.instant.details.air_temperature {
            let t = temperature("air_temperature", i, t)?;
            temps.push((e.time, e.time, t, t));
        }
        let six = e.data.next_6_hours.as_ref().map(|n| &n.details);
        let hourly = e.data.next_1_hours.is_some();
        // six-hour extremes where the instants are six-hourly (the tail);
        // where they are hourly the instants are the extremes
        if let Some(d) = six.filter(|_| !hourly)
            && let (Some(hi), Some(lo)) = (d.air_temperature_max, d.air_temperature_min)
        {
            let (hi, lo) = (
                temperature("air_temperature_max", i, hi)?,
                temperature("air_temperature_min", i, lo)?,
            );
            temps.push((e.time, e.time + TimeDelta::hours(6), hi, lo));
        }
        let one = e
            .data
            .next_1_hours
            .as_ref()
            .and_then(|n| n.details.precipitation_amount);
        let (hours, amount) = match (one, six.and_then(|d| d.precipitation_amount)) {
            (Some(p), _) => (1, p),
            (None, Some(p)) => (6, p),
            (None, None) => continue,
        };
        let amount = check_amount(
            "met-norway precipitation_amount",
            i,
            amount,
            hours as f64,
            false,
        )?;
        let end = e.time + TimeDelta::hours(hours);
        // a block that runs into the next entry is cut there (its amount
        // spread evenly over its hours)
        let next = ts.get(i + 1).map(|n| n.time);
        let (end, amount) = match next {
            Some(n) if n < end => {
                let share = (n - e.time).num_seconds() as f64 / (end - e.time).num_seconds() as f64;
                (n, amount * share)
            }
            _ => (end, amount),
        };
        rain.push((e.time, end, amount));
    }
    if temps.is_empty() {
        return Err(ProviderError::Malformed(
            "met-norway: no air temperatures, so no ET0".into(),
        ));
    }
    let span = (
        temps.iter().map(|t| t.0).min().unwrap_or(ts[0].time),
        temps.iter().map(|t| t.1).max().unwrap_or(ts[0].time),
    );
    let et0 = DailyEt0 {
        latitude,
        longitude,
        temps,
        span,
        cache: std::cell::RefCell::new(Vec::new()),
    };
    let intervals = rain
        .into_iter()
        .map(|(start, end, precip_mm)| Interval {
            start,
            end,
            et0_mm: et0.over(start, end),
            precip_mm,
        })
        .collect();
    Ok(Series {
        issued_at: r.properties.meta.updated_at.unwrap_or(fetched_at),
        intervals,
    })
}

/// Hargreaves ET0 of solar days, spread by irradiance.
struct DailyEt0 {
    latitude: f64,
    longitude: f64,
    temps: Vec<(DateTime<Utc>, DateTime<Utc>, f64, f64)>,
    span: (DateTime<Utc>, DateTime<Utc>),
    /// (day start, ET0 [mm/day]) of the days seen.
    cache: std::cell::RefCell<Vec<(DateTime<Utc>, f64)>>,
}

impl DailyEt0 {
    /// The solar day holding `t`: its start (UTC) and day of year.
    fn day(&self, t: DateTime<Utc>) -> (DateTime<Utc>, u32) {
        let shift = TimeDelta::milliseconds((self.longitude / 15.0 * 3_600_000.0) as i64);
        let solar = t + shift;
        let midnight = solar
            .date_naive()
            .and_hms_opt(0, 0, 0)
            .map(|m| m.and_utc())
            .unwrap_or(solar);
        (midnight - shift, solar.ordinal())
    }

    /// ET0 [mm/day] of the day starting at `start`.
    fn of_day(&self, start: DateTime<Utc>, doy: u32) -> f64 {
        if let Some(&(_, e)) = self.cache.borrow().iter().find(|c| c.0 == start) {
            return e;
        }
        let day = TimeDelta::hours(24);
        // the day's window, moved inside the forecast when it covers the
        // day only in part
        let (mut from, mut to) = (start, start + day);
        if from < self.span.0 {
            from = self.span.0;
            to = from + day;
        } else if to > self.span.1 {
            to = self.span.1;
            from = to - day;
        }
        let (mut hi, mut lo) = (f64::NEG_INFINITY, f64::INFINITY);
        for &(a, b, max, min) in &self.temps {
            let overlaps = if a == b {
                a >= from && a < to
            } else {
                a < to && b > from
            };
            if overlaps {
                hi = hi.max(max);
                lo = lo.min(min);
            }
        }
        let et0 = if hi >= lo {
            hargreaves_et0(hi, lo, extraterrestrial_radiation(self.latitude, doy))
        } else {
            0.0
        };
        self.cache.borrow_mut().push((start, et0));
        et0
    }

    /// ET0 [mm] over [from, to).
    fn over(&self, from: DateTime<Utc>, to: DateTime<Utc>) -> f64 {
        let phi = self.latitude.to_radians();
        let mut total = 0.0;
        let mut t = from;
        // piece by piece within one solar day
        while t < to {
            let (start, doy) = self.day(t);
            let end = (start + TimeDelta::hours(24)).min(to);
            let w = |x: DateTime<Utc>| {
                ((x - start).num_milliseconds() as f64 / 3.6e6 - 12.0) * std::f64::consts::PI / 12.0
            };
            let (_, delta) = earth_sun(doy);
            total += self.of_day(start, doy) * radiation_share(phi, delta, w(t), w(end));
            t = end;
        }
        total
    }
}
