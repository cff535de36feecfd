//! The own SDIRK4 integrator against an independent one: the same column as a
//! DAE through diffsol's BDF, on an unsaturated schedule where both work.

use rootzone::soil::diffsol_dae::DaeIntegrator;
use rootzone::soil::{ColumnState, Field, FieldSettings, Tolerances};
use rootzone::weather::{DRY_SCENARIO, WeatherSeries};

#[test]
fn own_integrator_agrees_with_diffsol_bdf() {
    let weather = WeatherSeries::parse(DRY_SCENARIO, "dry").unwrap();
    let tight = Tolerances {
        relative: 1e-8,
        absolute: 1e-10,
    };
    let settings = FieldSettings {
        tolerances: tight,
        ..FieldSettings::default()
    };
    let mut field = Field::new(settings).unwrap();
    let mut dae = DaeIntegrator::new(*field.column(), tight).unwrap();
    let mut state: ColumnState = field.state().clone();
    let soil = settings.soil;
    let dz = field.column().cell_thickness();
    for step in 0..24 {
        let u = if (3..6).contains(&(step % 12)) {
            3e-7
        } else {
            0.0
        };
        let forcing = weather.get(step).unwrap().forcing(u, 7200.0);
        field.step(forcing).unwrap();
        dae.advance(&mut state, step as f64 * 7200.0, 7200.0, forcing)
            .unwrap();
        let theirs = soil.water_content(state.heads[6]);
        assert!(
            (field.water_content() - theirs).abs() < 2e-6,
            "step {step}: {} vs {theirs}",
            field.water_content()
        );
        for k in 0..4 {
            let (a, b) = (field.state().amounts[k], state.amounts[k]);
            assert!(
                (a - b).abs() < 1e-7 + 1e-5 * a.abs(),
                "amount {k}: {a} vs {b}"
            );
        }
    }
    // diffsol's DAE conserves water too: Σ w·dz − I + D + U is invariant.
    // Its heads meet the algebraic constraint w = θ(h) + Ss·h only to its
    // Newton tolerance, so the storage recomputed from them is off by a
    // little more than round-off (measured 1.05e-9 m over the 24 steps).
    let storage: f64 = state.heads.iter().map(|&h| soil.storage(h)).sum::<f64>() * dz;
    let initial = 26.0 * soil.storage(-0.2) * dz;
    let [i, d, u, _] = state.amounts;
    let off = storage - initial - (i - d - u);
    assert!(off.abs() < 2e-9, "{off:e}");
}
