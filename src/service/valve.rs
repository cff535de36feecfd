//! Valve run times and cycle-and-soak (issue 18).
//!
//! A field that gives its area and its emitters' application rate gets,
//! with every setpoint, the valve time and volume of the period's planned
//! irrigation. When the emitters apply water faster than the soil takes it
//! in, the run is split into pulses with soak intervals between them.
//!
//! The split is predicted with the field's own Richards column (MODEL.md
//! §1: the infiltration capacity of the top face, what exceeds it runs
//! off), started from the state the controller starts from. The run is
//! tried as 1, 2, … [`MAX_PULSES`] equal pulses spread evenly over the
//! period, each followed by an equal soak; the first whose predicted runoff
//! is within [`RUNOFF_TOLERANCE_MM`] (or 1 % of the amount) wins, else the
//! one with the least runoff. Every prediction runs under small work limits;
//! a column that cannot be integrated leaves the schedule at one pulse with
//! no runoff prediction.

use serde::{Deserialize, Serialize};

use crate::soil::column::{AMOUNTS, RUNOFF};
use crate::soil::{
    Column, ColumnState, Crop, Forcing, Integrator, Tolerances, VanGenuchten, WorkLimits,
};

/// Largest field area [m²] (10,000 ha).
pub const AREA_M2: (f64, f64) = (0.0, 1e8);
/// Largest emitter application rate [mm/h].
pub const APPLICATION_RATE_MM_H: (f64, f64) = (0.0, 500.0);
/// Most pulses a period's run is split into.
pub const MAX_PULSES: usize = 8;
/// Predicted runoff [mm] below which a schedule needs no more pulses.
pub const RUNOFF_TOLERANCE_MM: f64 = 0.05;

/// A field's irrigation hardware.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct IrrigationSystem {
    /// Irrigated area [m²], in (0, 1e8].
    pub area_m2: f64,
    /// What the emitters apply while the valve is open [mm/h], in (0, 500].
    pub application_rate_mm_h: f64,
}

impl IrrigationSystem {
    pub fn validate(&self) -> Result<(), String> {
        let ok = |v: f64, (lo, hi): (f64, f64)| v.is_finite() && v > lo && v <= hi;
        if !ok(self.area_m2, AREA_M2) {
            return Err(format!(
                "irrigation_system.area_m2 = {} must lie in (0, {:e}] m²",
                self.area_m2, AREA_M2.1
            ));
        }
        if !ok(self.application_rate_mm_h, APPLICATION_RATE_MM_H) {
            return Err(format!(
                "irrigation_system.application_rate_mm_h = {} must lie in (0, {}] mm/h",
                self.application_rate_mm_h, APPLICATION_RATE_MM_H.1
            ));
        }
        Ok(())
    }

    /// m³ of water for a depth in mm over the field.
    pub fn cubic_metres(&self, mm: f64) -> f64 {
        mm * 1e-3 * self.area_m2
    }
}

/// One opening of the valve.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Pulse {
    /// Seconds after the setpoint's `valid_from`.
    pub start_offset_s: f64,
    pub minutes: f64,
}

/// What the valve does over one period.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ValveSchedule {
    /// Total valve time [min].
    pub valve_minutes: f64,
    /// Water applied [L] and [m³].
    pub litres: f64,
    pub volume_m3: f64,
    /// Depth applied [mm] (less than the setpoint's amount only when the
    /// emitters cannot deliver it within the period).
    pub applied_mm: f64,
    pub pulses: Vec<Pulse>,
    /// Soak after each pulse [min] (0 for a single pulse).
    pub soak_minutes: f64,
    /// Runoff the field's model predicts for this schedule [mm]; absent
    /// when the prediction failed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub predicted_runoff_mm: Option<f64>,
    /// Runoff the model predicts for the same water in one run [mm].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub runoff_single_run_mm: Option<f64>,
}

/// The column the schedule is predicted on: soil, crop, depth and heads
/// (top first), as the controller starts from them.
pub struct ColumnStart {
    pub soil: VanGenuchten,
    pub crop: Crop,
    pub depth: f64,
    pub heads: Vec<f64>,
}

/// The valve schedule of `amount_mm` over a period of `period_s` under the
/// period's weather `weather` (its irrigation is ignored).
pub fn schedule(
    system: &IrrigationSystem,
    amount_mm: f64,
    period_s: f64,
    start: Option<&ColumnStart>,
    weather: Forcing,
) -> ValveSchedule {
    let rate = system.application_rate_mm_h;
    let hours = (amount_mm.max(0.0) / rate).min(period_s / 3600.0);
    let applied_mm = hours * rate;
    let valve_minutes = hours * 60.0;
    let litres = system.cubic_metres(applied_mm) * 1e3;
    let mut out = ValveSchedule {
        valve_minutes,
        litres,
        volume_m3: litres * 1e-3,
        applied_mm,
        pulses: Vec::new(),
        soak_minutes: 0.0,
        predicted_runoff_mm: None,
        runoff_single_run_mm: None,
    };
    if valve_minutes <= 0.0 {
        out.predicted_runoff_mm = Some(0.0);
        return out;
    }
    let one = |n: usize| pulses(n, valve_minutes, period_s);
    out.pulses = one(1);
    let Some(start) = start else {
        return out;
    };
    let tolerance = RUNOFF_TOLERANCE_MM.max(0.01 * applied_mm);
    let mut best: Option<(usize, f64)> = None;
    for n in 1..=MAX_PULSES {
        let Some(runoff) = predicted_runoff(start, &one(n), period_s, rate, weather) else {
            break;
        };
        if n == 1 {
            out.runoff_single_run_mm = Some(runoff);
        }
        if best.is_none_or(|(_, r)| runoff < r) {
            best = Some((n, runoff));
        }
        if runoff <= tolerance {
            break;
        }
    }
    if let Some((n, runoff)) = best {
        out.pulses = one(n);
        out.soak_minutes = soak_minutes(n, valve_minutes, period_s);
        out.predicted_runoff_mm = Some(runoff);
    }
    out
}

/// `n` equal pulses, each at the start of one of `n` equal slices of the
/// period.
fn pulses(n: usize, valve_minutes: f64, period_s: f64) -> Vec<Pulse> {
    let slice = period_s / n as f64;
    (0..n)
        .map(|i| Pulse {
            start_offset_s: i as f64 * slice,
            minutes: valve_minutes / n as f64,
        })
        .collect()
}

fn soak_minutes(n: usize, valve_minutes: f64, period_s: f64) -> f64 {
    if n <= 1 {
        0.0
    } else {
        (period_s / 60.0 - valve_minutes) / n as f64
    }
}

/// Runoff [mm] of the period under `pulses` on the column, or None when the
/// column cannot be integrated within small work limits.
fn predicted_runoff(
    start: &ColumnStart,
    pulses: &[Pulse],
    period_s: f64,
    rate_mm_h: f64,
    weather: Forcing,
) -> Option<f64> {
    let column = Column::new(start.soil, start.crop, start.depth, start.heads.len()).ok()?;
    let mut integrator = Integrator::new(column, Tolerances::default()).ok()?;
    integrator.set_limits(WorkLimits {
        step_attempts: 200,
        newton_iterations: 4_000,
    });
    let mut state = ColumnState {
        heads: start.heads.clone(),
        amounts: [0.0; AMOUNTS],
    };
    let on = rate_mm_h * 1e-3 / 3600.0;
    let mut t = 0.0;
    for (i, p) in pulses.iter().enumerate() {
        let end = (p.start_offset_s + p.minutes * 60.0).min(period_s);
        let next = pulses.get(i + 1).map_or(period_s, |q| q.start_offset_s);
        for (until, irrigation) in [(end, on), (next, 0.0)] {
            if until > t {
                let forcing = Forcing {
                    irrigation,
                    ..weather
                };
                integrator.advance(&mut state, t, until - t, forcing).ok()?;
                t = until;
            }
        }
    }
    Some(state.amounts[RUNOFF] * 1e3)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn calm() -> Forcing {
        Forcing {
            irrigation: 0.0,
            precipitation: 0.0,
            reference_et: 0.0,
        }
    }

    #[test]
    fn time_and_volume_follow_from_depth_rate_and_area() {
        let system = IrrigationSystem {
            area_m2: 2_500.0,
            application_rate_mm_h: 12.0,
        };
        // 3 mm at 12 mm/h is a quarter of an hour; 3 mm on 2,500 m² is 7.5 m³
        let s = schedule(&system, 3.0, 7200.0, None, calm());
        assert!((s.valve_minutes - 15.0).abs() < 1e-12);
        assert!((s.litres - 7_500.0).abs() < 1e-9);
        assert!((s.volume_m3 - 7.5).abs() < 1e-12);
        assert_eq!(s.pulses.len(), 1);
        // emitters too slow for the amount: the valve runs the whole period
        let s = schedule(&system, 30.0, 7200.0, None, calm());
        assert!((s.valve_minutes - 120.0).abs() < 1e-9);
        assert!((s.applied_mm - 24.0).abs() < 1e-9);
    }

    #[test]
    fn bad_hardware_is_refused_naming_the_key() {
        for (area, rate, key) in [
            (0.0, 10.0, "area_m2"),
            (-5.0, 10.0, "area_m2"),
            (f64::NAN, 10.0, "area_m2"),
            (100.0, 0.0, "application_rate_mm_h"),
            (100.0, -1.0, "application_rate_mm_h"),
            (100.0, 1e4, "application_rate_mm_h"),
        ] {
            let e = IrrigationSystem {
                area_m2: area,
                application_rate_mm_h: rate,
            }
            .validate()
            .unwrap_err();
            assert!(e.contains(key), "{e}");
        }
    }

    fn clay_near_saturation() -> ColumnStart {
        let soil = crate::soil::Texture::Clay.parameters();
        ColumnStart {
            soil,
            crop: Crop::default(),
            depth: 1.3,
            heads: vec![-0.3; 26],
        }
    }

    #[test]
    fn fast_emitters_on_a_slow_soil_are_split_and_the_split_cuts_runoff() {
        // clay: Ks = 0.048 m/day = 2 mm/h; 60 mm/h emitters
        let start = clay_near_saturation();
        let system = IrrigationSystem {
            area_m2: 100.0,
            application_rate_mm_h: 60.0,
        };
        let s = schedule(&system, 6.0, 7200.0, Some(&start), calm());
        let single = s.runoff_single_run_mm.expect("the column integrates");
        let split = s.predicted_runoff_mm.unwrap();
        assert!(single > 0.5, "one 6-min run at 60 mm/h runs off: {single}");
        assert!(s.pulses.len() > 1, "{s:?}");
        assert!(split < single, "{split} vs {single}");
        // the pulses add up to the valve time and stay inside the period
        let total: f64 = s.pulses.iter().map(|p| p.minutes).sum();
        assert!((total - s.valve_minutes).abs() < 1e-9);
        let last = s.pulses.last().unwrap();
        assert!(last.start_offset_s + last.minutes * 60.0 <= 7200.0);
        assert!(s.soak_minutes > 0.0);
        // runoff cannot exceed what was applied
        assert!(single <= s.applied_mm + 1e-9);
    }

    #[test]
    fn slow_emitters_on_sand_run_once_without_runoff() {
        let soil = crate::soil::Texture::Sand.parameters();
        let start = ColumnStart {
            soil,
            crop: Crop::default(),
            depth: 1.3,
            heads: vec![-1.0; 26],
        };
        let system = IrrigationSystem {
            area_m2: 100.0,
            application_rate_mm_h: 5.0,
        };
        let s = schedule(&system, 4.0, 7200.0, Some(&start), calm());
        assert_eq!(s.pulses.len(), 1);
        assert_eq!(s.soak_minutes, 0.0);
        assert!(s.predicted_runoff_mm.unwrap() < 1e-12);
    }
}
