//! Weather scenarios and forecast error (MODEL.md §2).

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rootzone::weather::{DRY_SCENARIO, RAIN_SCENARIO, WeatherSeries, mm_to_rate, rate_to_mm};

#[test]
fn shipped_scenarios_match_their_description() {
    let dry = WeatherSeries::parse(DRY_SCENARIO, "dry").unwrap();
    let rain = WeatherSeries::parse(RAIN_SCENARIO, "rain").unwrap();
    assert_eq!(dry.len(), 96);
    assert_eq!(rain.len(), 96);
    // weather-dry: 4 mm/day ET0, no rain.
    for day in dry.steps().chunks(12) {
        let et: f64 = day.iter().map(|s| s.et0_mm).sum();
        assert!((et - 4.0).abs() < 1e-3, "{et}");
    }
    assert!(dry.steps().iter().all(|s| s.precip_mm == 0.0));
    // weather-rain: 19 mm of rain in all, ET0 between 2.5 and 4.5 mm/day.
    let rain_total: f64 = rain.steps().iter().map(|s| s.precip_mm).sum();
    assert!((rain_total - 19.0).abs() < 1e-6, "{rain_total}");
    for day in rain.steps().chunks(12) {
        let et: f64 = day.iter().map(|s| s.et0_mm).sum();
        assert!((2.5 - 1e-6..=4.5 + 1e-6).contains(&et), "{et}");
    }
    assert_eq!(dry.get(1).unwrap().start_hour, 2.0);
}

#[test]
fn units_round_trip() {
    assert!((mm_to_rate(1.0, 7200.0) - 1e-3 / 7200.0).abs() < 1e-20);
    assert!((rate_to_mm(mm_to_rate(3.7, 7200.0), 7200.0) - 3.7).abs() < 1e-12);
}

#[test]
fn forecast_error_is_bounded_seeded_and_exact_at_zero() {
    let rain = WeatherSeries::parse(RAIN_SCENARIO, "rain").unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let exact = rain.forecast(10, 20, 0.0, &mut rng);
    assert_eq!(exact.as_slice(), &rain.steps()[10..30]);
    let a = rain.forecast(10, 20, 0.2, &mut ChaCha8Rng::seed_from_u64(5));
    let b = rain.forecast(10, 20, 0.2, &mut ChaCha8Rng::seed_from_u64(5));
    assert_eq!(a, b);
    let mut perturbed = 0;
    for (f, t) in a.iter().zip(&rain.steps()[10..30]) {
        assert!(f.et0_mm >= 0.8 * t.et0_mm - 1e-12 && f.et0_mm <= 1.2 * t.et0_mm + 1e-12);
        assert!(
            f.precip_mm >= 0.8 * t.precip_mm - 1e-12 && f.precip_mm <= 1.2 * t.precip_mm + 1e-12
        );
        perturbed += usize::from(f.et0_mm != t.et0_mm);
    }
    assert!(perturbed > 5);
    // Past the end the last step repeats.
    let tail = rain.forecast(90, 10, 0.0, &mut rng);
    assert_eq!(tail[9], rain.steps()[95]);
}

#[test]
fn malformed_weather_names_line_and_value() {
    let cases = [
        (
            "step,start_hour,et0_mm,precip_mm\n0,0,0.1,0\n1,2,-0.1,0\n",
            3,
            "-0.1",
        ),
        (
            "step,start_hour,et0_mm,precip_mm\n0,0,0.1,0\n1,2,x,0\n",
            3,
            "'x'",
        ),
        (
            "step,start_hour,et0_mm,precip_mm\n0,0,0.1,0\n5,2,0.1,0\n",
            3,
            "out of order",
        ),
        (
            "step,start_hour,et0\n0,0,0.1\n",
            1,
            "missing column 'et0_mm'",
        ),
        (
            "step,start_hour,et0_mm,precip_mm\n0,0,inf,0\n",
            2,
            "not finite",
        ),
        // the API's rates over a 2-h step: ET0 at most 2 mm/h (4 mm), rain
        // at most 400 mm/h (800 mm)
        (
            "step,start_hour,et0_mm,precip_mm\n0,0,4,800\n1,2,4.01,0\n",
            3,
            "et0_mm = 4.01 exceeds 4 mm",
        ),
        (
            "step,start_hour,et0_mm,precip_mm\n0,0,4,800\n1,2,0,800.5\n",
            3,
            "precip_mm = 800.5 exceeds 800 mm",
        ),
    ];
    for (text, line, needle) in cases {
        let err = WeatherSeries::parse(text, "w.csv").unwrap_err();
        assert_eq!(err.line, line, "{err}");
        let message = err.to_string();
        assert!(message.starts_with(&format!("w.csv:{line}:")), "{message}");
        assert!(message.contains(needle), "{message}");
    }
    assert!(WeatherSeries::parse("step,start_hour,et0_mm,precip_mm\n", "w.csv").is_err());
    // the bounds themselves are accepted
    let edge = WeatherSeries::parse("step,start_hour,et0_mm,precip_mm\n0,0,4,800\n", "w.csv")
        .expect("the largest amounts are valid");
    assert_eq!(edge.steps()[0].et0_mm, 4.0);
    assert_eq!(edge.steps()[0].precip_mm, 800.0);
}
