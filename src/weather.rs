//! Weather series: scenario files, unit conversion, and forecast error (MODEL.md §2).

use std::path::Path;

use rand::{Rng, RngExt};

use crate::soil::Forcing;

/// Largest ET0 rate [mm/h] of a forecast or a weather file (the highest
/// hourly reference evapotranspiration observed is about 1.5 mm/h).
pub const MAX_ET0_MM_PER_H: f64 = 2.0;
/// Largest precipitation rate [mm/h] of a forecast or a weather file (the
/// world record for one hour is about 305 mm).
pub const MAX_PRECIP_MM_PER_H: f64 = 400.0;
/// The step of a weather file [h]: its amounts are per 2-h step, the
/// sampling time of MODEL.md.
pub const FILE_STEP_HOURS: f64 = 2.0;

/// Weather of one sampling step, amounts over the step in mm.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WeatherStep {
    /// Hour of day (or since the start) at which the step begins.
    pub start_hour: f64,
    /// Reference evapotranspiration over the step [mm].
    pub et0_mm: f64,
    /// Precipitation over the step [mm].
    pub precip_mm: f64,
}

impl WeatherStep {
    /// The step's rates in m/s together with an irrigation rate.
    pub fn forcing(&self, irrigation: f64, step_seconds: f64) -> Forcing {
        Forcing {
            irrigation,
            reference_et: mm_to_rate(self.et0_mm, step_seconds),
            precipitation: mm_to_rate(self.precip_mm, step_seconds),
        }
    }
}

/// mm over a step of `seconds` → m/s.
pub fn mm_to_rate(mm: f64, seconds: f64) -> f64 {
    mm * 1e-3 / seconds
}

/// m/s over a step of `seconds` → mm.
pub fn rate_to_mm(rate: f64, seconds: f64) -> f64 {
    rate * seconds * 1e3
}

/// An input file could not be used. Names the file, the line (1-based, the header
/// is line 1; 0 when the file as a whole is at fault) and what was wrong.
#[derive(Debug, Clone, PartialEq)]
pub struct InputError {
    pub path: String,
    pub line: u64,
    pub message: String,
}

impl std::fmt::Display for InputError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.line {
            0 => write!(f, "{}: {}", self.path, self.message),
            line => write!(f, "{}:{line}: {}", self.path, self.message),
        }
    }
}

impl std::error::Error for InputError {}

/// A weather scenario: one entry per sampling step, step 0 first.
#[derive(Debug, Clone, PartialEq)]
pub struct WeatherSeries {
    steps: Vec<WeatherStep>,
}

/// The scenarios shipped with rootzone (the files under `data/`), embedded.
pub const DRY_SCENARIO: &str = include_str!("../data/weather-dry.csv");
pub const RAIN_SCENARIO: &str = include_str!("../data/weather-rain.csv");

impl WeatherSeries {
    pub fn new(steps: Vec<WeatherStep>) -> Self {
        WeatherSeries { steps }
    }

    /// Reads a weather CSV with columns `step,start_hour,et0_mm,precip_mm`:
    /// steps 0, 1, 2, … in order, amounts in mm per 2-h step, each in
    /// [0, 4] (ET0, [`MAX_ET0_MM_PER_H`]) or [0, 800] (precipitation,
    /// [`MAX_PRECIP_MM_PER_H`]), the same rates the API takes.
    pub fn from_file(path: &Path) -> Result<Self, InputError> {
        let text = std::fs::read_to_string(path).map_err(|e| InputError {
            path: path.display().to_string(),
            line: 0,
            message: format!("cannot read: {e}"),
        })?;
        Self::parse(&text, &path.display().to_string())
    }

    /// Parses weather CSV text; `origin` names the source in errors.
    pub fn parse(text: &str, origin: &str) -> Result<Self, InputError> {
        let rows = read_table(text, origin, &["step", "start_hour", "et0_mm", "precip_mm"])?;
        let mut steps = Vec::with_capacity(rows.len());
        for row in rows {
            let err = |message: String| InputError {
                path: origin.to_string(),
                line: row.line,
                message,
            };
            let [step, start_hour, et0_mm, precip_mm] = [0, 1, 2, 3].map(|i| row.values[i]);
            if step != steps.len() as f64 {
                return Err(err(format!(
                    "step {} out of order: expected {}",
                    row.raw[0],
                    steps.len()
                )));
            }
            for (k, name, rate) in [
                (2, "et0_mm", MAX_ET0_MM_PER_H),
                (3, "precip_mm", MAX_PRECIP_MM_PER_H),
            ] {
                if row.values[k] < 0.0 {
                    return Err(err(format!("{name} = {} is negative", row.raw[k])));
                }
                let most = rate * FILE_STEP_HOURS;
                if row.values[k] > most {
                    return Err(err(format!(
                        "{name} = {} exceeds {most} mm ({rate} mm/h over a {FILE_STEP_HOURS}-h step)",
                        row.raw[k]
                    )));
                }
            }
            steps.push(WeatherStep {
                start_hour,
                et0_mm,
                precip_mm,
            });
        }
        if steps.is_empty() {
            return Err(InputError {
                path: origin.to_string(),
                line: 1,
                message: "no weather steps".into(),
            });
        }
        Ok(WeatherSeries { steps })
    }

    pub fn len(&self) -> usize {
        self.steps.len()
    }

    pub fn is_empty(&self) -> bool {
        self.steps.is_empty()
    }

    pub fn steps(&self) -> &[WeatherStep] {
        &self.steps
    }

    pub fn get(&self, step: usize) -> Option<&WeatherStep> {
        self.steps.get(step)
    }

    /// A forecast of `len` steps from `start`: every step's ET0 and P times
    /// `(1 + e_k)`, `e_k ~ U(−error, error)` (MODEL.md §2). Steps past the end of
    /// the series repeat its last step.
    pub fn forecast(
        &self,
        start: usize,
        len: usize,
        error: f64,
        rng: &mut impl Rng,
    ) -> Vec<WeatherStep> {
        let last = self.steps.len() - 1;
        (start..start + len)
            .map(|k| {
                let truth = self.steps[k.min(last)];
                let mut draw = || 1.0 + error * (2.0 * rng.random::<f64>() - 1.0);
                WeatherStep {
                    et0_mm: truth.et0_mm * draw(),
                    precip_mm: truth.precip_mm * draw(),
                    ..truth
                }
            })
            .collect()
    }
}

/// One data row of a numeric CSV table.
pub(crate) struct Row {
    /// 1-based line number in the file (header = 1).
    pub line: u64,
    pub values: Vec<f64>,
    /// The values as written, for messages.
    pub raw: Vec<String>,
}

/// Reads a CSV whose header must start with `columns`; every listed value must be a finite
/// number. Extra columns are ignored.
pub(crate) fn read_table(
    text: &str,
    origin: &str,
    columns: &[&str],
) -> Result<Vec<Row>, InputError> {
    let mut reader = csv::ReaderBuilder::new()
        .trim(csv::Trim::All)
        .comment(Some(b'#'))
        .from_reader(text.as_bytes());
    let err = |line: u64, message: String| InputError {
        path: origin.to_string(),
        line,
        message,
    };
    let header = reader
        .headers()
        .map_err(|e| err(1, format!("unreadable header: {e}")))?
        .clone();
    let mut index = Vec::with_capacity(columns.len());
    for c in columns {
        let i = header.iter().position(|h| h == *c).ok_or_else(|| {
            err(
                1,
                format!(
                    "missing column '{c}' (header: {})",
                    header.iter().collect::<Vec<_>>().join(",")
                ),
            )
        })?;
        index.push(i);
    }
    let mut rows = Vec::new();
    for record in reader.records() {
        let record = record.map_err(|e| {
            let line = e.position().map_or(0, |p| p.line());
            err(line, format!("malformed row: {e}"))
        })?;
        let line = record.position().map_or(0, |p| p.line());
        let mut values = Vec::with_capacity(columns.len());
        let mut raws = Vec::with_capacity(columns.len());
        for (c, &i) in columns.iter().zip(&index) {
            let raw = record
                .get(i)
                .ok_or_else(|| err(line, format!("missing value for '{c}'")))?;
            let v: f64 = raw
                .parse()
                .map_err(|_| err(line, format!("{c} = '{raw}' is not a number")))?;
            if !v.is_finite() {
                return Err(err(line, format!("{c} = {raw} is not finite")));
            }
            values.push(v);
            raws.push(raw.to_string());
        }
        rows.push(Row {
            line,
            values,
            raw: raws,
        });
    }
    Ok(rows)
}
