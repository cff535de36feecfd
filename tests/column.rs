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

/// The flux through the face between a saturated cell (h = 0) and the cell
/// below it at `below`, relative to Ks, from the column's own rates: the
/// last cell's rate is (q₂₅ − q₂₆)/dz with q₂₆ = K(h₂₅) the drainage.
fn face_flux_below_saturation(column: &Column, below: f64) -> f64 {
    let n = column.cells();
    let mut h = vec![0.0; n];
    h[n - 1] = below;
    let forcing = Forcing {
        irrigation: 0.0,
        reference_et: 0.0,
        precipitation: 0.0,
    };
    let r = rates(column, &h, &forcing);
    (r[n - 1] * column.cell_thickness() + r[n + 1]) / column.soil().saturated_conductivity
}

/// Heads of the lower cell from −1e2 m to −1e-18 m, 200 per decade, then
/// saturated heads up to dz: the face flux along them.
fn face_flux_curve(column: &Column) -> Vec<(f64, f64)> {
    let below = (0..4000).map(|k| -(10f64.powf(2.0 - k as f64 * 0.005)));
    let above = (0..=100).map(|k| k as f64 * 0.01 * column.cell_thickness());
    below
        .chain(above)
        .map(|h| (h, face_flux_below_saturation(column, h)))
        .collect()
}

/// Why the finest textures are slow in rain (ARCHITECTURE.md, "Ponding on
/// the finer textures"): MODEL.md's face flux K̄·(Δh/dz + 1) with the
/// arithmetic mean K̄ is not monotone in the lower cell's head when n is
/// near 1. Below a saturated cell it falls from Ks at h = 0⁻ (K's cusp) to
/// a minimum before the gradient makes it rise, so a flux between that
/// minimum and Ks passes the face at three heads of the lower cell: the
/// stage equations of an implicit step then have several solutions per
/// cell. The minima (q/Ks) are those of an independent evaluation of the
/// same formulas (a Python scan over the same heads): clay 0.6428, silty
/// clay 0.6537, sandy clay 0.8162, silty clay loam 0.8590, clay loam
/// 0.9116, loam 0.9930; for sandy loam and the coarser textures it stays
/// above 1 − 1e-6.
#[test]
fn below_a_saturated_cell_one_flux_passes_at_three_heads_when_n_is_near_one() {
    use rootzone::soil::Texture;
    let lowest = |texture: Texture| {
        let column = Column::new(texture.parameters(), Crop::default(), 0.5, 26).unwrap();
        face_flux_curve(&column)
            .into_iter()
            .filter(|&(h, _)| h < 0.0)
            .map(|(_, q)| q)
            .fold(f64::INFINITY, f64::min)
    };
    for (texture, expected) in [
        (Texture::Clay, 0.6428),
        (Texture::SiltyClay, 0.6537),
        (Texture::SandyClay, 0.8162),
        (Texture::SiltyClayLoam, 0.8590),
        (Texture::ClayLoam, 0.9116),
        (Texture::Loam, 0.9930),
    ] {
        let q = lowest(texture);
        assert!(
            (q - expected).abs() < 1e-3,
            "{texture}: the face flux's minimum is {q:.4} Ks, expected {expected}"
        );
    }
    for texture in [Texture::Sand, Texture::LoamySand, Texture::SandyLoam] {
        let q = lowest(texture);
        assert!(q > 1.0 - 1e-6, "{texture}: minimum {q} Ks");
    }
    // The case that costs the most (tests/textures.rs): clay under 0.935 Ks.
    // Three heads carry it; above saturation the one of K = Ks,
    // h = (1 − 0.935)·dz. Sandy loam carries it at that head only.
    let crossings = |texture: Texture, flux: f64| {
        let column = Column::new(texture.parameters(), Crop::default(), 0.5, 26).unwrap();
        let curve = face_flux_curve(&column);
        let heads: Vec<f64> = curve
            .windows(2)
            .filter(|w| (w[0].1 - flux) * (w[1].1 - flux) < 0.0)
            .map(|w| 0.5 * (w[0].0 + w[1].0))
            .collect();
        (heads, column.cell_thickness())
    };
    let (clay, dz) = crossings(Texture::Clay, 0.935);
    assert_eq!(clay.len(), 3, "clay: {clay:?}");
    assert!(
        clay[0] < -1e-4 && clay[1] < 0.0 && clay[1] > -1e-6,
        "{clay:?}"
    );
    assert!((clay[2] - 0.065 * dz).abs() < 0.01 * dz, "{clay:?}");
    let (sandy_loam, dz) = crossings(Texture::SandyLoam, 0.935);
    assert_eq!(sandy_loam.len(), 1, "sandy loam: {sandy_loam:?}");
    assert!((sandy_loam[0] - 0.065 * dz).abs() < 0.01 * dz);
}
