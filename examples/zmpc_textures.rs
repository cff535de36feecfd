//! The Richards-model zone MPC on every texture (issue 14, part 6): for
//! each of the 12 textures under its default zone (MODEL.md §4) and each
//! weather file, 60 steps from h = −0.2 m, no noise and a perfect forecast,
//! the controller given the plant's state (the oracle). Prints per case the
//! irrigation, the step at which θ first entered the zone (a plant that
//! never enters has no distance after entry: "never"), the largest
//! distance outside the zone after that (split into the dry and the wet
//! side), the solve times and how many
//! model evaluations the solves made. Beside it, the wet-side distance
//! after entry of the same plant never irrigated: no irrigation gives the
//! driest column there is (water only adds), so where that distance exceeds
//! a bound, no controller that enters the zone keeps within it.
//!
//! `cargo run --release --example zmpc_textures [--work-budget=N|none] [--no-fork] [TEXTURE…]`
//!
//! `--no-fork` makes every prediction on the solve's own thread (a model
//! without [`PredictionModel::fork`]): the same plans, the time a solve
//! takes without its first constant starts predicted beside its warm run.
//!
//! The solves' model work (Newton iterations per solve, their cost, and
//! how many solves the work and the time budget ended) goes to stderr.

use std::time::Instant;

use rootzone::control::{ModelError, SolveStatus};
use rootzone::control::{MpcSettings, PredictionModel, RichardsModel, ZoneMpc, ZoneSettings};
use rootzone::soil::{Field, FieldSettings, Interrupt, Texture};
use rootzone::weather::{DRY_SCENARIO, RAIN_SCENARIO, WeatherSeries};

/// A Richards model that counts its evaluations.
struct Counted {
    inner: RichardsModel,
    predictions: usize,
    jacobians: usize,
    prediction_time: f64,
    jacobian_time: f64,
    /// Whether the model forks (see the module docs), and the forks'
    /// predictions the solve adopted.
    fork: bool,
    forked: usize,
}

impl PredictionModel for Counted {
    fn predict(&mut self, plan: &[f64], out: &mut [f64]) -> Result<(), ModelError> {
        self.predictions += 1;
        let t = Instant::now();
        let r = self.inner.predict(plan, out);
        self.prediction_time += t.elapsed().as_secs_f64() * 1e3;
        r
    }

    fn predict_with_jacobian(
        &mut self,
        plan: &[f64],
        out: &mut [f64],
        jac: &mut [f64],
    ) -> Result<(), ModelError> {
        self.jacobians += 1;
        let t = Instant::now();
        let r = self.inner.predict_with_jacobian(plan, out, jac);
        self.jacobian_time += t.elapsed().as_secs_f64() * 1e3;
        r
    }

    fn set_interrupt(&mut self, interrupt: Option<Interrupt>) {
        self.inner.set_interrupt(interrupt);
    }

    fn monotone_in_supply(&self) -> bool {
        self.inner.monotone_in_supply()
    }

    fn fork(&self, interrupt: Interrupt) -> Option<Box<dyn PredictionModel>> {
        self.fork
            .then(|| Box::new(self.inner.forked(interrupt)) as Box<dyn PredictionModel>)
    }

    fn book_work(&mut self, work: usize) {
        self.forked += 1;
        self.inner.book_work(work);
    }

    fn set_work_budget(&mut self, budget: Option<usize>) {
        self.inner.set_work_budget(budget);
    }

    fn work_spent(&self) -> usize {
        self.inner.work_spent()
    }

    fn out_of_work(&self) -> bool {
        self.inner.out_of_work()
    }
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

fn main() {
    let mut only: Vec<String> = std::env::args().skip(1).collect();
    // --work-budget=N (Newton iterations per solve) or --work-budget=none
    let work_budget = only
        .iter()
        .position(|a| a.starts_with("--work-budget="))
        .map(|i| {
            let value = only.remove(i)["--work-budget=".len()..].to_string();
            (value != "none").then(|| {
                value.parse::<usize>().unwrap_or_else(|_| {
                    eprintln!("--work-budget takes a count or none, not {value}");
                    std::process::exit(2)
                })
            })
        });
    let fork = match only.iter().position(|a| a == "--no-fork") {
        Some(i) => {
            only.remove(i);
            false
        }
        None => true,
    };
    let dry = WeatherSeries::parse(DRY_SCENARIO, "weather-dry.csv").expect("embedded weather");
    let rain = WeatherSeries::parse(RAIN_SCENARIO, "weather-rain.csv").expect("embedded weather");
    println!(
        "| texture | weather | I_T mm | entered at | dry after entry | wet after entry | median ms | p95 ms | \
         max ms | predictions/solve | forked/solve | ms each | Jacobians/solve | ms each | iterations/solve | \
         not converged | fallbacks | wet after entry, never irrigated |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|");
    for texture in Texture::ALL {
        if !only.is_empty() && !only.contains(&texture.to_string()) {
            continue;
        }
        let soil = texture.parameters();
        for (name, weather) in [("dry", &dry), ("rain", &rain)] {
            let mut field = Field::new(FieldSettings {
                soil,
                ..FieldSettings::default()
            })
            .expect("a texture is a valid soil");
            let zone = ZoneSettings::default_for(&soil);
            let settings = MpcSettings {
                zone,
                theta_r: soil.residual_water_content,
                theta_s: soil.saturated_water_content,
                work_budget: work_budget.unwrap_or(MpcSettings::default().work_budget),
                ..MpcSettings::default()
            };
            let (low, up) = zone.bounds(0, settings.horizon);
            let mut mpc = ZoneMpc::new(settings);
            let (mut irrigation, mut times) = (0.0, Vec::new());
            let (mut predictions, mut jacobians, mut iterations, mut unconverged) = (0, 0, 0, 0);
            let mut forked = 0;
            let (mut prediction_ms, mut jacobian_ms) = (0.0, 0.0);
            let (mut entry, mut dry_excess, mut wet_excess) = (None, 0.0f64, 0.0f64);
            let mut stopped = false;
            let mut fallbacks = 0;
            let (mut work, mut budget_cut, mut time_cut) = (Vec::new(), 0, 0);
            for step in 0..60 {
                let forecast = weather.forecast(step, settings.horizon, 0.0, &mut rand_free());
                let mut model = Counted {
                    inner: RichardsModel::new(&field, &forecast),
                    predictions: 0,
                    jacobians: 0,
                    prediction_time: 0.0,
                    jacobian_time: 0.0,
                    fork,
                    forked: 0,
                };
                let started = Instant::now();
                let solution = mpc.solve(&mut model);
                times.push(started.elapsed().as_secs_f64() * 1e3);
                work.push(model.work_spent() as f64);
                budget_cut += usize::from(solution.status == SolveStatus::WorkBudget);
                time_cut += usize::from(solution.status == SolveStatus::TimeBudget);
                predictions += model.predictions;
                forked += model.forked;
                jacobians += model.jacobians;
                prediction_ms += model.prediction_time;
                jacobian_ms += model.jacobian_time;
                iterations += solution.iterations;
                if solution.status != SolveStatus::Converged {
                    unconverged += 1;
                }
                if matches!(solution.status, SolveStatus::Fallback(_)) {
                    fallbacks += 1;
                }
                let u = solution.plan[0].clamp(0.0, settings.u_max);
                irrigation += u * field.settings().sampling_time * 1e3;
                let truth = weather.steps()[step.min(weather.len() - 1)];
                let report = match field.step(truth.forcing(u, field.settings().sampling_time)) {
                    Ok(report) => report,
                    Err(e) => {
                        println!("| {texture} | {name} | plant stopped: {e} |");
                        stopped = true;
                        break;
                    }
                };
                let theta = report.water_content;
                if entry.is_none() && (low..=up).contains(&theta) {
                    entry = Some(step);
                }
                if entry.is_some() {
                    dry_excess = dry_excess.max(low - theta);
                    wet_excess = wet_excess.max(theta - up);
                }
            }
            if stopped {
                continue;
            }
            let n = times.len() as f64;
            let mut sorted = times.clone();
            sorted.sort_by(f64::total_cmp);
            println!(
                "| {texture} | {name} | {irrigation:.2} | {} | {:.1e} | {:.1e} | {:.1} | {:.1} | {:.1} | \
                 {:.1} | {:.1} | {:.2} | {:.1} | {:.2} | {:.1} | {unconverged} | {fallbacks} | {:.1e} |",
                entry.map_or("never".to_string(), |k| k.to_string()),
                dry_excess.max(0.0),
                wet_excess.max(0.0),
                median(times.clone()),
                sorted[((0.95 * n) as usize).min(sorted.len() - 1)],
                sorted[sorted.len() - 1],
                predictions as f64 / n,
                forked as f64 / n,
                prediction_ms / predictions.max(1) as f64,
                jacobians as f64 / n,
                jacobian_ms / jacobians.max(1) as f64,
                iterations as f64 / n,
                unirrigated_wet_excess(soil, weather, low, up),
            );
            let total_work: f64 = work.iter().sum();
            eprintln!(
                "{texture} {name}: Newton iterations per solve median {:.0}, max {:.0}; \
                 {:.3} ms per 1000; work-budget stops {budget_cut}, time-budget stops {time_cut}",
                median(work.clone()),
                work.iter().copied().fold(0.0, f64::max),
                times.iter().sum::<f64>() / total_work.max(1.0) * 1e3,
            );
        }
    }
}

/// The largest θ − up after θ first enters [low, up] in 60 steps of the
/// plant never irrigated (0 if it never enters or never leaves upward).
fn unirrigated_wet_excess(
    soil: rootzone::soil::VanGenuchten,
    weather: &WeatherSeries,
    low: f64,
    up: f64,
) -> f64 {
    let mut field = Field::new(FieldSettings {
        soil,
        ..FieldSettings::default()
    })
    .expect("a texture is a valid soil");
    let (mut entered, mut excess) = (false, 0.0f64);
    for step in 0..60 {
        let truth = weather.steps()[step.min(weather.len() - 1)];
        let Ok(report) = field.step(truth.forcing(0.0, field.settings().sampling_time)) else {
            return f64::NAN;
        };
        let theta = report.water_content;
        entered |= (low..=up).contains(&theta);
        if entered {
            excess = excess.max(theta - up);
        }
    }
    excess
}

/// A perfect forecast draws nothing; the generator is only its argument.
fn rand_free() -> rand_chacha::ChaCha8Rng {
    use rand::SeedableRng;
    rand_chacha::ChaCha8Rng::seed_from_u64(0)
}
