//! The `rootzone` command line: parses arguments and calls one library function per command.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};
use rootzone::simulate::{SimulateOptions, run as run_simulation};
use rootzone::soil::Texture;

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
        /// Soil texture (Carsel & Parrish 1988), e.g. sandy-loam, loam, clay.
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
}

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
            let soil: Texture = soil.parse()?;
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
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::from(BAD_INPUT)
        }
    }
}
