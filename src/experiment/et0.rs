//! The weather experiment (issue 17): does the two-layer ZMPC know the
//! weather? Five-day seasons whose ET0 is held at 1.5, 4 and 7 mm/day,
//! rises from 2 to 7 mm/day or alternates between 2 and 7 from day to day,
//! one at 5 mm/day with rain on days 2 and 3, and weather-rain, each run by
//! the oracle (the Richards ZMPC on the plant's true soil and state, the
//! yardstick), by the two-layer ZMPC fed the forecast ET0, and by the same
//! network told a constant 4 mm/day (the training weather of the networks
//! without ET0). The alternating and the rainy season are weather the issue
//! does not name, for the general case; both miss the dry-side target
//! (ARCHITECTURE.md).
//! Both two-layer runs read the sensor through the reading filter
//! ([`crate::control::Controller::with_reading_filter`]: the ensemble filter
//! around the networks' soil, told the sensor's noise; the daemon's surrogate
//! cycles do not have it yet). On the raw readings (MODEL.md §3's f = 2 bias)
//! the two-layer ZMPC irrigated 6.3 ± 0.7 % more than the oracle at
//! 1.5 mm/day and 6.3 ± 0.8 % more in rain over seeds 3 … 102: it answered
//! each noisy reading below the zone with a large move.
//!
//! Conditions: the models' own soil, 2 % process and 2 % measurement noise,
//! 20 % forecast error, the time-invariant zone, 60 steps from θ0 of MODEL.md
//! §1, the seeds `--seed` … `--seed` + `--seeds` − 1: one season's I_T moves
//! by several per cent with the seed (the networks before the refinement
//! stage, 1.5 mm/day: +6.2 %, +10.2 %, +1.3 % on seeds 3, 5, 7), so the
//! controllers are compared on their means.

use std::fmt::Write as _;
use std::path::PathBuf;

use crate::control::{
    ClosedLoopRun, ClosedLoopSettings, Controller, MpcSettings, ZoneSettings, reading_filter,
    relative_noise_sd, run_closed_loop,
};
use crate::soil::FieldSettings;
use crate::weather::{DRY_SCENARIO, RAIN_SCENARIO, WeatherSeries, WeatherStep};

use super::closed_loop::{BIAS_PERIOD, Models, SeedMean};
use super::{ExperimentError, ExperimentOptions, write_file};

/// Steps of a day (2-h steps).
const STEPS_PER_DAY: usize = 12;
/// The daily ET0 of the dry scenario, whose diurnal shape the seasons keep.
const DRY_DAILY_MM: f64 = 4.0;

/// One season: its name and weather.
struct Season {
    name: String,
    weather: WeatherSeries,
}

fn parse(text: &str, name: &str) -> Result<WeatherSeries, ExperimentError> {
    WeatherSeries::parse(text, name).map_err(|e| ExperimentError::Input(e.to_string()))
}

/// The dry scenario's 60 steps with each day's ET0 scaled to `daily(day)`
/// mm/day (no rain).
fn scaled_dry(daily: impl Fn(usize) -> f64) -> Result<WeatherSeries, ExperimentError> {
    let dry = parse(DRY_SCENARIO, "embedded weather-dry.csv")?;
    let steps = dry
        .steps()
        .iter()
        .enumerate()
        .map(|(k, w)| WeatherStep {
            et0_mm: w.et0_mm * daily(k / STEPS_PER_DAY) / DRY_DAILY_MM,
            precip_mm: 0.0,
            ..*w
        })
        .collect();
    Ok(WeatherSeries::new(steps))
}

/// `weather` with the rain (step, mm) added.
fn with_rain(weather: WeatherSeries, rain: &[(usize, f64)]) -> WeatherSeries {
    let mut steps = weather.steps().to_vec();
    for &(k, mm) in rain {
        if let Some(w) = steps.get_mut(k) {
            w.precip_mm += mm;
        }
    }
    WeatherSeries::new(steps)
}

fn seasons() -> Result<Vec<Season>, ExperimentError> {
    let mut out = Vec::new();
    for mm in [1.5, 4.0, 7.0] {
        out.push(Season {
            name: format!("ET0 {mm} mm/day"),
            weather: scaled_dry(|_| mm)?,
        });
    }
    out.push(Season {
        name: "ET0 2 → 7 mm/day".into(),
        // day 0 at 2, day 4 at 7, in equal steps
        weather: scaled_dry(|d| 2.0 + 5.0 * d.min(4) as f64 / 4.0)?,
    });
    // weather the issue does not name, for the general case: a hot day
    // straight after a mild one while the window still holds the season's
    // start, and rain events at a high ET0
    out.push(Season {
        name: "ET0 2 / 7 mm/day, alternating".into(),
        weather: scaled_dry(|d| if d % 2 == 0 { 2.0 } else { 7.0 })?,
    });
    out.push(Season {
        name: "ET0 5 mm/day, rain on days 2 and 3".into(),
        weather: with_rain(
            scaled_dry(|_| 5.0)?,
            &[(26, 6.0), (27, 4.0), (44, 12.0), (45, 6.0)],
        ),
    });
    out.push(Season {
        name: "weather-rain".into(),
        weather: parse(RAIN_SCENARIO, "embedded weather-rain.csv")?,
    });
    Ok(out)
}

/// The controllers compared.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Runner {
    Oracle,
    TwoLayer,
    /// The two-layer network told 4 mm/day (the dry scenario's ET0).
    TwoLayerHeld,
}

fn run_one(
    runner: Runner,
    models: &Models,
    weather: &WeatherSeries,
    seed: u64,
) -> Result<ClosedLoopRun, ExperimentError> {
    let mpc = MpcSettings {
        zone: ZoneSettings::default(),
        theta_r: models.field.soil.residual_water_content,
        theta_s: models.field.soil.saturated_water_content,
        ..MpcSettings::default()
    };
    let told_et0 = match runner {
        Runner::TwoLayerHeld => Some(
            parse(DRY_SCENARIO, "embedded weather-dry.csv")?
                .steps()
                .iter()
                .map(|w| w.et0_mm)
                .collect(),
        ),
        _ => None,
    };
    let settings = ClosedLoopSettings {
        field: FieldSettings {
            process_noise: 0.02,
            measurement_noise: 0.02,
            seed,
            ..models.field
        },
        forecast_error: 0.2,
        forecast_seed: seed.wrapping_add(1000),
        told_et0,
        ..ClosedLoopSettings::default()
    };
    let dt = settings.field.sampling_time;
    // the reading filter around the networks' own soil, told the sensor's
    // noise at the middle of the zone
    let sd = relative_noise_sd(
        settings.field.measurement_noise,
        0.5 * (mpc.zone.y_low + mpc.zone.y_up),
    );
    let mut failure = None;
    let mut make = |first: f64| match runner {
        Runner::Oracle => Controller::oracle(mpc, dt),
        Runner::TwoLayer | Runner::TwoLayerHeld => {
            match reading_filter(models.field.soil, first, sd, seed.wrapping_add(2000)) {
                Ok(filter) => {
                    Controller::surrogate(mpc, models.two_layer.predictor(), BIAS_PERIOD, first, dt)
                        .with_reading_filter(filter)
                }
                Err(e) => {
                    failure = Some(e);
                    Controller::oracle(mpc, dt)
                }
            }
        }
    };
    let run = run_closed_loop(&settings, weather, &mut make)
        .map_err(|e| ExperimentError::Input(format!("closed loop: {e}")));
    match failure {
        Some(e) => Err(ExperimentError::Input(format!("reading filter: {e}"))),
        None => run,
    }
}

/// One season's three runs: oracle, two-layer, two-layer told 4 mm/day.
pub struct SeasonResult {
    pub name: String,
    pub oracle: ClosedLoopRun,
    pub two_layer: ClosedLoopRun,
    pub held: ClosedLoopRun,
}

/// Runs every season (in parallel, one season per task).
pub fn season_results(models: &Models, seed: u64) -> Result<Vec<SeasonResult>, ExperimentError> {
    use rayon::prelude::*;
    seasons()?
        .into_par_iter()
        .map(|s| {
            Ok(SeasonResult {
                oracle: run_one(Runner::Oracle, models, &s.weather, seed)?,
                two_layer: run_one(Runner::TwoLayer, models, &s.weather, seed)?,
                held: run_one(Runner::TwoLayerHeld, models, &s.weather, seed)?,
                name: s.name,
            })
        })
        .collect()
}

fn percent(value: f64, reference: f64) -> f64 {
    100.0 * (value - reference) / reference
}

/// One controller's scores on one season over the seeds.
struct Scores {
    irrigation_mm: Vec<f64>,
    dry: Vec<f64>,
}

impl Scores {
    fn new() -> Scores {
        Scores {
            irrigation_mm: Vec::new(),
            dry: Vec::new(),
        }
    }
    fn push(&mut self, run: &ClosedLoopRun) {
        self.irrigation_mm.push(run.total_irrigation_mm());
        self.dry.push(run.dry_violation());
    }
    fn mean_irrigation(&self) -> SeedMean {
        SeedMean::of(&self.irrigation_mm)
    }
    fn mean_dry(&self) -> SeedMean {
        SeedMean::of(&self.dry)
    }
}

/// The table cells of one controller against the oracle: I_T ± its
/// standard error, Δ of the means [%], the paired seed-by-seed Δ's
/// standard error, the seeds within 5 %, the dry-side violation and its Δ.
fn cells(s: &Scores, oracle: &Scores) -> String {
    let (i, o) = (s.mean_irrigation(), oracle.mean_irrigation());
    let paired: Vec<f64> = s
        .irrigation_mm
        .iter()
        .zip(&oracle.irrigation_mm)
        .map(|(a, b)| percent(*a, *b))
        .collect();
    let within = paired.iter().filter(|d| d.abs() <= 5.0).count();
    let dry = s.mean_dry().mean;
    format!(
        "{:.2} ± {:.2} | {:+.1} ± {:.1} | {within}/{} | {dry:.2e} | {:+.1e}",
        i.mean,
        i.standard_error,
        percent(i.mean, o.mean),
        SeedMean::of(&paired).standard_error,
        paired.len(),
        dry - oracle.mean_dry().mean,
    )
}

/// The weather experiment over `--seeds` seeds: `et0.md` (means), `et0.csv`
/// (means) and `et0-seasons.csv` (every run).
pub fn et0(options: &ExperimentOptions) -> Result<Vec<PathBuf>, ExperimentError> {
    let models = Models::load(options)?;
    let last = options.seed.wrapping_add(options.seeds - 1);
    let mut names = Vec::new();
    // per season: oracle, two-layer, told 4 mm/day
    let mut scores: Vec<[Scores; 3]> = Vec::new();
    let mut seasons = String::from(
        "season,controller,seed,irrigation_mm,dry_violation,wet_violation_after_entry,zone_violation,solve_median_ms,fallbacks\n",
    );
    for k in 0..options.seeds {
        let seed = options.seed.wrapping_add(k);
        for (i, r) in season_results(&models, seed)?.into_iter().enumerate() {
            if k == 0 {
                names.push(r.name.clone());
                scores.push([Scores::new(), Scores::new(), Scores::new()]);
            }
            for (j, (name, run)) in [
                ("oracle", &r.oracle),
                ("two-layer", &r.two_layer),
                ("two-layer told 4 mm/day", &r.held),
            ]
            .into_iter()
            .enumerate()
            {
                scores[i][j].push(run);
                let _ = writeln!(
                    seasons,
                    "{},{name},{seed},{},{},{},{},{},{}",
                    r.name,
                    run.total_irrigation_mm(),
                    run.dry_violation(),
                    run.wet_violation_after_entry(),
                    run.zone_violation(),
                    run.solve_times().median_ms,
                    run.fallbacks()
                );
            }
        }
    }
    let mut md = format!(
        "# The weather: ET0 and rain\n\n\
         The two-layer ZMPC fed the forecast ET0, and the same network told a constant \
         4 mm/day (the dry scenario's ET0, blind to the season), against the oracle (the \
         Richards ZMPC on the plant's true soil and state). Both two-layer runs see the \
         sensor through the reading filter (the ensemble filter around the networks' soil \
         takes the reading's place in the window and the f = 2 bias). Soil {}, 2 % process and 2 % \
         measurement noise, 20 % forecast error, time-invariant zone [0.18, 0.23], 60 steps \
         of 2 h. The seasons keep weather-dry's diurnal shape with each day's ET0 scaled. \
         Every figure is the mean over the {} seeds {} … {last} (each controller sees the \
         same noise and forecast errors) ± its standard error; \"Δ [%]\" compares the means, \
         its ± is the standard error of the seed-by-seed Δ, and \"≤ 5 %\" counts the seeds \
         whose own Δ is within 5 %. Dry-side violation: mean of max(0, 0.18 − θ_true) \
         [m³/m³]. Targets (issue 17): I_T within 5 % of the oracle's, dry-side violation at \
         most 1e-4 above the oracle's. Every run: `et0-seasons.csv`.\n\n\
         | season | oracle I_T [mm] | oracle dry viol. | two-layer I_T [mm] | Δ [%] | ≤ 5 % | dry viol. | Δ dry viol. | told 4 mm/day: I_T [mm] | Δ [%] | ≤ 5 % | dry viol. | Δ dry viol. | targets |\n\
         |---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|\n",
        models.two_layer.metadata.soil, options.seeds, options.seed
    );
    let mut csv = String::from(
        "season,controller,seeds,irrigation_mm,irrigation_mm_se,dry_violation,dry_violation_se\n",
    );
    for (name, [o, t, h]) in names.iter().zip(&scores) {
        let (oi, ti) = (o.mean_irrigation().mean, t.mean_irrigation().mean);
        let met = percent(ti, oi).abs() <= 5.0 && t.mean_dry().mean - o.mean_dry().mean <= 1e-4;
        let _ = writeln!(
            md,
            "| {name} | {:.2} ± {:.2} | {:.2e} | {} | {} | {} |",
            oi,
            o.mean_irrigation().standard_error,
            o.mean_dry().mean,
            cells(t, o),
            cells(h, o),
            if met { "met" } else { "missed" }
        );
        for (controller, s) in [
            ("oracle", o),
            ("two-layer", t),
            ("two-layer told 4 mm/day", h),
        ] {
            let (i, d) = (s.mean_irrigation(), s.mean_dry());
            let _ = writeln!(
                csv,
                "{name},{controller},{},{},{},{},{}",
                options.seeds, i.mean, i.standard_error, d.mean, d.standard_error
            );
        }
    }
    Ok(vec![
        write_file(&options.out.join("et0.md"), &md)?,
        write_file(&options.out.join("et0.csv"), &csv)?,
        write_file(&options.out.join("et0-seasons.csv"), &seasons)?,
    ])
}
