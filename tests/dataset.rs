//! Training data: range-keeping signals, noise bounds, determinism and the cache.

use rootzone::soil::FieldSettings;
use rootzone::surrogate::dataset::{
    DatasetError, DatasetSpec, Excitation, generate, load_or_generate, read_series,
};
use rootzone::weather::{DRY_SCENARIO, WeatherSeries};

fn spec(excitation: Excitation, samples: usize, seed: u64) -> DatasetSpec {
    DatasetSpec {
        name: "test".into(),
        excitation,
        samples,
        noise_fraction: 0.1,
        seed,
    }
}

fn dry() -> WeatherSeries {
    WeatherSeries::parse(DRY_SCENARIO, "dry").unwrap()
}

#[test]
fn signals_keep_the_output_in_range_and_cover_it() {
    let weather = dry();
    for (low, high) in [(0.12, 0.27), (0.21, 0.32), (0.29, 0.40)] {
        let s = generate(
            &spec(Excitation::MultiLevel { low, high }, 3000, 11),
            &FieldSettings::default(),
            weather.steps(),
        )
        .unwrap();
        let (inside, bins) = s.coverage(low, high);
        assert!(inside >= 0.95, "[{low}, {high}]: {inside} inside");
        assert!(bins >= 0.9, "[{low}, {high}]: {bins} of the range covered");
        assert!(s.irrigation.iter().all(|u| (0.0..=1e-5).contains(u)));
    }
    let s = generate(
        &spec(
            Excitation::Impulse {
                low: 0.12,
                high: 0.40,
            },
            4000,
            12,
        ),
        &FieldSettings::default(),
        weather.steps(),
    )
    .unwrap();
    let (inside, bins) = s.coverage(0.12, 0.40);
    assert!(inside >= 0.95 && bins >= 0.9, "{inside} {bins}");
    // impulses: most steps dry
    let dry_steps = s.irrigation.iter().filter(|u| **u == 0.0).count();
    assert!(dry_steps > s.len() / 2);
}

#[test]
fn output_noise_is_bounded_by_the_fraction_of_the_range() {
    let s = generate(
        &spec(
            Excitation::MultiLevel {
                low: 0.21,
                high: 0.32,
            },
            1000,
            3,
        ),
        &FieldSettings::default(),
        dry().steps(),
    )
    .unwrap();
    let (min, max) = s
        .water_content
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| {
            (a.min(v), b.max(v))
        });
    let bound = 0.1 * (max - min);
    let mut largest: f64 = 0.0;
    for (m, y) in s.measured.iter().zip(&s.water_content) {
        assert!((m - y).abs() <= bound + 1e-15);
        largest = largest.max((m - y).abs());
    }
    assert!(
        largest > 0.8 * bound,
        "noise should fill its bound: {largest} of {bound}"
    );
}

#[test]
fn generation_is_seeded_and_cached() {
    let weather = dry();
    let settings = FieldSettings::default();
    let a = spec(
        Excitation::MultiLevel {
            low: 0.12,
            high: 0.27,
        },
        500,
        5,
    );
    let b = spec(
        Excitation::MultiLevel {
            low: 0.12,
            high: 0.27,
        },
        500,
        6,
    );
    let first = generate(&a, &settings, weather.steps()).unwrap();
    assert_eq!(first, generate(&a, &settings, weather.steps()).unwrap());
    assert_ne!(
        first.irrigation,
        generate(&b, &settings, weather.steps()).unwrap().irrigation
    );

    let dir = tempfile::tempdir().unwrap();
    let cached =
        load_or_generate(&a, "sandy-loam", &settings, weather.steps(), dir.path()).unwrap();
    let path = dir.path().join(a.cache_name("sandy-loam", &settings));
    assert!(path.exists());
    // Round trip: reading the file gives the generated series (to print precision).
    let back = read_series(&path).unwrap();
    assert_eq!(back.len(), cached.len());
    for k in 0..back.len() {
        assert!((back.water_content[k] - first.water_content[k]).abs() < 1e-12);
        assert!((back.irrigation[k] - first.irrigation[k]).abs() <= 1e-15 * first.irrigation[k]);
        assert!((back.et0[k] - first.et0[k]).abs() <= 1e-15 * first.et0[k]);
        assert!((back.rain[k] - first.rain[k]).abs() <= 1e-15 * first.rain[k]);
    }
    // The second call reads the cache: a marker written into it comes back.
    let text = std::fs::read_to_string(&path).unwrap().replacen(
        &format!("{:e}", first.water_content[0]),
        "0.5",
        1,
    );
    std::fs::write(&path, text).unwrap();
    let again = load_or_generate(&a, "sandy-loam", &settings, weather.steps(), dir.path()).unwrap();
    assert_eq!(again.water_content[0], 0.5);
    // Another seed is another file.
    assert_ne!(
        a.cache_name("sandy-loam", &settings),
        b.cache_name("sandy-loam", &settings)
    );
    // A corrupt cache entry is an error naming file and line.
    std::fs::write(
        &path,
        "irrigation_m_per_s,rain_m_per_s,et0_m_per_s,theta,theta_measured\n1,0,0,2,3\n1,0,0,x,3\n",
    )
    .unwrap();
    match read_series(&path) {
        Err(DatasetError::Malformed { line, .. }) => assert_eq!(line, 3),
        other => panic!("expected a malformed-file error, got {other:?}"),
    }
}

#[test]
fn the_training_weather_spans_et0_from_day_to_day_and_brings_rain() {
    // 120 days of the whole-range impulse set
    let s = generate(
        &spec(
            Excitation::Impulse {
                low: 0.12,
                high: 0.40,
            },
            1440,
            21,
        ),
        &FieldSettings::default(),
        dry().steps(),
    )
    .unwrap();
    let dt = 7200.0;
    // recording starts 24 steps (two days) in: days are whole 12-step blocks
    let days: Vec<f64> = s
        .et0
        .chunks_exact(12)
        .map(|d| d.iter().map(|e| e * dt * 1e3).sum::<f64>())
        .collect();
    assert_eq!(days.len(), 120);
    assert!(
        days.iter().all(|d| (0.5 - 1e-9..=8.0 + 1e-9).contains(d)),
        "{days:?}"
    );
    let (lo, hi) = days
        .iter()
        .fold((f64::INFINITY, 0.0f64), |(a, b), &d| (a.min(d), b.max(d)));
    assert!(lo < 1.5 && hi > 7.0, "daily totals {lo}..{hi}");
    // the diurnal shape of weather-dry: night steps have none, noon most
    for d in s.et0.chunks_exact(12) {
        assert_eq!(d[0], 0.0);
        assert!(d[5] > d[4] && d[4] > d[3] && d[3] > 0.0);
    }
    // rain events of 1–20 mm, a few in 120 days, counted in the supply
    let events = s
        .rain
        .iter()
        .zip(std::iter::once(&0.0).chain(&s.rain))
        .filter(|(r, before)| **r > 0.0 && **before == 0.0)
        .count();
    assert!((10..=80).contains(&events), "{events} rain events");
    assert!(s.rain.iter().all(|r| *r * dt * 1e3 <= 20.0 + 1e-9));
    for ((total, u), p) in s.supply().iter().zip(&s.irrigation).zip(&s.rain) {
        assert_eq!(*total, u + p);
    }
}
