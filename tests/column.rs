//! The discretised column: geometry, the analytic derivatives against finite
//! differences, and the conservation identity of its rates.

use rootzone::soil::{Column, Crop, Derivatives, Evaluation, Forcing, VanGenuchten};

fn column() -> Column {
    Column::new(VanGenuchten::SANDY_LOAM, Crop::default(), 0.5, 26).unwrap()
}

/// Heads from `top` to `bottom`, with a wiggle so neighbours differ both ways.
fn heads(column: &Column, top: f64, bottom: f64) -> Vec<f64> {
    let n = column.cells();
    (0..n)
        .map(|i| {
            let f = i as f64 / (n - 1) as f64;
            top + (bottom - top) * f + 0.03 * (i as f64 * 1.7).sin() * top.abs()
        })
        .collect()
}

/// All rates as one vector: cells then amounts.
fn rates(column: &Column, h: &[f64], forcing: &Forcing) -> Vec<f64> {
    let mut e = Evaluation::new(column.cells());
    column.evaluate(h, forcing, &mut e, Derivatives::Omitted);
    e.storage.iter().copied().chain(e.amounts).collect()
}

/// d(rates)/d(heads) from the analytic bands, as a dense matrix (rows: cells, amounts).
fn analytic(column: &Column, h: &[f64], forcing: &Forcing) -> Vec<Vec<f64>> {
    let n = column.cells();
    let mut e = Evaluation::new(n);
    column.evaluate(h, forcing, &mut e, Derivatives::Included);
    let mut j = vec![vec![0.0; n]; n + 4];
    for i in 0..n {
        if i > 0 {
            j[i][i - 1] = e.lower[i];
        }
        j[i][i] = e.diagonal[i];
        if i + 1 < n {
            j[i][i + 1] = e.upper[i];
        }
        j[n + 2][i] = e.uptake_gradient[i];
    }
    j[n][0] = e.top_gradient;
    j[n + 3][0] = -e.top_gradient;
    j[n + 1][n - 1] = e.bottom_gradient;
    j
}

fn assert_derivatives_match(h: &[f64], forcing: Forcing) {
    let column = column();
    let j = analytic(&column, h, &forcing);
    let scale = j.iter().flatten().fold(0.0f64, |m, v| m.max(v.abs()));
    for c in 0..h.len() {
        let step = 1e-5 * h[c].abs();
        let mut plus = h.to_vec();
        plus[c] += step;
        let mut minus = h.to_vec();
        minus[c] -= step;
        let (rp, rm) = (
            rates(&column, &plus, &forcing),
            rates(&column, &minus, &forcing),
        );
        for r in 0..rp.len() {
            let fd = (rp[r] - rm[r]) / (2.0 * step);
            let a = j[r][c];
            assert!(
                (a - fd).abs() <= 1e-6 * scale + 1e-5 * a.abs(),
                "d rate[{r}]/d h[{c}] = {a:e}, finite difference {fd:e} (scale {scale:e})"
            );
        }
    }
}

#[test]
fn geometry_follows_model_md() {
    let c = column();
    assert!((c.cell_thickness() - 0.5 / 26.0).abs() < 1e-15);
    assert_eq!(c.root_cells(), 7);
    assert_eq!(c.sensor_cell(), 6);
    assert!((c.cell_centre(6) - 0.125).abs() < 1e-3);
}

#[test]
fn invalid_geometry_is_rejected() {
    let soil = VanGenuchten::SANDY_LOAM;
    assert!(Column::new(soil, Crop::default(), 0.5, 1).is_err());
    assert!(Column::new(soil, Crop::default(), -1.0, 26).is_err());
    assert!(Column::new(soil, Crop::default(), 0.1, 26).is_err());
    let shallow = Crop {
        rooting_depth: 0.001,
        ..Crop::default()
    };
    assert!(Column::new(soil, shallow, 0.5, 26).is_err());
}

#[test]
fn derivatives_match_finite_differences_in_unsaturated_soil() {
    let column = column();
    let forcing = Forcing {
        irrigation: 3e-7,
        reference_et: 5e-8,
        precipitation: 1e-7,
    };
    // Heads across the Feddes plateau and both ramps, uptake active.
    assert_derivatives_match(&heads(&column, -3.0, -0.4), forcing);
    assert_derivatives_match(&heads(&column, -0.18, -0.3), forcing);
    assert_derivatives_match(&heads(&column, -30.0, -5.0), forcing);
}

#[test]
fn derivatives_match_finite_differences_when_infiltration_is_capped() {
    let column = column();
    let h = heads(&column, -0.02, -0.2);
    let forcing = Forcing {
        irrigation: 5e-5,
        reference_et: 0.0,
        precipitation: 0.0,
    };
    assert!(
        rates(&column, &h, &forcing)[column.cells() + 3] > 0.0,
        "expected runoff"
    );
    assert_derivatives_match(&h, forcing);
}

#[test]
fn rates_conserve_water() {
    // d/dt(Σ w·dz) = infiltration − drainage − uptake, and supply = infiltration + runoff.
    let column = column();
    let n = column.cells();
    let dz = column.cell_thickness();
    for (top, bottom, forcing) in [
        (
            -3.0,
            -0.4,
            Forcing {
                irrigation: 3e-7,
                reference_et: 5e-8,
                precipitation: 0.0,
            },
        ),
        (
            -0.02,
            -0.2,
            Forcing {
                irrigation: 5e-5,
                reference_et: 1e-8,
                precipitation: 1e-6,
            },
        ),
        (
            -90.0,
            -50.0,
            Forcing {
                irrigation: 0.0,
                reference_et: 1e-7,
                precipitation: 0.0,
            },
        ),
    ] {
        let r = rates(&column, &heads(&column, top, bottom), &forcing);
        let storage_rate: f64 = r[..n].iter().sum::<f64>() * dz;
        let balance = r[n] - r[n + 1] - r[n + 2];
        let scale = r[n..].iter().map(|v| v.abs()).sum::<f64>().max(1e-12);
        assert!(
            (storage_rate - balance).abs() <= 1e-14 * scale,
            "{storage_rate:e} vs {balance:e}"
        );
        let supply = forcing.irrigation + forcing.precipitation;
        assert!((r[n] + r[n + 3] - supply).abs() <= 1e-18 + 1e-14 * supply);
    }
}
