//! `rootzone simulate`: the soil column driven by a weather file and an
//! irrigation schedule, written out as CSV, one row per step.

use std::io::Write;
use std::path::{Path, PathBuf};

use crate::soil::{Field, FieldSettings, IntegrationError, VanGenuchten};
use crate::weather::{InputError, WeatherSeries, read_table};

/// What to simulate.
#[derive(Debug, Clone)]
pub struct SimulateOptions {
    /// Weather CSV (`step,start_hour,et0_mm,precip_mm`).
    pub weather: PathBuf,
    /// Irrigation CSV (`step,irrigation_m_per_s`).
    pub irrigation: PathBuf,
    /// Steps to simulate; default: every row of the irrigation file.
    pub steps: Option<usize>,
    /// Soil (a texture's parameters or any valid set).
    pub soil: VanGenuchten,
    /// Process noise level (fraction).
    pub process_noise: f64,
    /// Measurement noise level (fraction).
    pub measurement_noise: f64,
    /// Seed of the noise generators.
    pub seed: u64,
    /// Output CSV; standard output when absent.
    pub out: Option<PathBuf>,
}

/// Why a simulation could not be run or written.
#[derive(Debug, thiserror::Error)]
pub enum SimulateError {
    #[error(transparent)]
    Input(#[from] InputError),
    #[error("invalid settings: {0}")]
    Settings(String),
    #[error("simulation failed at step {step}: {source}")]
    Integration {
        step: usize,
        source: IntegrationError,
    },
    #[error("cannot write {path}: {source}")]
    Output {
        path: String,
        source: std::io::Error,
    },
}

/// An irrigation schedule: one rate per step, in m/s.
pub fn read_irrigation(path: &Path) -> Result<Vec<f64>, InputError> {
    let origin = path.display().to_string();
    let text = std::fs::read_to_string(path).map_err(|e| InputError {
        path: origin.clone(),
        line: 0,
        message: format!("cannot read: {e}"),
    })?;
    parse_irrigation(&text, &origin)
}

/// The largest rate of an irrigation file [m/s]: the largest irrigation
/// rate a field of the daemon may be given (`irrigation_max`, 360 mm/h).
pub const MAX_IRRIGATION: f64 = 1e-4;

/// Parses irrigation CSV text; `origin` names the source in errors: steps
/// 0, 1, 2, … in order, rates in [0, [`MAX_IRRIGATION`]] m/s.
pub fn parse_irrigation(text: &str, origin: &str) -> Result<Vec<f64>, InputError> {
    let rows = read_table(text, origin, &["step", "irrigation_m_per_s"])?;
    let mut rates = Vec::with_capacity(rows.len());
    for row in rows {
        let err = |message: String| InputError {
            path: origin.to_string(),
            line: row.line,
            message,
        };
        let (step, rate) = (row.values[0], row.values[1]);
        if step != rates.len() as f64 {
            return Err(err(format!(
                "step {} out of order: expected {}",
                row.raw[0],
                rates.len()
            )));
        }
        if rate < 0.0 {
            return Err(err(format!(
                "irrigation_m_per_s = {} is negative",
                row.raw[1]
            )));
        }
        if rate > MAX_IRRIGATION {
            return Err(err(format!(
                "irrigation_m_per_s = {} exceeds {MAX_IRRIGATION} m/s (360 mm/h, the largest \
                 irrigation rate a field may be given)",
                row.raw[1]
            )));
        }
        rates.push(rate);
    }
    if rates.is_empty() {
        return Err(InputError {
            path: origin.to_string(),
            line: 1,
            message: "no irrigation steps".into(),
        });
    }
    Ok(rates)
}

/// One output row.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SimulatedStep {
    pub step: usize,
    /// Hours since the start at the end of the step (when θ is read).
    pub hour: f64,
    pub irrigation_m_per_s: f64,
    pub et0_mm: f64,
    pub precip_mm: f64,
    pub theta: f64,
    pub theta_measured: f64,
    pub storage_mm: f64,
    pub infiltration_mm: f64,
    pub runoff_mm: f64,
    pub drainage_mm: f64,
    pub uptake_mm: f64,
}

/// Runs the simulation in memory; nothing is written.
pub fn simulate(
    options: &SimulateOptions,
    weather: &WeatherSeries,
    irrigation: &[f64],
) -> Result<Vec<SimulatedStep>, SimulateError> {
    let steps = options.steps.unwrap_or(irrigation.len());
    if steps > irrigation.len() {
        return Err(InputError {
            path: options.irrigation.display().to_string(),
            line: irrigation.len() as u64 + 2,
            message: format!(
                "no step {}: the file holds {} steps, {steps} requested",
                irrigation.len(),
                irrigation.len()
            ),
        }
        .into());
    }
    if steps > weather.len() {
        return Err(InputError {
            path: options.weather.display().to_string(),
            line: weather.len() as u64 + 2,
            message: format!(
                "no step {}: the file holds {} steps, {steps} requested",
                weather.len(),
                weather.len()
            ),
        }
        .into());
    }
    let settings = FieldSettings {
        soil: options.soil,
        process_noise: options.process_noise,
        measurement_noise: options.measurement_noise,
        seed: options.seed,
        ..FieldSettings::default()
    };
    let dt = settings.sampling_time;
    let mut field = Field::new(settings).map_err(SimulateError::Settings)?;
    let mut rows = Vec::with_capacity(steps);
    for (step, (&rate, w)) in irrigation
        .iter()
        .zip(weather.steps())
        .take(steps)
        .enumerate()
    {
        let report = field
            .step(w.forcing(rate, dt))
            .map_err(|source| SimulateError::Integration { step, source })?;
        let balance = field.water_balance();
        rows.push(SimulatedStep {
            step,
            hour: report.time / 3600.0,
            irrigation_m_per_s: rate,
            et0_mm: w.et0_mm,
            precip_mm: w.precip_mm,
            theta: report.water_content,
            theta_measured: report.measured_water_content,
            storage_mm: balance.storage * 1e3,
            infiltration_mm: balance.infiltration * 1e3,
            runoff_mm: balance.runoff * 1e3,
            drainage_mm: balance.drainage * 1e3,
            uptake_mm: balance.uptake * 1e3,
        });
    }

    Ok(rows)
}

/// Writes the rows as CSV.
pub fn write_csv(rows: &[SimulatedStep], out: &mut impl Write) -> std::io::Result<()> {
    writeln!(
        out,
        "step,hour,irrigation_m_per_s,et0_mm,precip_mm,theta,theta_measured,\
         storage_mm,infiltration_mm,runoff_mm,drainage_mm,uptake_mm"
    )?;
    for r in rows {
        writeln!(
            out,
            "{},{},{:e},{},{},{:.8},{:.8},{:.6},{:.6},{:.6},{:.6},{:.6}",
            r.step,
            r.hour,
            r.irrigation_m_per_s,
            r.et0_mm,
            r.precip_mm,
            r.theta,
            r.theta_measured,
            r.storage_mm,
            r.infiltration_mm,
            r.runoff_mm,
            r.drainage_mm,
            r.uptake_mm
        )?;
    }
    Ok(())
}

/// The whole command: read, validate, simulate, then write atomically (a temporary
/// file renamed into place), so a failure leaves no partial output file. An
/// output path that exists and is not a regular file (`/dev/null`, a named
/// pipe, `/dev/stdout`) is written in place: a rename would replace it.
pub fn run(options: &SimulateOptions) -> Result<(), SimulateError> {
    let weather = WeatherSeries::from_file(&options.weather)?;
    let irrigation = read_irrigation(&options.irrigation)?;
    let rows = simulate(options, &weather, &irrigation)?;
    match &options.out {
        None => {
            let stdout = std::io::stdout();
            write_csv(&rows, &mut stdout.lock()).map_err(|source| SimulateError::Output {
                path: "<stdout>".into(),
                source,
            })
        }
        Some(path) => {
            let output = |source| SimulateError::Output {
                path: path.display().to_string(),
                source,
            };
            let write_into = |file: &mut std::fs::File| {
                let mut out = std::io::BufWriter::new(file);
                write_csv(&rows, &mut out)?;
                out.flush()
            };
            if std::fs::metadata(path).is_ok_and(|m| !m.is_file()) {
                let mut file = std::fs::OpenOptions::new()
                    .write(true)
                    .open(path)
                    .map_err(output)?;
                return write_into(&mut file).map_err(output);
            }
            let dir = path
                .parent()
                .filter(|p| !p.as_os_str().is_empty())
                .unwrap_or(Path::new("."));
            let mut tmp = tempfile::NamedTempFile::new_in(dir).map_err(output)?;
            write_into(tmp.as_file_mut()).map_err(output)?;
            tmp.persist(path).map_err(|e| output(e.error))?;
            Ok(())
        }
    }
}
