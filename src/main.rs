//! The `rootzone` command line: parses arguments and calls one library function per command.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};
use rootzone::experiment::{ExperimentId, ExperimentOptions, run_experiment};
use rootzone::simulate::{SimulateOptions, run as run_simulation};
use rootzone::soil::Texture;
use rootzone::surrogate::pipeline::{ProgressEvent, TrainPlan, run_training};

#[derive(Parser)]
#[command(
    name = "rootzone",
    version,
    about = "Closed-loop irrigation by zone MPC"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Simulate the soil column under a weather file and an irrigation schedule; CSV out.
    Simulate {
        /// Weather CSV: step,start_hour,et0_mm,precip_mm (amounts per 2-h step).
        #[arg(long)]
        weather: PathBuf,
        /// Irrigation CSV: step,irrigation_m_per_s.
        #[arg(long)]
        irrigation: PathBuf,
        /// Number of steps (default: every row of the irrigation file).
        #[arg(long)]
        steps: Option<usize>,
        /// Soil: a texture (Carsel & Parrish 1988), e.g. sandy-loam, loam,
        /// clay, or `ks=…,alpha=…,n=…,theta_r=…,theta_s=…` (SI, α in 1/m).
        #[arg(long, default_value = "sandy-loam")]
        soil: String,
        /// Process noise level, e.g. 0.02 for 2 %.
        #[arg(long, default_value_t = 0.0)]
        process_noise: f64,
        /// Measurement noise level, e.g. 0.05 for 5 %.
        #[arg(long, default_value_t = 0.0)]
        measurement_noise: f64,
        /// Seed of the noise generators.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Output CSV file (default: standard output).
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// Generate (or load cached) data and train the five surrogate networks.
    Train {
        /// Soil texture the models are trained for.
        #[arg(long, default_value = "sandy-loam", conflicts_with = "soil_params")]
        soil: String,
        /// A soil given by its parameters instead of a texture:
        /// `ks=…,alpha=…,n=…,theta_r=…,theta_s=…` (SI, α in 1/m). The data
        /// sets' water-content ranges are sandy loam's carried to it by
        /// effective saturation.
        #[arg(long, value_name = "PARAMS")]
        soil_params: Option<String>,
        /// Folder for the model files and the training report.
        #[arg(long, default_value = "models")]
        out: PathBuf,
        /// Seed of the data, the initial weights and the shuffling.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Tiny networks on small data (under a minute): for tests and smoke runs.
        #[arg(long)]
        quick: bool,
        /// Folder of the generated-data cache.
        #[arg(long, default_value = "data/cache")]
        cache: PathBuf,
        /// Bring the training input windows up to the noise of Uniform(±LEVEL
        /// of the whole range); the targets stay as measured. Default: the
        /// plan's level, 0.2 (the validation data's noise); 0 leaves the
        /// windows as measured (see ARCHITECTURE.md).
        #[arg(long, value_name = "LEVEL", value_parser = parse_window_noise)]
        window_noise: Option<f64>,
    },
    /// Reproduce one of the paper's experiments (tables as Markdown and CSV, figures as SVG).
    Experiment {
        /// e1 … e8, et0 (the weather: ET0 seasons and rain), or all (every
        /// one and one report).
        id: String,
        /// Folder of the trained model files.
        #[arg(long, default_value = "models")]
        models: PathBuf,
        /// Folder for the tables and figures.
        #[arg(long, default_value = "reports")]
        out: PathBuf,
        /// Seed of the fresh validation data (E1–E3) and of the field's
        /// noise and the forecast error (E4–E7).
        #[arg(long, default_value_t = 7)]
        seed: u64,
        /// Folder of the generated-data cache.
        #[arg(long, default_value = "data/cache")]
        cache: PathBuf,
        /// Validation samples per set (smaller for smoke runs), 200 … 100000.
        #[arg(long, default_value_t = 5000)]
        samples: usize,
        /// Seeds per design of E6, E7 and et0 (the seeds S … S + N − 1,
        /// common to every design; the tables give means ± standard
        /// errors), 1 … 500.
        #[arg(long, default_value_t = rootzone::experiment::DEFAULT_SEEDS)]
        seeds: u64,
    },
    /// A season of any controller against any plant ("what if"): the trace
    /// as CSV, the scores as JSON on standard output.
    ClosedLoop {
        /// The plant's soil: a texture name (e.g. sandy-loam) or
        /// ks=…,alpha=…,n=…,theta_r=…,theta_s=… (SI units, α in 1/m).
        #[arg(long)]
        plant: String,
        /// oracle (the Richards ZMPC given the plant's true soil and state),
        /// richards (the Richards ZMPC on the estimated state and soil),
        /// two-layer or single-lstm (sandy loam only: the shipped models,
        /// reading the sensor through the ensemble filter around sandy loam).
        #[arg(long)]
        controller: String,
        /// The estimator's prior: a texture name or unknown (default: the
        /// plant's texture when it is named, else unknown).
        #[arg(long)]
        prior: Option<String>,
        /// Weather CSV: step,start_hour,et0_mm,precip_mm (default: the
        /// embedded weather-dry).
        #[arg(long)]
        weather: Option<PathBuf>,
        /// Control steps of 2 h, 1 … 10000 (after the weather file's last
        /// row, that row holds).
        #[arg(long, default_value_t = 60)]
        steps: usize,
        /// Process noise level, e.g. 0.02 for 2 %.
        #[arg(long, default_value_t = 0.0)]
        process_noise: f64,
        /// Measurement noise level, e.g. 0.02 for 2 %.
        #[arg(long, default_value_t = 0.0)]
        measurement_noise: f64,
        /// Forecast error level, e.g. 0.2 for 20 %.
        #[arg(long, default_value_t = 0.0)]
        forecast_error: f64,
        /// Seed of the noise, the forecast error and the estimator.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Sensor depths [m], comma-separated, each in [0, 0.5], at most 16
        /// (default: 0.125, the rooting depth).
        #[arg(long, value_delimiter = ',')]
        sensor_depths: Option<Vec<f64>>,
        /// Write the step-by-step trace CSV here.
        #[arg(long)]
        trace: Option<PathBuf>,
    },
    /// Simulate fields beside a controller: measurements and forecasts to it
    /// over HTTP, setpoints back through its webhook actuator.
    #[command(after_help = FIELD_SIM_DEFAULTS)]
    FieldSim {
        /// Base URL of the controller (e.g. http://127.0.0.1:8080).
        #[arg(long)]
        controller: Option<String>,
        /// TOML configuration; environment variables ROOTZONE_… override it.
        #[arg(long)]
        config: Option<PathBuf>,
    },
    /// Copy every table of one store into another, empty one (for example
    /// from the embedded SQLite file to a PostgreSQL server).
    Migrate {
        /// The store to read: sqlite:<data folder> or postgres://user@host/db.
        #[arg(long)]
        from: String,
        /// The store to fill (migrated to this binary's schema first; it must
        /// hold no fields): sqlite:<folder> or postgres://user@host/db.
        #[arg(long)]
        to: String,
    },
    /// Run the controller daemon: HTTP API, control loop, simulated fields.
    #[command(after_help = SERVE_DEFAULTS)]
    Serve {
        /// TOML configuration (see config/default.toml); environment
        /// variables ROOTZONE_… override it.
        #[arg(long)]
        config: Option<PathBuf>,
    },
}

const SERVE_DEFAULTS: &str = "\
Defaults (each setting: config file key / environment variable):
  listen                    127.0.0.1:8080        ROOTZONE_LISTEN (host:port, names allowed)
  data_dir                  data                  ROOTZONE_DATA_DIR (made 0700; database 0600)
  api_token                 generated into <data_dir>/api-token   ROOTZONE_API_TOKEN
  models_dir                the shipped models    ROOTZONE_MODELS_DIR
  clock.speedup             1 (real time; ≤ 100000, 1e3 is fine)  ROOTZONE_CLOCK__SPEEDUP
  clock.epoch               unset (RFC 3339, years 2000-2199)    ROOTZONE_CLOCK__EPOCH
  limits.max_batch          10000 measurements    ROOTZONE_LIMITS__MAX_BATCH
  limits.max_future_skew_s  300                   ROOTZONE_LIMITS__MAX_FUTURE_SKEW_S
  limits.worker_threads     2                     ROOTZONE_LIMITS__WORKER_THREADS
  limits.max_catch_up_s     172800 (2 days)       ROOTZONE_LIMITS__MAX_CATCH_UP_S
  limits.late_window_s      3600 (readings up to 1 h late are assimilated)  ROOTZONE_LIMITS__LATE_WINDOW_S
  log.format                text (or json)        ROOTZONE_LOG__FORMAT
  log.level                 info (RUST_LOG wins)  ROOTZONE_LOG__LEVEL
  webhooks.allow_link_local false                 ROOTZONE_WEBHOOKS__ALLOW_LINK_LOCAL
  fields                    one simulated sandy-loam field 'demo' (first start only)
See config/default.toml and README.md.";

const FIELD_SIM_DEFAULTS: &str = "\
Defaults (each setting: config file key / environment variable):
  controller                http://127.0.0.1:8080 ROOTZONE_CONTROLLER (or --controller)
  api_token                 unset: the controller's token   ROOTZONE_API_TOKEN
  sim_listen                127.0.0.1:9090        ROOTZONE_SIM_LISTEN
  public_url                http://<sim_listen>   ROOTZONE_PUBLIC_URL
  sim_data_dir              field-data            ROOTZONE_SIM_DATA_DIR
  sim_token                 generated into <sim_data_dir>/sim-token   ROOTZONE_SIM_TOKEN
  clock.speedup             1                     ROOTZONE_CLOCK__SPEEDUP (same as the controller)
  clock.epoch               unset                 ROOTZONE_CLOCK__EPOCH (same as the controller)
  max_buffer                100000 measurements per field   ROOTZONE_MAX_BUFFER
  max_catch_up_s            172800 (2 days)       ROOTZONE_MAX_CATCH_UP_S
  fields                    one simulated sandy-loam field 'sim-field'
See config/field-sim.toml and README.md.";

/// Exit code for bad input (files, values, arguments).
const BAD_INPUT: u8 = 2;

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result: anyhow::Result<()> = match cli.command {
        Command::Simulate {
            weather,
            irrigation,
            steps,
            soil,
            process_noise,
            measurement_noise,
            seed,
            out,
        } => (|| {
            let (soil, _) = rootzone::experiment::estimated::parse_soil(&soil)
                .map_err(|e| anyhow::anyhow!("--soil: {}", e.trim_start_matches("soil: ")))?;
            run_simulation(&SimulateOptions {
                weather,
                irrigation,
                steps,
                soil,
                process_noise,
                measurement_noise,
                seed,
                out,
            })?;
            Ok(())
        })(),
        Command::Train {
            soil,
            soil_params,
            out,
            seed,
            quick,
            cache,
            window_noise,
        } => (|| {
            let (parameters, name) = match soil_params {
                Some(text) => {
                    let (parameters, _) = rootzone::experiment::estimated::parse_soil(&text)
                        .map_err(|e| anyhow::anyhow!("--soil-params: {e}"))?;
                    (parameters, text.replace(' ', ""))
                }
                None => {
                    let texture: Texture = soil.parse()?;
                    (texture.parameters(), texture.name().to_string())
                }
            };
            train(&name, parameters, &out, seed, quick, window_noise, &cache)
        })(),
        Command::Experiment {
            id,
            models,
            out,
            seed,
            cache,
            samples,
            seeds,
        } => (|| {
            let id: ExperimentId = id.parse()?;
            let written = run_experiment(
                id,
                &ExperimentOptions {
                    models,
                    out,
                    seed,
                    cache,
                    samples,
                    seeds,
                },
            )?;
            for path in written {
                println!("wrote {}", path.display());
            }
            Ok(())
        })(),
        Command::ClosedLoop {
            plant,
            controller,
            prior,
            weather,
            steps,
            process_noise,
            measurement_noise,
            forecast_error,
            seed,
            sensor_depths,
            trace,
        } => closed_loop(ClosedLoopArgs {
            plant,
            controller,
            prior,
            weather,
            steps,
            process_noise,
            measurement_noise,
            forecast_error,
            seed,
            sensor_depths,
            trace,
        }),
        Command::Serve { config } => serve(config),
        Command::Migrate { from, to } => migrate(&from, &to),
        Command::FieldSim { controller, config } => field_sim(controller, config),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::from(BAD_INPUT)
        }
    }
}

/// `rootzone migrate`: opens both stores (the target is created and
/// migrated), copies, reports the rows per table.
fn migrate(from: &str, to: &str) -> anyhow::Result<()> {
    use rootzone::store::{Location, Store, redact};
    let source = Location::parse(from).map_err(|e| anyhow::anyhow!("--from: {e}"))?;
    let target = Location::parse(to).map_err(|e| anyhow::anyhow!("--to: {e}"))?;
    if source == target {
        anyhow::bail!("--from and --to name the same store");
    }
    if let Location::Sqlite(dir) = &source
        && !dir.join("rootzone.sqlite3").is_file()
    {
        anyhow::bail!("--from: {}: no rootzone.sqlite3 there", dir.display());
    }
    let source =
        Store::connect(&source).map_err(|e| anyhow::anyhow!("--from {}: {e}", redact(from)))?;
    let target =
        Store::connect(&target).map_err(|e| anyhow::anyhow!("--to {}: {e}", redact(to)))?;
    let report = source
        .copy_into(&target)
        .map_err(|e| anyhow::anyhow!("{} → {}: {e}", redact(from), redact(to)))?;
    println!("copied {} → {}: {report}", redact(from), redact(to));
    Ok(())
}

/// `--window-noise`: a fraction of the range in [0, 1].
fn parse_window_noise(text: &str) -> Result<f64, String> {
    let level: f64 = text
        .parse()
        .map_err(|_| format!("'{text}' is not a number"))?;
    if (0.0..=1.0).contains(&level) {
        Ok(level)
    } else {
        Err(format!("{level} is not a fraction of the range in [0, 1]"))
    }
}

/// `rootzone train`: one progress bar per network.
fn train(
    soil_name: &str,
    soil: rootzone::soil::VanGenuchten,
    out: &std::path::Path,
    seed: u64,
    quick: bool,
    window_noise: Option<f64>,
    cache: &std::path::Path,
) -> anyhow::Result<()> {
    use indicatif::{MultiProgress, ProgressBar, ProgressStyle};
    let mut plan = if quick {
        TrainPlan::quick(seed)
    } else {
        TrainPlan::full(seed)
    };
    if let Some(level) = window_noise {
        plan.window_noise = (level > 0.0).then_some(level);
    }
    plan.soil = soil;
    let bars = MultiProgress::new();
    let style = ProgressStyle::with_template(
        "{prefix:>18} [{bar:30}] {pos:>3}/{len:3} epochs {msg} ({elapsed})",
    )
    .expect("a valid progress template")
    .progress_chars("=> ");
    let mut current: Option<ProgressBar> = None;
    let outcome = run_training(&plan, soil_name, out, cache, |event| match event {
        ProgressEvent::Stage {
            network,
            what,
            max_epochs,
        } => {
            if max_epochs == 0 {
                let _ = bars.println(format!("{network}: {what}"));
            } else {
                let bar = bars.add(ProgressBar::new(max_epochs as u64));
                bar.set_style(style.clone());
                bar.set_prefix(network);
                current = Some(bar);
            }
        }
        ProgressEvent::Epoch { report, .. } => {
            if let Some(bar) = &current {
                bar.set_position(report.epoch as u64);
                bar.set_message(format!(
                    "val MSE {:.3e} (best {:.3e} at {})",
                    report.validation_mse, report.best_validation_mse, report.best_epoch
                ));
            }
        }
        ProgressEvent::Finished {
            seconds,
            best_validation_mse,
            ..
        } => {
            if let Some(bar) = current.take() {
                bar.finish_with_message(format!(
                    "best val MSE {best_validation_mse:.3e} in {seconds:.1} s"
                ));
            }
        }
    })?;
    for (file, s) in &outcome.scores {
        println!(
            "{file}: NRMSE 1/10/20 steps {:.4} {:.4} {:.4}",
            s[0], s[1], s[2]
        );
    }
    println!(
        "wrote {} model files and {} in {:.1} s",
        outcome.files.len(),
        outcome.report.display(),
        outcome.seconds
    );
    Ok(())
}

struct ClosedLoopArgs {
    plant: String,
    controller: String,
    prior: Option<String>,
    weather: Option<PathBuf>,
    steps: usize,
    process_noise: f64,
    measurement_noise: f64,
    forecast_error: f64,
    seed: u64,
    sensor_depths: Option<Vec<f64>>,
    trace: Option<PathBuf>,
}

/// `rootzone closed-loop`: one run, JSON on standard output.
fn closed_loop(args: ClosedLoopArgs) -> anyhow::Result<()> {
    use rootzone::estimate::{EstimatorSettings, Prior};
    use rootzone::experiment::estimated::{
        Case, ControllerChoice, parse_soil, run_case, summary, trace,
    };
    use rootzone::weather::{DRY_SCENARIO, WeatherSeries};
    let (plant, texture) = parse_soil(&args.plant).map_err(|e| anyhow::anyhow!("--plant: {e}"))?;
    let controller: ControllerChoice = args
        .controller
        .parse()
        .map_err(|e| anyhow::anyhow!("--controller: {e}"))?;
    let prior = match args.prior.as_deref() {
        None => texture.map_or(Prior::Unknown, Prior::Texture),
        Some("unknown") => Prior::Unknown,
        Some(name) => Prior::Texture(
            name.parse::<Texture>()
                .map_err(|e| anyhow::anyhow!("--prior: {e} or unknown"))?,
        ),
    };
    let weather = match &args.weather {
        Some(path) => WeatherSeries::from_file(path)?,
        None => WeatherSeries::parse(DRY_SCENARIO, "weather-dry")?,
    };
    let case = Case {
        plant,
        controller,
        prior,
        weather,
        steps: args.steps,
        process_noise: args.process_noise,
        measurement_noise: args.measurement_noise,
        forecast_error: args.forecast_error,
        seed: args.seed,
        sensor_depths: args.sensor_depths.unwrap_or_else(|| vec![0.125]),
        estimator: EstimatorSettings::default(),
    };
    let run = run_case(&case).map_err(|e| anyhow::anyhow!("{e}"))?;
    if let Some(path) = &args.trace {
        std::fs::write(path, trace(&run))
            .map_err(|e| anyhow::anyhow!("cannot write {}: {e}", path.display()))?;
    }
    println!("{}", serde_json::to_string_pretty(&summary(&case, &run))?);
    Ok(())
}

/// `rootzone serve`: builds the daemon, says where it is, serves until
/// SIGINT/SIGTERM.
fn serve(config: Option<PathBuf>) -> anyhow::Result<()> {
    use rootzone::service::{App, Settings, shutdown_signal};
    let settings = Settings::load(config.as_deref())?;
    rootzone::service::init_logging(&settings.log);
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .max_blocking_threads(settings.limits.worker_threads.max(1) + 4)
        .build()?;
    let outcome = runtime.block_on(async move {
        let token_source = if settings.api_token.is_some() {
            "from the configuration".to_string()
        } else {
            format!("in {}", settings.data_dir.join("api-token").display())
        };
        let data = settings.data_dir.clone();
        let speedup = settings.clock.speedup;
        let app = App::build(settings).await?;
        let addr = app.local_addr()?;
        // a closed stdout must not stop the daemon: write errors are ignored
        let say = |line: String| {
            use std::io::Write;
            let mut out = std::io::stdout();
            let _ = writeln!(out, "{line}");
            let _ = out.flush();
        };
        say(format!(
            "rootzone listening on http://{addr} (API under /v1, metrics at /metrics)"
        ));
        say(format!(
            "data in {}; API token {token_source}",
            data.display()
        ));
        if speedup != 1.0 {
            say(format!("clock running {speedup}× real time"));
        }
        app.run(shutdown_signal()).await?;
        say("rootzone stopped".into());
        Ok::<(), anyhow::Error>(())
    });
    // a blocking task that did not stop within the grace period (it cannot
    // be cancelled from outside) must not hold the process
    runtime.shutdown_timeout(std::time::Duration::from_secs(1));
    outcome
}

/// `rootzone field-sim`: the separate field simulator.
fn field_sim(controller: Option<String>, config: Option<PathBuf>) -> anyhow::Result<()> {
    use rootzone::fieldsim::{FieldSimSettings, run};
    let settings = FieldSimSettings::load(config.as_deref(), controller.as_deref())?;
    rootzone::service::init_logging(&rootzone::service::settings::LogSettings::default());
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    runtime.block_on(run(settings, rootzone::service::shutdown_signal()))?;
    Ok(())
}
