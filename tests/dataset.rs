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
        "irrigation_m_per_s,theta,theta_measured\n1,2,3\n1,x,3\n",
    )
    .unwrap();
    match read_series(&path) {
        Err(DatasetError::Malformed { line, .. }) => assert_eq!(line, 3),
        other => panic!("expected a malformed-file error, got {other:?}"),
    }
}
