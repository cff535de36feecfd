//! The shipped surrogates know the weather: a forecast of more ET0 makes
//! them predict a drier root zone, by about as much as the Richards model
//! (the simulator) says, from the same history.

use rootzone::soil::{Field, FieldSettings, Forcing};
use rootzone::surrogate::evaluate::WINDOW;
use rootzone::surrogate::{ModelFile, Past};
use rootzone::weather::{DRY_SCENARIO, WeatherSeries, mm_to_rate};

const DT: f64 = 7200.0;
const AHEAD: usize = 20;

/// The dry scenario's ET0 of step k scaled to `daily` mm/day, as a rate.
fn et0(dry: &WeatherSeries, k: usize, daily: f64) -> f64 {
    let w = dry.steps()[k % 12];
    mm_to_rate(w.et0_mm * daily / 4.0, DT)
}

/// A field after a 30-step history at 4 mm/day with pulses of irrigation:
/// the field, and the window of its last 20 steps (supply, θ, ET0).
fn history(dry: &WeatherSeries) -> (Field, Vec<f64>, Vec<f64>, Vec<f64>) {
    let mut field = Field::new(FieldSettings::default()).unwrap();
    let (mut u, mut y, mut e) = (Vec::new(), Vec::new(), Vec::new());
    for k in 0..30 {
        let rate = if k % 7 == 3 { 3e-6 } else { 0.0 };
        let et = et0(dry, k, 4.0);
        let report = field
            .step(Forcing {
                irrigation: rate,
                reference_et: et,
                precipitation: 0.0,
            })
            .unwrap();
        u.push(rate);
        y.push(report.water_content);
        e.push(et);
    }
    let n = u.len();
    (
        field,
        u[n - WINDOW..].to_vec(),
        y[n - WINDOW..].to_vec(),
        e[n - WINDOW..].to_vec(),
    )
}

#[test]
fn more_forecast_et0_predicts_a_drier_root_zone_as_the_richards_model_does() {
    let dry = WeatherSeries::parse(DRY_SCENARIO, "dry").unwrap();
    let models = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("models");
    for name in ["two-layer.json", "single-lstm.json"] {
        let file = ModelFile::load(&models.join(name)).unwrap();
        let at = |daily: f64| {
            // the simulator: the same history, then 20 dry steps at `daily`
            let (mut field, past_u, past_y, past_e) = history(&dry);
            let mut simulated = 0.0;
            for k in 30..30 + AHEAD {
                simulated = field
                    .step(Forcing {
                        irrigation: 0.0,
                        reference_et: et0(&dry, k, daily),
                        precipitation: 0.0,
                    })
                    .unwrap()
                    .water_content;
            }
            // the network: the same window and ET0 forecast
            let future_e: Vec<f64> = (30..30 + AHEAD).map(|k| et0(&dry, k, daily)).collect();
            let mut out = vec![0.0; AHEAD];
            file.predictor()
                .predict(
                    Past {
                        u: &past_u,
                        y: &past_y,
                        et0: &past_e,
                    },
                    &[0.0; AHEAD],
                    &future_e,
                    0.0,
                    &mut out,
                )
                .unwrap();
            (simulated, out[AHEAD - 1])
        };
        let (sim_low, net_low) = at(1.0);
        let (sim_high, net_high) = at(7.0);
        let sim = sim_low - sim_high;
        let net = net_low - net_high;
        // 6 mm/day more over 40 h takes about 10 mm from the root zone
        assert!(sim > 0.005, "the simulator's difference {sim}");
        eprintln!("{name}: Richards {sim:.4}, network {net:.4}");
        assert!(
            (net - sim).abs() <= 0.35 * sim,
            "{name}: 1 → 7 mm/day lowers θ after 40 h by {net:.4} (network) against {sim:.4} (Richards)"
        );
    }
}
