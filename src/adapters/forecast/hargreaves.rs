//! FAO-56 temperature-based reference evapotranspiration (Hargreaves), for
//! providers that forecast temperatures but no ET0 (MET Norway).
//!
//! Allen, Pereira, Raes & Smith (1998), *Crop evapotranspiration*, FAO
//! Irrigation and Drainage Paper 56: extraterrestrial radiation Ra from
//! latitude and day of year (eqs 21–25) and the Hargreaves equation (eq 52),
//! ET0 = 0.0023 (Tmean + 17.8) (Tmax − Tmin)^0.5 · 0.408 Ra [mm/day].
//!
//! Accuracy (FAO-56, chapter 3, "Missing climatic data"): Hargreaves ET0
//! estimates should be checked against Penman-Monteith where possible; the
//! equation tends to underpredict under high winds (u2 > 3 m/s) and to
//! overpredict under high relative humidity. Published comparisons (Allen
//! et al. 1998; Hargreaves & Allen 2003) put it typically within about
//! ±10–20 % of Penman-Monteith on weekly to monthly totals, worse on single
//! days. rootzone uses it only where the provider gives nothing better.

use std::f64::consts::PI;

/// Solar constant [MJ m⁻² min⁻¹] (FAO-56 eq 21).
const SOLAR_CONSTANT: f64 = 0.0820;

/// Inverse relative Earth–Sun distance dr (eq 23) and solar declination δ
/// [rad] (eq 24) on day of year `doy` (1 … 366).
pub fn earth_sun(doy: u32) -> (f64, f64) {
    let x = 2.0 * PI * doy as f64 / 365.0;
    (1.0 + 0.033 * x.cos(), 0.409 * (x - 1.39).sin())
}

/// Sunset hour angle ωs [rad] (eq 25) at latitude φ [rad] with declination
/// δ; the argument is clamped, so polar day gives π and polar night 0.
pub fn sunset_hour_angle(phi: f64, delta: f64) -> f64 {
    (-phi.tan() * delta.tan()).clamp(-1.0, 1.0).acos()
}

/// Daily extraterrestrial radiation Ra [MJ m⁻² day⁻¹] at `latitude_deg`
/// (south negative) on day of year `doy` (eq 21).
pub fn extraterrestrial_radiation(latitude_deg: f64, doy: u32) -> f64 {
    let phi = latitude_deg.to_radians();
    let (dr, delta) = earth_sun(doy);
    let ws = sunset_hour_angle(phi, delta);
    let ra = 24.0 * 60.0 / PI
        * SOLAR_CONSTANT
        * dr
        * (ws * phi.sin() * delta.sin() + phi.cos() * delta.cos() * ws.sin());
    ra.max(0.0)
}

/// Hargreaves ET0 [mm/day] from the day's extreme temperatures [°C] and Ra
/// [MJ m⁻² day⁻¹] (eq 52, with Tmean = (Tmax + Tmin)/2 as FAO-56 uses it).
/// A range below zero (inconsistent input) counts as zero.
pub fn hargreaves_et0(t_max: f64, t_min: f64, ra: f64) -> f64 {
    let t_mean = (t_max + t_min) / 2.0;
    let range = (t_max - t_min).max(0.0);
    (0.0023 * (t_mean + 17.8) * range.sqrt() * 0.408 * ra).max(0.0)
}

/// The extraterrestrial radiation between solar hour angles ω1 < ω2 [rad]
/// of one day, relative to the day's (∫ of dr·cos zenith over the sunlit
/// part of [ω1, ω2] divided by the same over the whole day; FAO-56 eq 28
/// over eq 21). Spreads a day's ET0 over its hours; 0 in polar night.
pub fn radiation_share(phi: f64, delta: f64, w1: f64, w2: f64) -> f64 {
    let ws = sunset_hour_angle(phi, delta);
    let (a, b) = (phi.sin() * delta.sin(), phi.cos() * delta.cos());
    let integral = |lo: f64, hi: f64| {
        let (lo, hi) = (lo.max(-ws), hi.min(ws));
        if hi > lo {
            a * (hi - lo) + b * (hi.sin() - lo.sin())
        } else {
            0.0
        }
    };
    let day = integral(-ws, ws);
    if day > 0.0 {
        (integral(w1, w2) / day).clamp(0.0, 1.0)
    } else {
        0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fao56_example_8_extraterrestrial_radiation() {
        // FAO-56 Example 8: 20° S on 3 September (day 246): Ra = 32.2 MJ m⁻² day⁻¹
        // (dr = 0.985, δ = 0.120 rad, ωs = 1.527 rad in the worked example)
        let doy = 246;
        let (dr, delta) = earth_sun(doy);
        assert!((dr - 0.985).abs() < 5e-4, "dr = {dr}");
        assert!((delta - 0.120).abs() < 5e-4, "δ = {delta}");
        let ws = sunset_hour_angle((-20f64).to_radians(), delta);
        assert!((ws - 1.527).abs() < 5e-4, "ωs = {ws}");
        let ra = extraterrestrial_radiation(-20.0, doy);
        assert!((ra - 32.2).abs() < 0.05, "Ra = {ra}");
    }

    #[test]
    fn polar_night_has_no_radiation_and_polar_day_some() {
        // 80° N around the winter solstice: the sun never rises
        assert_eq!(extraterrestrial_radiation(80.0, 355), 0.0);
        // and around the summer solstice it never sets (ωs = π)
        let (_, delta) = earth_sun(172);
        assert_eq!(sunset_hour_angle(80f64.to_radians(), delta), PI);
        assert!(extraterrestrial_radiation(80.0, 172) > 40.0);
    }

    #[test]
    fn a_day_shares_out_to_one_and_nights_get_nothing() {
        use std::f64::consts::PI;
        let (_, delta) = earth_sun(246);
        let phi = (-20f64).to_radians();
        let ws = sunset_hour_angle(phi, delta);
        let hours: f64 = (0..24)
            .map(|h| {
                let w = |h: f64| (h - 12.0) * PI / 12.0;
                radiation_share(phi, delta, w(h as f64), w(h as f64 + 1.0))
            })
            .sum();
        assert!((hours - 1.0).abs() < 1e-12, "{hours}");
        // before sunrise, nothing; the morning and the afternoon alike
        assert_eq!(radiation_share(phi, delta, -PI, -ws), 0.0);
        let am = radiation_share(phi, delta, -ws, 0.0);
        assert!((am - 0.5).abs() < 1e-12);
    }

    #[test]
    fn hargreaves_by_hand() {
        // 0.0023 · (20 + 17.8) · √10 · 0.408 · 30 = 3.3656… mm/day
        let et0 = hargreaves_et0(25.0, 15.0, 30.0);
        let by_hand = 0.0023 * 37.8 * 10f64.sqrt() * 0.408 * 30.0;
        assert!((et0 - by_hand).abs() < 1e-12);
        assert!((et0 - 3.3656).abs() < 1e-3, "{et0}");
        // an inverted range is not a negative ET0
        assert_eq!(hargreaves_et0(10.0, 12.0, 30.0), 0.0);
    }
}
