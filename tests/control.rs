//! The zone MPC: zone formula, optimality of the SQP (KKT on a convex case,
//! against a slow independent optimiser on the shipped surrogate), fallback.

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rootzone::control::{
    LinearModel, ModelError, MpcSettings, PredictionModel, SolveStatus, SurrogateModel, ZoneMpc,
    ZoneSettings, objective,
};
use rootzone::surrogate::ModelFile;

#[test]
fn zone_matches_hand_computed_values() {
    let z = ZoneSettings {
        low0: 0.18,
        up0: 0.23,
        y_low: 0.205,
        y_up: 0.205,
        mu: 1.0,
    };
    // k = 2 of 20: e^0.1 = 1.1051709, e^−0.1 = 0.9048374
    let (low, up) = z.bounds(2, 20);
    assert!((low - 0.198_930_76).abs() < 1e-7, "{low}");
    assert!((up - 0.208_112_61).abs() < 1e-7, "{up}");
    // k = 4: 0.18·e^0.2 = 0.2199 > 0.205 and 0.23·e^−0.2 = 0.1883 < 0.205: the terminal zone
    assert_eq!(z.bounds(4, 20), (0.205, 0.205));
    assert_eq!(z.bounds(20, 20), (0.205, 0.205));
    // μ = 0: time-invariant
    let fixed = ZoneSettings::default();
    assert_eq!(fixed.bounds(1, 20), (0.18, 0.23));
    assert_eq!(fixed.bounds(20, 20), (0.18, 0.23));
    assert!(fixed.problem().is_none());
    assert!(ZoneSettings { mu: -1.0, ..z }.problem().is_some());
}

fn cost(settings: &MpcSettings, model: &mut dyn PredictionModel, ubar: &[f64]) -> f64 {
    let plan: Vec<f64> = ubar.iter().map(|v| v * settings.u_max).collect();
    let mut y = vec![0.0; plan.len()];
    match model.predict(&plan, &mut y) {
        Ok(()) => objective(settings, &y, ubar),
        Err(_) => f64::INFINITY,
    }
}

fn fd_gradient(settings: &MpcSettings, model: &mut dyn PredictionModel, ubar: &[f64]) -> Vec<f64> {
    let h = 1e-6;
    (0..ubar.len())
        .map(|j| {
            let (mut up, mut down) = (ubar.to_vec(), ubar.to_vec());
            up[j] += h;
            down[j] -= h;
            (cost(settings, model, &up) - cost(settings, model, &down)) / (2.0 * h)
        })
        .collect()
}

#[test]
fn sqp_solution_satisfies_the_kkt_conditions_of_a_convex_problem() {
    let settings = MpcSettings::default();
    for (start, b, rho) in [(0.15, 600.0, 0.85), (0.26, 800.0, 0.7), (0.19, 300.0, 0.9)] {
        // dries out by 0.004 per step without irrigation
        let a: Vec<f64> = (0..20).map(|k| start - 0.004 * k as f64).collect();
        let mut model = LinearModel { a, b, rho };
        let mut mpc = ZoneMpc::new(settings);
        let sol = mpc.solve(&mut model);
        assert_eq!(sol.status, SolveStatus::Converged, "{sol:?}");
        let ubar: Vec<f64> = sol.plan.iter().map(|u| u / settings.u_max).collect();
        let g = fd_gradient(&settings, &mut model, &ubar);
        let scale = g.iter().map(|v| v.abs()).fold(1.0, f64::max);
        for (j, (&u, &gj)) in ubar.iter().zip(&g).enumerate() {
            let tol = 1e-3 * scale;
            if u <= 1e-6 {
                assert!(gj >= -tol, "ū_{j} = 0 but ∂J/∂ū = {gj}");
            } else if u >= 1.0 - 1e-6 {
                assert!(gj <= tol, "ū_{j} = 1 but ∂J/∂ū = {gj}");
            } else {
                assert!(gj.abs() <= tol, "interior ū_{j} = {u}, ∂J/∂ū = {gj}");
            }
        }
        // nontrivial: something is irrigated when starting dry
        if start < 0.18 {
            assert!(sol.plan.iter().any(|&u| u > 1e-7));
        }
    }
}

/// Projected gradient with finite-difference gradients and Armijo
/// backtracking, run from a start until it stalls.
fn slow_optimum(settings: &MpcSettings, model: &mut dyn PredictionModel, start: Vec<f64>) -> f64 {
    let mut u = start;
    let mut j = cost(settings, model, &u);
    let mut step = 1e-3;
    for _ in 0..400 {
        let g = fd_gradient(settings, model, &u);
        let mut improved = false;
        for _ in 0..30 {
            let trial: Vec<f64> = u
                .iter()
                .zip(&g)
                .map(|(x, gx)| (x - step * gx).clamp(0.0, 1.0))
                .collect();
            let decrease: f64 = u
                .iter()
                .zip(&trial)
                .zip(&g)
                .map(|((a, b), gx)| gx * (a - b))
                .sum();
            let jt = cost(settings, model, &trial);
            if jt <= j - 1e-4 * decrease && jt < j {
                u = trial;
                j = jt;
                step *= 2.0;
                improved = true;
                break;
            }
            step *= 0.5;
        }
        if !improved {
            break;
        }
    }
    j
}

/// The SQP's objective against the best of the slow optimiser from three
/// starts; returns the relative excess.
fn excess_over_slow(
    settings: &MpcSettings,
    model: &mut SurrogateModel,
    sol: &rootzone::control::Solution,
    rng: &mut ChaCha8Rng,
    label: &str,
) -> f64 {
    assert!(
        !matches!(sol.status, SolveStatus::Fallback(_)),
        "{label}: {:?}",
        sol.status
    );
    let ubar: Vec<f64> = sol.plan.iter().map(|u| u / settings.u_max).collect();
    let j_sqp = cost(settings, model, &ubar);
    assert!((j_sqp - sol.objective).abs() <= 1e-9 * (1.0 + j_sqp));
    let starts = [
        vec![0.0; 20],
        vec![0.5; 20],
        (0..20).map(|_| rng.random::<f64>()).collect(),
    ];
    let j_slow = starts
        .into_iter()
        .map(|s| slow_optimum(settings, model, s))
        .fold(f64::INFINITY, f64::min);
    assert!(
        j_sqp <= j_slow * 1.001 + 1e-9,
        "{label}: SQP {j_sqp} vs slow {j_slow} ({:?}, {} iterations, plan {:?})",
        sol.status,
        sol.iterations,
        ubar.iter().map(|v| format!("{v:.2e}")).collect::<Vec<_>>()
    );
    (j_sqp - j_slow) / j_slow.max(1e-9)
}

#[test]
fn sqp_matches_a_slow_optimiser_on_the_shipped_two_layer_model() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("models/two-layer.json");
    let file = ModelFile::load(&path).unwrap();
    let settings = MpcSettings::default();
    let mut rng = ChaCha8Rng::seed_from_u64(2024);
    let mut worst: f64 = 0.0;
    // The problem is not convex, so the SQP runs from several starts. The
    // warm problems are where the shifted previous plan can sit in a poor
    // basin after a new measurement: on networks trained on noisier windows
    // (as the shipped ones are), 4× above the slow optimiser until the SQP
    // also tried the constant starts after a converged warm run.
    // ten windows, each solved cold (multi-start) and then, one step later,
    // warm-started from the shifted plan as in the closed loop: 20 problems
    for problem in 0..10 {
        let level = 0.13 + 0.2 * rng.random::<f64>();
        let past_u: Vec<f64> = (0..20)
            .map(|_| {
                if rng.random::<f64>() < 0.2 {
                    5e-6 * rng.random::<f64>()
                } else {
                    0.0
                }
            })
            .collect();
        let past_y: Vec<f64> = (0..20)
            .map(|i| level + 0.002 * (i as f64 - 10.0) * (rng.random::<f64>() - 0.5))
            .collect();
        let past_e = (0..20).map(|i| 4.6e-8 * (i % 12) as f64 / 6.0).collect();
        let mut model = SurrogateModel::new(file.predictor(), past_u, past_y, past_e);
        model.bias = 0.01 * (2.0 * rng.random::<f64>() - 1.0);
        let mut mpc = ZoneMpc::new(settings);
        let cold = mpc.solve(&mut model);
        let label = format!("problem {problem} (cold)");
        worst = worst.max(excess_over_slow(
            &settings, &mut model, &cold, &mut rng, &label,
        ));
        // the first move applied, a measurement 0.003 off the prediction
        model.push(
            cold.plan[0],
            cold.predicted[0] + 0.003 * (2.0 * rng.random::<f64>() - 1.0),
            4.6e-8,
        );
        let warm = mpc.solve(&mut model);
        let label = format!("problem {problem} (warm)");
        worst = worst.max(excess_over_slow(
            &settings, &mut model, &warm, &mut rng, &label,
        ));
    }
    eprintln!("largest relative excess of the SQP objective: {worst:e}");
}

struct Broken;

impl PredictionModel for Broken {
    fn predict(&mut self, _: &[f64], out: &mut [f64]) -> Result<(), ModelError> {
        out.fill(f64::NAN);
        Err(ModelError("non-finite prediction at step 0".into()))
    }
    fn predict_with_jacobian(
        &mut self,
        p: &[f64],
        out: &mut [f64],
        _: &mut [f64],
    ) -> Result<(), ModelError> {
        self.predict(p, out)
    }
}

#[test]
fn a_model_returning_nan_gives_a_flagged_safe_plan() {
    let settings = MpcSettings::default();
    let mut mpc = ZoneMpc::new(settings);
    // first a good solve, so that there is a plan to fall back on
    let mut good = LinearModel {
        a: (0..20).map(|k| 0.16 - 0.004 * k as f64).collect(),
        b: 600.0,
        rho: 0.85,
    };
    let first = mpc.solve(&mut good);
    let sol = mpc.solve(&mut Broken);
    assert!(
        matches!(&sol.status, SolveStatus::Fallback(r) if r.contains("non-finite")),
        "{:?}",
        sol.status
    );
    assert!(
        sol.plan
            .iter()
            .all(|u| u.is_finite() && (0.0..=settings.u_max).contains(u))
    );
    // the previous plan shifted by one step
    assert_eq!(sol.plan[..19], first.plan[1..]);
    assert_eq!(sol.plan[19], first.plan[19]);
    // without any previous plan: no irrigation
    let sol = ZoneMpc::new(settings).solve(&mut Broken);
    assert!(matches!(sol.status, SolveStatus::Fallback(_)));
    assert!(sol.plan.iter().all(|&u| u == 0.0));
}

#[test]
fn richards_jacobian_from_integrator_tangents_matches_finite_differences() {
    use rootzone::control::RichardsModel;
    use rootzone::soil::{Field, FieldSettings};
    use rootzone::weather::{DRY_SCENARIO, WeatherSeries};
    let weather = WeatherSeries::parse(DRY_SCENARIO, "dry").unwrap();
    // Tight tolerances: the tangents differentiate the discrete solution with
    // its step sizes fixed, finite differences also see the step sizes move
    // with the input (an effect of the size of the local error).
    let settings = FieldSettings {
        tolerances: rootzone::soil::Tolerances {
            relative: 1e-8,
            absolute: 1e-10,
        },
        ..FieldSettings::default()
    };
    let mut field = Field::new(settings).unwrap();
    for (k, step) in weather.steps()[..6].iter().enumerate() {
        let u = if k == 2 { 4e-6 } else { 0.0 };
        field.step(step.forcing(u, 7200.0)).unwrap();
    }
    let n = 8;
    let mut model = RichardsModel::new(&field, &weather.steps()[6..6 + n]);
    let plan: Vec<f64> = (0..n)
        .map(|k| [0.0, 2e-6, 5e-7, 0.0, 8e-6, 1e-6, 0.0, 3e-6][k])
        .collect();
    let mut y = vec![0.0; n];
    let mut jac = vec![0.0; n * n];
    model
        .predict_with_jacobian(&plan, &mut y, &mut jac)
        .unwrap();
    let mut plain = vec![0.0; n];
    model.predict(&plan, &mut plain).unwrap();
    assert_eq!(y, plain, "tangents must not change the prediction");
    let scale = jac.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    assert!(scale > 1e3, "irrigation must wet the sensor: {scale}");
    // central differences; second-order one-sided ones at the bound u = 0
    let delta = 2e-8;
    let (mut a, mut b) = (vec![0.0; n], vec![0.0; n]);
    let mut worst: f64 = 0.0;
    for j in 0..n {
        let mut p = plan.clone();
        let one_sided = plan[j] < delta;
        p[j] = plan[j] + delta;
        model.predict(&p, &mut a).unwrap();
        p[j] = if one_sided {
            plan[j] + 2.0 * delta
        } else {
            plan[j] - delta
        };
        model.predict(&p, &mut b).unwrap();
        for k in 0..n {
            let fd = if one_sided {
                (-3.0 * y[k] + 4.0 * a[k] - b[k]) / (2.0 * delta)
            } else {
                (a[k] - b[k]) / (2.0 * delta)
            };
            let exact = jac[k * n + j];
            worst = worst.max((fd - exact).abs() / scale);
            assert!(
                (fd - exact).abs() <= 1e-3 * scale,
                "dy_{k}/du_{j}: tangent {exact:e}, finite difference {fd:e}"
            );
            if j > k {
                assert_eq!(exact, 0.0, "no input affects earlier outputs");
            }
        }
    }
    eprintln!("largest difference / largest entry: {worst:e}");
}

/// The same check where the zone MPC's linearisation is weakest: clay
/// (n = 1.09, whose K rises steeply just below saturation) from h = −0.2 m
/// under a pulsed plan that brings the sensor cell within 3e-3 of θs,
/// above clay's default zone (whose top is 4.4e-3 below θs). At the
/// default tolerances this check fails (1.2 % of the largest entry here,
/// and 2.0 % at 10× tighter; 2.5 % with the SDIRK4 integrator before, on
/// whose 20-step plans the model's response to a 0.1–10 % change of one
/// step's rate differed from the tangents by 22–78 %, the integration's
/// error); at tolerances 1,000× tighter the two agree to 1 % of the
/// largest entry, so the tangents are the derivative the discrete model
/// converges to (ARCHITECTURE.md, zone MPC).
#[test]
fn richards_tangents_match_finite_differences_near_saturation_on_clay() {
    use rootzone::control::RichardsModel;
    use rootzone::soil::{Field, FieldSettings, Texture, Tolerances};
    use rootzone::weather::{DRY_SCENARIO, WeatherSeries};
    let weather = WeatherSeries::parse(DRY_SCENARIO, "dry").unwrap();
    let soil = Texture::Clay.parameters();
    let field = Field::new(FieldSettings {
        soil,
        initial_head: -0.2,
        tolerances: Tolerances {
            relative: 1e-8,
            absolute: 1e-10,
        },
        ..FieldSettings::default()
    })
    .unwrap();
    let n = 12;
    let ks = soil.saturated_conductivity;
    // 0.1 Ks every third step, 0.02 Ks otherwise
    let plan: Vec<f64> = (0..n)
        .map(|k| if k % 3 == 0 { 0.1 * ks } else { 0.02 * ks })
        .collect();
    let mut model = RichardsModel::new(&field, &weather.steps()[..n]);
    let (mut y, mut jac) = (vec![0.0; n], vec![0.0; n * n]);
    model
        .predict_with_jacobian(&plan, &mut y, &mut jac)
        .unwrap();
    let wettest = y.iter().fold(0.0f64, |m, &t| m.max(t));
    assert!(
        wettest > soil.saturated_water_content - 3e-3,
        "the plan must bring the sensor near saturation: {wettest}"
    );
    let (mut a, mut b) = (vec![0.0; n], vec![0.0; n]);
    for j in [0, 5, 10] {
        let delta = 1e-2 * plan[j];
        let mut p = plan.clone();
        p[j] = plan[j] + delta;
        model.predict(&p, &mut a).unwrap();
        p[j] = plan[j] - delta;
        model.predict(&p, &mut b).unwrap();
        let scale = (j..n).fold(0.0f64, |m, k| m.max(jac[k * n + j].abs()));
        assert!(scale > 1e3, "u_{j} must wet the sensor: {scale}");
        for k in j..n {
            let fd = (a[k] - b[k]) / (2.0 * delta);
            let exact = jac[k * n + j];
            assert!(
                (fd - exact).abs() <= 1e-2 * scale,
                "dy_{k}/du_{j}: tangent {exact:e}, finite difference {fd:e} (largest {scale:e})"
            );
        }
    }
}

/// The SQP takes a trial plan's prediction from the evaluation that also
/// gives its Jacobian (`ZoneMpc::solve`): the tangents must leave the
/// prediction as it is, bit for bit, on every texture and also where the
/// plan ponds the surface (the integrator's robust path).
#[test]
fn the_richards_prediction_is_the_same_with_and_without_its_jacobian_on_every_texture() {
    use rootzone::control::RichardsModel;
    use rootzone::soil::{Field, FieldSettings, Texture};
    use rootzone::weather::{RAIN_SCENARIO, WeatherSeries};
    let weather = WeatherSeries::parse(RAIN_SCENARIO, "rain").unwrap();
    let n = 6;
    let plan = [1e-5, 0.0, 3e-6, 1e-5, 1e-7, 0.0];
    for texture in Texture::ALL {
        let field = Field::new(FieldSettings {
            soil: texture.parameters(),
            ..FieldSettings::default()
        })
        .unwrap();
        // the rain scenario's wet days, from step 18
        let mut model = RichardsModel::new(&field, &weather.steps()[18..18 + n]);
        let (mut y, mut jac, mut plain) = (vec![0.0; n], vec![0.0; n * n], vec![0.0; n]);
        model
            .predict_with_jacobian(&plan, &mut y, &mut jac)
            .unwrap();
        model.predict(&plan, &mut plain).unwrap();
        assert_eq!(y, plain, "{texture}: tangents changed the prediction");
        assert!(
            jac.iter().any(|&d| d > 0.0) && y.iter().any(|&t| t > field.water_content() + 1e-3),
            "{texture}: the plan must wet the sensor"
        );
    }
}

/// The zone MPC skips constant start plans by the wet side of a lower one
/// for a model `monotone_in_supply`: the Richards model claims it, so more
/// irrigation must never predict a lower θ. Random plans and random
/// non-negative increments on every texture, dry and wet weather (the
/// larger rates pond the fine soils), from a moist column.
#[test]
fn more_irrigation_never_predicts_less_water_in_the_richards_model() {
    use rootzone::control::RichardsModel;
    use rootzone::soil::{Field, FieldSettings, Texture};
    use rootzone::weather::{DRY_SCENARIO, RAIN_SCENARIO, WeatherSeries};
    let n = 8;
    let u_max = MpcSettings::default().u_max;
    let mut rng = ChaCha8Rng::seed_from_u64(21);
    let mut largest_rise: f64 = 0.0;
    let (mut compared, mut failed) = (0, 0);
    for (text, from) in [(DRY_SCENARIO, 6), (RAIN_SCENARIO, 18)] {
        let weather = WeatherSeries::parse(text, "scenario").unwrap();
        for texture in Texture::ALL {
            let field = Field::new(FieldSettings {
                soil: texture.parameters(),
                initial_head: -0.5,
                ..FieldSettings::default()
            })
            .unwrap();
            let mut model = RichardsModel::new(&field, &weather.steps()[from..from + n]);
            assert!(model.monotone_in_supply());
            for _ in 0..3 {
                let u: Vec<f64> = (0..n)
                    .map(|_| u_max * 10f64.powf(rng.random_range(-4.0..0.0)))
                    .collect();
                let v: Vec<f64> = u
                    .iter()
                    .map(|&x| (x + u_max * rng.random_range(0.0..0.3)).min(u_max))
                    .collect();
                let (mut yu, mut yv) = (vec![0.0; n], vec![0.0; n]);
                // a plan that ponds a fine soil may reach the model's work
                // limits (the solve then has no prediction to bound with)
                if model.predict(&u, &mut yu).is_err() || model.predict(&v, &mut yv).is_err() {
                    failed += 1;
                    continue;
                }
                compared += 1;
                for k in 0..n {
                    // the integrations' tolerance, not a physical drop
                    assert!(
                        yv[k] >= yu[k] - 1e-6,
                        "{texture}, step {k}: {} with more water against {}",
                        yv[k],
                        yu[k]
                    );
                    largest_rise = largest_rise.max(yv[k] - yu[k]);
                }
            }
        }
    }
    assert!(largest_rise > 1e-2, "the increments must wet the column");
    assert!(compared >= 60, "{compared} pairs compared, {failed} failed");
}

/// The time budget binds every part of a solve: a Richards-model solve on a
/// soil whose trial plans pond the surface ends within its budget plus the
/// cost of one integration of one sampling step, and says how it ended.
#[test]
fn the_time_budget_binds_richards_solves_on_every_texture() {
    use rootzone::control::RichardsModel;
    use rootzone::soil::{Field, FieldSettings, Forcing, Texture};
    use rootzone::weather::{DRY_SCENARIO, WeatherSeries};
    use std::time::{Duration, Instant};
    let weather = WeatherSeries::parse(DRY_SCENARIO, "weather-dry.csv").unwrap();
    let budget = Duration::from_millis(150);
    for texture in Texture::ALL {
        let soil = texture.parameters();
        let field = Field::new(FieldSettings {
            soil,
            ..FieldSettings::default()
        })
        .unwrap();
        // the cost of one sampling step's integration at the largest rate
        // from this state (where the integrator works hardest)
        let mut integrator = field.integrator().clone();
        let mut state = field.state().clone();
        let clock = Instant::now();
        let _ = integrator.advance(
            &mut state,
            0.0,
            7200.0,
            Forcing {
                irrigation: 1e-5,
                ..weather.steps()[0].forcing(0.0, 7200.0)
            },
        );
        let one_step = clock.elapsed();
        let settings = MpcSettings {
            zone: ZoneSettings::default_for(&soil),
            theta_r: soil.residual_water_content,
            theta_s: soil.saturated_water_content,
            time_budget: budget,
            // the safety net alone: no count ends the solve first
            work_budget: None,
            ..MpcSettings::default()
        };
        let mut model = RichardsModel::new(&field, &weather.steps()[..20]);
        let clock = Instant::now();
        let solution = ZoneMpc::new(settings).solve(&mut model);
        let wall = clock.elapsed();
        // slack for the QP and the bookkeeping after the last evaluation
        let limit = budget + one_step + Duration::from_millis(30);
        assert!(
            wall <= limit,
            "{texture}: solve took {wall:?}, budget {budget:?} + one step {one_step:?}"
        );
        assert!(solution.solve_time <= wall);
        assert_eq!(solution.plan.len(), 20);
        assert!(solution.plan.iter().all(|u| (0.0..=1e-5).contains(u)));
        // a solve that ran out says so
        if wall > budget + Duration::from_millis(5) {
            assert!(
                matches!(
                    solution.status,
                    SolveStatus::TimeBudget | SolveStatus::Fallback(_)
                ),
                "{texture}: {:?} after {wall:?}",
                solution.status
            );
        }
    }
}

/// A Richards model whose every evaluation is made slow, as on a loaded
/// machine, and made on the solve's own thread (it has no fork).
struct Slowed(rootzone::control::RichardsModel, std::time::Duration);

impl PredictionModel for Slowed {
    fn predict(&mut self, plan: &[f64], out: &mut [f64]) -> Result<(), ModelError> {
        std::thread::sleep(self.1);
        self.0.predict(plan, out)
    }

    fn predict_with_jacobian(
        &mut self,
        plan: &[f64],
        out: &mut [f64],
        jac: &mut [f64],
    ) -> Result<(), ModelError> {
        std::thread::sleep(self.1);
        self.0.predict_with_jacobian(plan, out, jac)
    }

    fn set_interrupt(&mut self, interrupt: Option<rootzone::soil::Interrupt>) {
        self.0.set_interrupt(interrupt);
    }

    fn set_work_budget(&mut self, budget: Option<usize>) {
        self.0.set_work_budget(budget);
    }

    fn work_spent(&self) -> usize {
        self.0.work_spent()
    }

    fn out_of_work(&self) -> bool {
        self.0.out_of_work()
    }

    fn monotone_in_supply(&self) -> bool {
        self.0.monotone_in_supply()
    }
}

/// A solve that its work budget ends (a count of Newton iterations, not
/// the wall clock) says so, spends about its budget, and gives the same
/// plan when every evaluation is made 20 ms slower: the plan does not
/// depend on the machine's speed. Without a budget the same solve spends
/// more and differs.
#[test]
fn the_work_budget_ends_a_richards_solve_the_same_at_any_speed() {
    use rootzone::control::RichardsModel;
    use rootzone::soil::{Field, FieldSettings, Texture};
    use rootzone::weather::{RAIN_SCENARIO, WeatherSeries};
    use std::time::Duration;
    let weather = WeatherSeries::parse(RAIN_SCENARIO, "weather-rain.csv").unwrap();
    let soil = Texture::Loam.parameters();
    let field = Field::new(FieldSettings {
        soil,
        ..FieldSettings::default()
    })
    .unwrap();
    let budget = 1_500;
    let settings = MpcSettings {
        zone: ZoneSettings::default_for(&soil),
        theta_r: soil.residual_water_content,
        theta_s: soil.saturated_water_content,
        time_budget: Duration::from_secs(3600),
        work_budget: Some(budget),
        ..MpcSettings::default()
    };
    let forecast = &weather.steps()[15..35];
    let mut model = RichardsModel::new(&field, forecast);
    let fast = ZoneMpc::new(settings).solve(&mut model);
    assert_eq!(fast.status, SolveStatus::WorkBudget, "{fast:?}");
    // the last evaluation may overrun by at most one step attempt's Newton
    // iterations (3 stages, a few each)
    let spent = model.work_spent();
    assert!(
        (budget..budget + 200).contains(&spent),
        "{spent} Newton iterations against a budget of {budget}"
    );
    assert!(!fast.predicted.is_empty());
    assert!(fast.plan.iter().all(|u| (0.0..=1e-5).contains(u)));
    let mut slowed = Slowed(
        RichardsModel::new(&field, forecast),
        Duration::from_millis(20),
    );
    let slow = ZoneMpc::new(settings).solve(&mut slowed);
    assert_eq!(slow.status, SolveStatus::WorkBudget);
    assert_eq!(slow.plan, fast.plan);
    assert_eq!(slow.predicted, fast.predicted);
    assert_eq!(slow.iterations, fast.iterations);
    assert!(slow.solve_time > fast.solve_time);
    // the budget is what ended it
    let mut model = RichardsModel::new(&field, forecast);
    let free = ZoneMpc::new(MpcSettings {
        work_budget: None,
        ..settings
    })
    .solve(&mut model);
    assert_ne!(free.status, SolveStatus::WorkBudget);
    assert!(model.work_spent() > budget, "{}", model.work_spent());
}

/// A set cancel flag ends a solve as its budget would.
#[test]
fn a_cancelled_solve_stops_at_once() {
    use rootzone::control::RichardsModel;
    use rootzone::soil::{Field, FieldSettings, Texture};
    use rootzone::weather::{DRY_SCENARIO, WeatherSeries};
    use std::sync::Arc;
    use std::sync::atomic::AtomicBool;
    let weather = WeatherSeries::parse(DRY_SCENARIO, "weather-dry.csv").unwrap();
    let soil = Texture::Clay.parameters();
    let field = Field::new(FieldSettings {
        soil,
        ..FieldSettings::default()
    })
    .unwrap();
    let mut mpc = ZoneMpc::new(MpcSettings {
        zone: ZoneSettings::default_for(&soil),
        theta_r: soil.residual_water_content,
        theta_s: soil.saturated_water_content,
        time_budget: std::time::Duration::from_secs(30),
        ..MpcSettings::default()
    });
    mpc.set_cancel(Some(Arc::new(AtomicBool::new(true))));
    let mut model = RichardsModel::new(&field, &weather.steps()[..20]);
    let solution = mpc.solve(&mut model);
    assert!(solution.solve_time < std::time::Duration::from_secs(1));
    let SolveStatus::Fallback(reason) = &solution.status else {
        panic!("expected a fallback, got {:?}", solution.status);
    };
    assert!(reason.contains("time budget"), "{reason}");
    assert_eq!(solution.plan, vec![0.0; 20]);
}

/// The default zone of a soil is the sandy-loam head band in that soil
/// (MODEL.md §4), and [0.18, 0.23] for the sandy loam itself.
#[test]
fn default_zones_are_the_head_band_of_each_soil() {
    use rootzone::soil::{Texture, VanGenuchten};
    let sandy = ZoneSettings::default_for(&VanGenuchten::SANDY_LOAM);
    assert_eq!((sandy.low0, sandy.up0), (0.18, 0.23));
    // the band is what the heads give in sandy loam, to the rounding of 0.18/0.23
    let s = VanGenuchten::SANDY_LOAM;
    assert!((s.water_content(-0.43) - 0.18).abs() < 2e-3);
    assert!((s.water_content(-0.27) - 0.23).abs() < 2e-3);
    for texture in Texture::ALL {
        let soil = texture.parameters();
        let z = ZoneSettings::default_for(&soil);
        assert!(z.problem().is_none(), "{texture}");
        if texture != Texture::SandyLoam {
            // back through the inverse retention: the heads again
            assert!(
                (soil.pressure_head_at(z.low0) + 0.43).abs() < 1e-9,
                "{texture}"
            );
            assert!(
                (soil.pressure_head_at(z.up0) + 0.27).abs() < 1e-9,
                "{texture}"
            );
        }
        assert!(z.low0 < z.up0 && z.low0 > soil.residual_water_content);
    }
}

/// A model that is not smooth at the zero plan: that plan predicts θ just
/// below the zone, every other plan, however near, far above it, while its
/// Jacobian says that irrigation raises θ smoothly. No trial step can be
/// accepted. The run must see that the misses do not shrink with the step
/// and stop, not shrink the trust region from 0.5 to the step tolerance
/// (10 rejections, each a prediction).
struct Jumpy {
    evaluations: usize,
}

impl PredictionModel for Jumpy {
    fn predict(&mut self, plan: &[f64], out: &mut [f64]) -> Result<(), ModelError> {
        self.evaluations += 1;
        out.fill(if plan.iter().all(|&u| u == 0.0) {
            0.17
        } else {
            0.30
        });
        Ok(())
    }

    fn predict_with_jacobian(
        &mut self,
        plan: &[f64],
        out: &mut [f64],
        jac: &mut [f64],
    ) -> Result<(), ModelError> {
        self.predict(plan, out)?;
        let n = out.len();
        for k in 0..n {
            for j in 0..n {
                jac[k * n + j] = if j <= k { 2000.0 } else { 0.0 };
            }
        }
        Ok(())
    }
}

#[test]
fn a_run_on_a_model_that_jumps_stops_without_shrinking_to_the_tolerance() {
    let settings = MpcSettings {
        starts: 1,
        ..MpcSettings::default()
    };
    let mut model = Jumpy { evaluations: 0 };
    let sol = ZoneMpc::new(settings).solve(&mut model);
    assert_eq!(sol.status, SolveStatus::Converged);
    assert!(sol.plan.iter().all(|&u| u == 0.0), "{:?}", sol.plan);
    assert!(sol.predicted.iter().all(|&y| y == 0.17));
    // 0.5 · 4^−k < 1e-6 takes 10 rejections: the test stops at the second
    // rejection below a step of 1e-3 (the sixth and seventh)
    assert!(
        (2..=8).contains(&sol.iterations),
        "{} iterations, {} evaluations",
        sol.iterations,
        model.evaluations
    );
    assert_eq!(model.evaluations, sol.iterations + 1);
}

/// A forking Richards model whose first evaluation waits until its forks
/// have predicted, so that the solve adopts their predictions (the pool
/// would otherwise start them whenever it is free); it counts what it
/// adopted.
struct Forking {
    inner: rootzone::control::RichardsModel,
    forks_done: std::sync::Arc<std::sync::atomic::AtomicUsize>,
    waited: bool,
    adopted: usize,
}

/// A fork that says when it has predicted.
struct Fork(
    rootzone::control::RichardsModel,
    std::sync::Arc<std::sync::atomic::AtomicUsize>,
);

impl PredictionModel for Fork {
    fn predict(&mut self, plan: &[f64], out: &mut [f64]) -> Result<(), ModelError> {
        let r = self.0.predict(plan, out);
        self.1.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
        r
    }

    fn predict_with_jacobian(
        &mut self,
        plan: &[f64],
        out: &mut [f64],
        jac: &mut [f64],
    ) -> Result<(), ModelError> {
        self.0.predict_with_jacobian(plan, out, jac)
    }

    fn work_spent(&self) -> usize {
        self.0.work_spent()
    }
}

impl PredictionModel for Forking {
    fn predict(&mut self, plan: &[f64], out: &mut [f64]) -> Result<(), ModelError> {
        self.inner.predict(plan, out)
    }

    fn predict_with_jacobian(
        &mut self,
        plan: &[f64],
        out: &mut [f64],
        jac: &mut [f64],
    ) -> Result<(), ModelError> {
        if !self.waited {
            self.waited = true;
            let since = std::time::Instant::now();
            while self.forks_done.load(std::sync::atomic::Ordering::SeqCst) < 2
                && since.elapsed() < std::time::Duration::from_secs(60)
            {
                std::thread::sleep(std::time::Duration::from_millis(1));
            }
        }
        self.inner.predict_with_jacobian(plan, out, jac)
    }

    fn set_interrupt(&mut self, interrupt: Option<rootzone::soil::Interrupt>) {
        self.inner.set_interrupt(interrupt);
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

    fn monotone_in_supply(&self) -> bool {
        self.inner.monotone_in_supply()
    }

    fn fork(&self, interrupt: rootzone::soil::Interrupt) -> Option<Box<dyn PredictionModel>> {
        Some(Box::new(Fork(
            self.inner.forked(interrupt),
            self.forks_done.clone(),
        )))
    }

    fn book_work(&mut self, work: usize) {
        self.adopted += 1;
        self.inner.book_work(work);
    }
}

/// The constant starts a solve predicts on other threads while its warm
/// run goes on change nothing: on three textures in rain, warm-started,
/// with no work budget and with budgets that run out during the solve,
/// the solve that adopts its forks' predictions gives the plan, the
/// predictions, the objective, the status, the iterations and the work of
/// the solve that makes every prediction itself.
#[test]
fn predicting_the_first_starts_on_other_threads_changes_no_solve() {
    use rootzone::control::RichardsModel;
    use rootzone::soil::{Field, FieldSettings, Texture};
    use rootzone::weather::{RAIN_SCENARIO, WeatherSeries};
    use std::time::Duration;
    let weather = WeatherSeries::parse(RAIN_SCENARIO, "weather-rain.csv").unwrap();
    let mut adopted = 0;
    for texture in [Texture::SandyLoam, Texture::Loam, Texture::Clay] {
        let soil = texture.parameters();
        let field = Field::new(FieldSettings {
            soil,
            ..FieldSettings::default()
        })
        .unwrap();
        let forecast = &weather.steps()[15..35];
        let base = MpcSettings {
            zone: ZoneSettings::default_for(&soil),
            theta_r: soil.residual_water_content,
            theta_s: soil.saturated_water_content,
            time_budget: Duration::from_secs(3600),
            work_budget: None,
            ..MpcSettings::default()
        };
        // a first solve, so that the compared ones are warm-started
        let previous = ZoneMpc::new(base)
            .solve(&mut Slowed(
                RichardsModel::new(&field, forecast),
                Duration::ZERO,
            ))
            .plan;
        let mut alone = Slowed(RichardsModel::new(&field, forecast), Duration::ZERO);
        let mut free = ZoneMpc::new(base);
        free.remember(previous.clone());
        free.solve(&mut alone);
        let total = alone.work_spent();
        for budget in [None, Some(total), Some(total - 1), Some(3 * total / 4)] {
            let settings = MpcSettings {
                work_budget: budget,
                ..base
            };
            let mut one = ZoneMpc::new(settings);
            one.remember(previous.clone());
            let mut two = ZoneMpc::new(settings);
            two.remember(previous.clone());
            let mut alone = Slowed(RichardsModel::new(&field, forecast), Duration::ZERO);
            let expected = one.solve(&mut alone);
            let mut forking = Forking {
                inner: RichardsModel::new(&field, forecast),
                forks_done: Default::default(),
                waited: false,
                adopted: 0,
            };
            let got = two.solve(&mut forking);
            let case = format!("{texture}, budget {budget:?}");
            assert_eq!(got.plan, expected.plan, "{case}");
            assert_eq!(got.predicted, expected.predicted, "{case}");
            assert_eq!(got.status, expected.status, "{case}");
            assert_eq!(got.iterations, expected.iterations, "{case}");
            assert_eq!(
                got.objective.to_bits(),
                expected.objective.to_bits(),
                "{case}"
            );
            assert_eq!(forking.work_spent(), alone.work_spent(), "{case}");
            adopted += forking.adopted;
        }
    }
    // the forks' predictions were used, not only made
    assert!(adopted >= 6, "{adopted} predictions adopted");
}
