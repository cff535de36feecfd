//! Water accounts (issue 18): the irrigation a field was told to apply, per
//! day, week and season.
//!
//! A setpoint applies its rate from `valid_from` until it expires
//! (`valid_until`) or the next setpoint replaces it, whichever comes first,
//! so a control cycle run on demand between boundaries is not counted
//! twice. Windows are in UTC: the day from midnight, the week from Monday
//! 00:00 (ISO 8601), the season from 1 January.

use chrono::{DateTime, Datelike, Duration, NaiveTime, TimeZone, Utc};
use serde::Serialize;

use super::valve::IrrigationSystem;
use super::wire::Setpoint;

/// The water of one window.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct WaterTotal {
    pub from: DateTime<Utc>,
    pub to: DateTime<Utc>,
    /// Depth [mm].
    pub mm: f64,
    /// Volume [m³]; absent for a field without an `irrigation_system` area.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub m3: Option<f64>,
}

/// A field's water accounts at `now`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct WaterAccounts {
    pub field_id: i64,
    pub day: WaterTotal,
    pub week: WaterTotal,
    pub season: WaterTotal,
}

/// The depth [mm] that `setpoints` (oldest first) apply within [from, to).
pub fn applied_mm(setpoints: &[Setpoint], from: DateTime<Utc>, to: DateTime<Utc>) -> f64 {
    let mut total = 0.0;
    for (i, s) in setpoints.iter().enumerate() {
        let mut end = s.valid_until;
        if let Some(next) = setpoints.get(i + 1) {
            end = end.min(next.valid_from.max(s.valid_from));
        }
        let a = s.valid_from.max(from);
        let b = end.min(to);
        if b > a && s.rate.is_finite() && s.rate > 0.0 {
            total += s.rate * (b - a).as_seconds_f64() * 1e3;
        }
    }
    total
}

/// The start of `now`'s day, ISO week and calendar year (UTC).
pub fn windows(now: DateTime<Utc>) -> [DateTime<Utc>; 3] {
    let midnight = Utc.from_utc_datetime(&now.date_naive().and_time(NaiveTime::MIN));
    let monday = midnight - Duration::days(i64::from(now.weekday().num_days_from_monday()));
    let year = Utc
        .with_ymd_and_hms(now.year(), 1, 1, 0, 0, 0)
        .single()
        .unwrap_or(midnight);
    [midnight, monday, year]
}

/// The accounts of a field from its setpoints since the start of the
/// season (oldest first) at `now`.
pub fn accounts(
    field_id: i64,
    setpoints: &[Setpoint],
    system: Option<&IrrigationSystem>,
    now: DateTime<Utc>,
) -> WaterAccounts {
    let total = |from: DateTime<Utc>| {
        let mm = applied_mm(setpoints, from, now);
        WaterTotal {
            from,
            to: now,
            mm,
            m3: system.map(|s| s.cubic_metres(mm)),
        }
    };
    let [day, week, season] = windows(now);
    WaterAccounts {
        field_id,
        day: total(day),
        week: total(week),
        season: total(season),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::service::wire::ModelKind;

    fn at(s: &str) -> DateTime<Utc> {
        s.parse().unwrap()
    }

    fn setpoint(from: &str, hours: i64, rate: f64) -> Setpoint {
        let valid_from = at(from);
        Setpoint {
            field_id: 1,
            time: valid_from,
            valid_from,
            valid_until: valid_from + Duration::hours(hours),
            rate,
            amount_mm: rate * hours as f64 * 3.6e6,
            plan: vec![],
            predicted_theta: vec![],
            zone: vec![],
            model: ModelKind::Richards,
            status: "converged".into(),
            fallback_reason: None,
            iterations: 0,
            solve_ms: 0.0,
            degraded: vec![],
            measured_at: None,
            bias: 0.0,
            predicted_next: None,
            valve: None,
            surrogate: None,
            forecast: None,
            predicted_theta_dry: Vec::new(),
            rain_mm: Vec::new(),
            et0_mm: Vec::new(),
            explanation: String::new(),
        }
    }

    #[test]
    fn a_replaced_setpoint_counts_only_until_it_was_replaced() {
        // 1e-6 m/s = 3.6 mm/h
        let s = [
            setpoint("2026-06-03T00:00:00Z", 2, 1e-6),
            // an on-demand cycle one hour in replaces it: 0.5e-6 for 2 h
            setpoint("2026-06-03T01:00:00Z", 2, 0.5e-6),
        ];
        let mm = applied_mm(&s, at("2026-06-01T00:00:00Z"), at("2026-06-04T00:00:00Z"));
        assert!((mm - (3.6 + 3.6)).abs() < 1e-9, "{mm}");
        // a window cuts a period
        let mm = applied_mm(&s, at("2026-06-03T00:30:00Z"), at("2026-06-03T02:00:00Z"));
        assert!((mm - (1.8 + 1.8)).abs() < 1e-9, "{mm}");
        // the running period counts up to now
        let mm = applied_mm(&s, at("2026-06-03T00:00:00Z"), at("2026-06-03T00:15:00Z"));
        assert!((mm - 0.9).abs() < 1e-9, "{mm}");
    }

    #[test]
    fn windows_start_at_midnight_monday_and_new_year() {
        // 2026-06-03 is a Wednesday
        let [d, w, y] = windows(at("2026-06-03T13:45:10Z"));
        assert_eq!(d, at("2026-06-03T00:00:00Z"));
        assert_eq!(w, at("2026-06-01T00:00:00Z"));
        assert_eq!(y, at("2026-01-01T00:00:00Z"));
        let system = IrrigationSystem {
            area_m2: 10_000.0,
            application_rate_mm_h: 10.0,
        };
        let s = [
            setpoint("2026-05-31T22:00:00Z", 2, 1e-6), // Sunday: season only
            setpoint("2026-06-02T00:00:00Z", 2, 1e-6), // this week
            setpoint("2026-06-03T10:00:00Z", 2, 1e-6), // today
        ];
        let a = accounts(1, &s, Some(&system), at("2026-06-03T13:45:10Z"));
        assert!((a.day.mm - 7.2).abs() < 1e-9);
        assert!((a.week.mm - 14.4).abs() < 1e-9);
        assert!((a.season.mm - 21.6).abs() < 1e-9);
        // 7.2 mm on a hectare is 72 m³
        assert!((a.day.m3.unwrap() - 72.0).abs() < 1e-9);
        assert!(
            accounts(1, &s, None, at("2026-06-03T13:45:10Z"))
                .day
                .m3
                .is_none()
        );
    }
}
