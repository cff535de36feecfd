//! Van Genuchten–Mualem hydraulics and Feddes uptake against closed forms and
//! finite differences.

use rootzone::soil::{Feddes, Texture, VanGenuchten};

const HEADS: [f64; 9] = [-150.0, -30.0, -5.0, -1.0, -0.4, -0.13, -0.05, -0.01, -1e-4];

fn central(f: impl Fn(f64) -> f64, x: f64) -> f64 {
    let step = 1e-6 * x.abs().max(1e-3);
    (f(x + step) - f(x - step)) / (2.0 * step)
}

fn relative(a: f64, b: f64) -> f64 {
    (a - b).abs() / a.abs().max(b.abs()).max(1e-300)
}

#[test]
fn saturated_at_zero_head_and_residual_when_dry() {
    for texture in Texture::ALL {
        let soil = texture.parameters();
        assert_eq!(soil.water_content(0.0), soil.saturated_water_content);
        assert_eq!(soil.water_content(0.3), soil.saturated_water_content);
        assert_eq!(soil.conductivity(0.0), soil.saturated_conductivity);
        // Se ~ (α|h|)^(1−n): for n = 1.09 only astronomically dry heads come near θr.
        let dry = soil.water_content(-1e200);
        assert!(dry - soil.residual_water_content < 1e-6, "{texture}: {dry}");
        assert!(dry >= soil.residual_water_content);
        assert!(soil.conductivity(-1e200) < 1e-20 * soil.saturated_conductivity);
    }
}

#[test]
fn water_content_and_conductivity_decrease_with_suction() {
    for texture in Texture::ALL {
        let soil = texture.parameters();
        for pair in HEADS.windows(2) {
            assert!(soil.water_content(pair[0]) < soil.water_content(pair[1]));
            assert!(soil.conductivity(pair[0]) < soil.conductivity(pair[1]));
        }
    }
}

#[test]
fn conductivity_matches_the_textbook_mualem_form() {
    // K = Ks·Se^½·[1 − (1 − Se^(1/m))^m]², evaluated literally.
    for texture in Texture::ALL {
        let soil = texture.parameters();
        let m = 1.0 - 1.0 / soil.n;
        for h in HEADS {
            let se = soil.effective_saturation(h);
            let literal = soil.saturated_conductivity
                * se.sqrt()
                * (1.0 - (1.0 - se.powf(1.0 / m)).powf(m)).powi(2);
            assert!(
                relative(soil.conductivity(h), literal) < 1e-6,
                "{texture} h={h}"
            );
        }
    }
}

#[test]
fn capacity_matches_model_formula_and_finite_differences() {
    for texture in Texture::ALL {
        let soil = texture.parameters();
        let (a, n) = (soil.alpha, soil.n);
        let m = 1.0 - 1.0 / n;
        for h in HEADS {
            let x = -a * h;
            let fd_step = 1e-5 * h.abs();
            let formula = (soil.saturated_water_content - soil.residual_water_content)
                * a
                * n
                * m
                * x.powf(n - 1.0)
                * (1.0 + x.powf(n)).powf(-m - 1.0);
            let c = soil.capacity(h);
            assert!(
                relative(c, formula) < 1e-10,
                "{texture} h={h}: {c} vs {formula}"
            );
            // Differentiate Se rather than θ = θr + …: far from round-off when dry.
            let range = soil.saturated_water_content - soil.residual_water_content;
            if h > -1e-3 {
                // Se − 1 ~ 1e-8 here: a difference quotient of Se is round-off.
                continue;
            }
            let se = |h| soil.effective_saturation(h);
            let fd = range * (se(h + fd_step) - se(h - fd_step)) / (2.0 * fd_step);
            assert!(relative(c, fd) < 1e-5, "{texture} h={h}: {c} vs {fd}");
        }
    }
}

#[test]
fn conductivity_derivative_matches_finite_differences() {
    for texture in Texture::ALL {
        let soil = texture.parameters();
        for h in HEADS {
            let dk = soil.state(h).conductivity_derivative;
            let fd = central(|h| soil.conductivity(h), h);
            assert!(relative(dk, fd) < 1e-5, "{texture} h={h}: {dk} vs {fd}");
        }
    }
}

#[test]
fn storage_inverse_round_trips() {
    for texture in Texture::ALL {
        let soil = texture.parameters();
        for h in HEADS.into_iter().chain([0.0, 0.02, 1.5]) {
            let w = soil.storage(h);
            let back = soil.pressure_head_from_storage(w);
            // The contract: |w(h) − w| ≤ 1e-12, so h within 1e-12/(C + Ss).
            let slack = 2e-12 / (soil.capacity(h) + soil.specific_storage) + 1e-12 * h.abs();
            assert!(
                (soil.storage(back) - w).abs() <= 1e-12,
                "{texture}: {h} -> {back}"
            );
            assert!((back - h).abs() < slack, "{texture}: {h} -> {w} -> {back}");
        }
    }
}

#[test]
fn retention_inverse_round_trips() {
    let soil = VanGenuchten::SANDY_LOAM;
    for h in HEADS {
        let back = soil.pressure_head_at(soil.water_content(h));
        assert!(relative(back, h) < 1e-9, "{h} -> {back}");
    }
    assert_eq!(soil.pressure_head_at(soil.saturated_water_content), 0.0);
    // MODEL.md §1: the initial condition h = −0.2 m gives θ = 0.2659.
    assert!((soil.water_content(-0.2) - 0.2659).abs() < 5e-5);
}

#[test]
fn texture_names_round_trip_and_unknown_names_are_rejected() {
    for texture in Texture::ALL {
        assert_eq!(texture.name().parse::<Texture>().unwrap(), texture);
        assert!(texture.parameters().validate().is_ok());
    }
    assert_eq!("Sandy_Loam".parse::<Texture>().unwrap(), Texture::SandyLoam);
    let err = "peat".parse::<Texture>().unwrap_err();
    assert!(err.to_string().contains("peat") && err.to_string().contains("sandy-loam"));
    // Carsel & Parrish sandy loam: Ks = 106.1 cm/day; MODEL.md rounds to 1.23e-5 m/s.
    let ks = Texture::SandyLoam.parameters().saturated_conductivity;
    assert!((ks - 106.1 / 100.0 / 86400.0).abs() / ks < 0.002);
    assert!((Texture::Loam.parameters().alpha - 3.6).abs() < 1e-12);
}

#[test]
fn invalid_soils_are_rejected() {
    let soil = VanGenuchten::SANDY_LOAM;
    for bad in [
        VanGenuchten { n: 1.0, ..soil },
        VanGenuchten {
            residual_water_content: 0.5,
            ..soil
        },
        VanGenuchten {
            saturated_conductivity: -1.0,
            ..soil
        },
        VanGenuchten {
            alpha: f64::NAN,
            ..soil
        },
        VanGenuchten {
            specific_storage: 0.0,
            ..soil
        },
    ] {
        assert!(bad.validate().is_err(), "{bad:?}");
    }
}

#[test]
fn feddes_stress_has_the_trapezoid_shape() {
    let f = Feddes::GRASS;
    assert_eq!(f.stress(-0.05), 0.0);
    assert_eq!(f.stress(-0.10), 0.0);
    assert!((f.stress(-0.175) - 0.5).abs() < 1e-12);
    assert_eq!(f.stress(-0.25), 1.0);
    assert_eq!(f.stress(-1.0), 1.0);
    assert_eq!(f.stress(-2.0), 1.0);
    assert!((f.stress(-41.0) - 0.5).abs() < 1e-12);
    assert_eq!(f.stress(-80.0), 0.0);
    assert_eq!(f.stress(-100.0), 0.0);
    for h in [-0.15, -0.2, -10.0, -60.0] {
        let (_, d) = f.stress_and_derivative(h);
        let fd = central(|h| f.stress(h), h);
        assert!((d - fd).abs() < 1e-8, "h={h}: {d} vs {fd}");
    }
    assert!(Feddes { h2: 0.0, ..f }.validate().is_err());
}
