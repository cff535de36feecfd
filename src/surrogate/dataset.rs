//! Training and validation data for the surrogates: pseudo-random irrigation
//! signals fed to the soil-column simulator (MODEL.md §3).
//!
//! Two kinds of excitation:
//!
//! * **multi-level** (sub-models M1–M3): the signal holds a level for a random
//!   number of steps; each level aims at a random water content inside the
//!   operating range (the steady flux K(h(θ*)) that holds θ*, times a random
//!   factor so that the dynamics are excited), and a guard switches irrigation
//!   off above the range and to the top level below it, so the output stays
//!   inside the range;
//! * **impulse** (M_A and the single LSTM, the whole range): dry spells of random
//!   length broken by short irrigation pulses of random size, with the same guard.
//!
//! The weather is drawn too, so that the networks learn what ET0 and rain do:
//! every day's ET0 total is drawn from Uniform(0.5, 8) mm/day and spread over
//! the day with the diurnal shape of the given weather (`weather-dry`); a
//! step starts a rain event with probability 1/48 (about one every four
//! days), of Uniform(1, 20) mm over one or two steps, when the output is in
//! the lower half of the set's range (so that the rain does not carry it out
//! of the range). The networks' input is the supply, irrigation plus rain
//! ([`Series::supply`]), beside ET0. The output noise of MODEL.md §2
//! (uniform, ±fraction × the output range of the set) is added afterwards;
//! the noise-free output is kept for scoring.

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::soil::{Field, FieldSettings, Forcing, IntegrationError};
use crate::weather::WeatherStep;

/// How the irrigation signal is drawn.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Excitation {
    /// Multi-level holds inside the water-content range [low, high].
    MultiLevel { low: f64, high: f64 },
    /// Dry spells and pulses over the water-content range [low, high].
    Impulse { low: f64, high: f64 },
}

impl Excitation {
    /// The water-content range the signal keeps the output in.
    pub fn range(&self) -> (f64, f64) {
        match *self {
            Excitation::MultiLevel { low, high } | Excitation::Impulse { low, high } => (low, high),
        }
    }
}

/// One data set to generate.
#[derive(Debug, Clone, PartialEq)]
pub struct DatasetSpec {
    /// Name used in file names and reports (`m1-train`, …).
    pub name: String,
    pub excitation: Excitation,
    /// Samples recorded (after the warm-up).
    pub samples: usize,
    /// Output noise as a fraction of the set's output range (0.1 training, 0.2 validation).
    pub noise_fraction: f64,
    /// Seed of the signal and of the noise.
    pub seed: u64,
}

/// A generated series: the inputs over each step and the output after it.
#[derive(Debug, Clone, PartialEq)]
pub struct Series {
    /// Irrigation rate applied over step k [m/s].
    pub irrigation: Vec<f64>,
    /// Precipitation rate over step k [m/s].
    pub rain: Vec<f64>,
    /// Reference evapotranspiration rate over step k [m/s].
    pub et0: Vec<f64>,
    /// Noise-free water content after step k.
    pub water_content: Vec<f64>,
    /// The same with the output noise added.
    pub measured: Vec<f64>,
}

impl Series {
    /// The water supplied at the surface over each step, irrigation plus
    /// rain [m/s]: the surrogates' input.
    pub fn supply(&self) -> Vec<f64> {
        self.irrigation
            .iter()
            .zip(&self.rain)
            .map(|(u, p)| u + p)
            .collect()
    }

    pub fn len(&self) -> usize {
        self.irrigation.len()
    }

    pub fn is_empty(&self) -> bool {
        self.irrigation.is_empty()
    }

    /// Fraction of noise-free samples inside [low, high], and the fraction of
    /// the range's 20 equal bins that hold at least one of them.
    pub fn coverage(&self, low: f64, high: f64) -> (f64, f64) {
        const BINS: usize = 20;
        let mut occupied = [false; BINS];
        let mut inside = 0usize;
        for &y in &self.water_content {
            if (low..=high).contains(&y) {
                inside += 1;
                let bin = (((y - low) / (high - low)) * BINS as f64) as usize;
                occupied[bin.min(BINS - 1)] = true;
            }
        }
        let bins = occupied.iter().filter(|&&b| b).count();
        (
            inside as f64 / self.len().max(1) as f64,
            bins as f64 / BINS as f64,
        )
    }
}

/// Steps simulated before recording starts, from the initial state of MODEL.md.
const WARM_UP: usize = 24;
/// Largest irrigation rate the signals use [m/s] (u_max of MODEL.md §4).
const MAX_RATE: f64 = 1e-5;
/// Range of the daily ET0 totals drawn [mm/day].
pub const ET0_RANGE_MM_DAY: (f64, f64) = (0.5, 8.0);
/// Chance that a step starts a rain event.
const RAIN_CHANCE: f64 = 1.0 / 48.0;
/// Range of a rain event's total [mm].
const RAIN_RANGE_MM: (f64, f64) = (1.0, 20.0);

/// The diurnal shape of `weather`'s ET0: each step's share of its day
/// times the steps per day (mean 1), the day being `steps_per_day` steps;
/// flat when the weather has no ET0.
fn diurnal_shape(weather: &[WeatherStep], steps_per_day: usize) -> Vec<f64> {
    let day: Vec<f64> = (0..steps_per_day)
        .map(|j| weather.get(j).map_or(0.0, |w| w.et0_mm.max(0.0)))
        .collect();
    let total: f64 = day.iter().sum();
    if total > 0.0 && total.is_finite() {
        day.iter()
            .map(|e| e * steps_per_day as f64 / total)
            .collect()
    } else {
        vec![1.0; steps_per_day]
    }
}

/// Generates a series with the simulator of `settings` (its noise settings are
/// ignored: the series carries output noise only, as MODEL.md §3 asks).
pub fn generate(
    spec: &DatasetSpec,
    settings: &FieldSettings,
    weather: &[WeatherStep],
) -> Result<Series, IntegrationError> {
    let settings = FieldSettings {
        process_noise: 0.0,
        measurement_noise: 0.0,
        ..*settings
    };
    let mut field =
        Field::new(settings).map_err(|message| IntegrationError::invalid(0.0, message))?;
    let soil = settings.soil;
    let dt = settings.sampling_time;
    let mut rng = ChaCha8Rng::seed_from_u64(spec.seed);
    let (low, high) = spec.excitation.range();
    let margin = 0.03 * (high - low);
    // The steady flux that holds water content θ: K at the head where θ(h) = θ.
    let steady_rate = |theta: f64| soil.conductivity(soil.pressure_head_at(theta));

    let total = WARM_UP + spec.samples;
    let mut series = Series {
        irrigation: Vec::with_capacity(spec.samples),
        rain: Vec::with_capacity(spec.samples),
        et0: Vec::with_capacity(spec.samples),
        water_content: Vec::with_capacity(spec.samples),
        measured: Vec::with_capacity(spec.samples),
    };
    // the weather has a stream of its own, so the signal stays the same
    // draw for draw whatever the weather does
    let mut sky = ChaCha8Rng::seed_from_u64(spec.seed ^ 0x5eed_e7a0_0000_0001);
    let steps_per_day = ((86_400.0 / dt).round() as usize).max(1);
    let shape = diurnal_shape(weather, steps_per_day);
    let mut day_rate = 0.0;
    let mut raining = (0usize, 0.0);
    let mut theta = field.water_content();
    let mut level = 0.0;
    let mut hold = 0usize;
    for k in 0..total {
        if k % steps_per_day == 0 {
            let (lo, hi) = ET0_RANGE_MM_DAY;
            day_rate = sky.random_range(lo..hi) * 1e-3 / 86_400.0;
        }
        let et0 = day_rate * shape[k % steps_per_day];
        if raining.0 == 0 && sky.random::<f64>() < RAIN_CHANCE && theta < 0.5 * (low + high) {
            let steps = sky.random_range(1..=2usize);
            let mm = sky.random_range(RAIN_RANGE_MM.0..RAIN_RANGE_MM.1);
            raining = (steps, mm * 1e-3 / (steps as f64 * dt));
        }
        let rain = if raining.0 > 0 {
            raining.0 -= 1;
            raining.1
        } else {
            0.0
        };
        if hold == 0 {
            (level, hold) = match spec.excitation {
                Excitation::MultiLevel { .. } => {
                    let target = rng.random_range(low..high);
                    let factor = 10f64.powf(rng.random_range(-0.7..0.7));
                    let steps = rng.random_range(1..=18);
                    // never more than what holds the top of the range
                    let cap = steady_rate(high).min(MAX_RATE);
                    ((steady_rate(target) * factor).min(cap), steps)
                }
                Excitation::Impulse { .. } => {
                    if level > 0.0 {
                        // a dry spell after every pulse
                        (0.0, rng.random_range(2..=30))
                    } else {
                        let size = 10f64.powf(rng.random_range(-6.3..-5.0));
                        (size.min(MAX_RATE), rng.random_range(1..=3))
                    }
                }
            };
        }
        // Guard: keep the output inside the range.
        let rate = if theta > high - margin {
            0.0
        } else if theta < low + margin {
            match spec.excitation {
                Excitation::MultiLevel { .. } => steady_rate(high).min(MAX_RATE),
                Excitation::Impulse { .. } => MAX_RATE,
            }
        } else {
            level
        };
        hold -= 1;
        let forcing = Forcing {
            irrigation: rate,
            reference_et: et0,
            precipitation: rain,
        };
        theta = field.step(forcing)?.water_content;
        if k >= WARM_UP {
            series.irrigation.push(rate);
            series.rain.push(rain);
            series.et0.push(et0);
            series.water_content.push(theta);
        }
    }
    let (min, max) = series
        .water_content
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &y| {
            (a.min(y), b.max(y))
        });
    let amplitude = spec.noise_fraction * (max - min);
    series.measured = series
        .water_content
        .iter()
        .map(|&y| y + amplitude * (2.0 * rng.random::<f64>() - 1.0))
        .collect();
    Ok(series)
}

/// A cached data set could not be read or written.
#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    #[error("cannot {action} {path}: {source}")]
    Io {
        action: &'static str,
        path: String,
        source: std::io::Error,
    },
    #[error("{path}:{line}: {message}")]
    Malformed {
        path: String,
        line: usize,
        message: String,
    },
    #[error(transparent)]
    Simulation(#[from] IntegrationError),
}

/// Version of the generator: part of the cache key, bumped when the signals change.
const GENERATOR_VERSION: u32 = 2;

impl DatasetSpec {
    /// File name of the cached series: every setting that changes the data is in it.
    pub fn cache_name(&self, soil: &str, settings: &FieldSettings) -> String {
        let (low, high) = self.excitation.range();
        let kind = match self.excitation {
            Excitation::MultiLevel { .. } => "levels",
            Excitation::Impulse { .. } => "impulse",
        };
        format!(
            "{}-{soil}-{kind}-{low}-{high}-n{}-noise{}-seed{}-dt{}-g{GENERATOR_VERSION}.csv",
            self.name, self.samples, self.noise_fraction, self.seed, settings.sampling_time
        )
    }
}

/// Loads the series from `cache_dir` if it was generated before with the same
/// settings, otherwise generates and stores it (written to a temporary file and
/// renamed, so a crash never leaves a truncated cache entry).
pub fn load_or_generate(
    spec: &DatasetSpec,
    soil_name: &str,
    settings: &FieldSettings,
    weather: &[WeatherStep],
    cache_dir: &std::path::Path,
) -> Result<Series, DatasetError> {
    let path = cache_dir.join(spec.cache_name(soil_name, settings));
    if path.exists() {
        return read_series(&path);
    }
    let series = generate(spec, settings, weather)?;
    let io = |action, source| DatasetError::Io {
        action,
        path: path.display().to_string(),
        source,
    };
    std::fs::create_dir_all(cache_dir).map_err(|e| io("create the folder of", e))?;
    let mut text =
        String::from("irrigation_m_per_s,rain_m_per_s,et0_m_per_s,theta,theta_measured\n");
    for k in 0..series.len() {
        text.push_str(&format!(
            "{:e},{:e},{:e},{:e},{:e}\n",
            series.irrigation[k],
            series.rain[k],
            series.et0[k],
            series.water_content[k],
            series.measured[k]
        ));
    }
    let tmp = path.with_extension("csv.tmp");
    std::fs::write(&tmp, text).map_err(|e| io("write", e))?;
    std::fs::rename(&tmp, &path).map_err(|e| io("write", e))?;
    Ok(series)
}

/// Reads a series written by [`load_or_generate`].
pub fn read_series(path: &std::path::Path) -> Result<Series, DatasetError> {
    let shown = path.display().to_string();
    let text = std::fs::read_to_string(path).map_err(|source| DatasetError::Io {
        action: "read",
        path: shown.clone(),
        source,
    })?;
    let mut series = Series {
        irrigation: vec![],
        rain: vec![],
        et0: vec![],
        water_content: vec![],
        measured: vec![],
    };
    for (index, line) in text.lines().enumerate().skip(1) {
        let values: Result<Vec<f64>, _> = line.split(',').map(str::parse::<f64>).collect();
        match values
            .ok()
            .filter(|v| v.len() == 5 && v.iter().all(|x| x.is_finite()))
        {
            Some(v) => {
                series.irrigation.push(v[0]);
                series.rain.push(v[1]);
                series.et0.push(v[2]);
                series.water_content.push(v[3]);
                series.measured.push(v[4]);
            }
            None => {
                return Err(DatasetError::Malformed {
                    path: shown,
                    line: index + 1,
                    message: format!("expected five finite numbers, got '{line}'"),
                });
            }
        }
    }
    Ok(series)
}
