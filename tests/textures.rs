//! Every texture, every allowed input: the simulator's matrix of issue 14.
//!
//! For each of the 12 Carsel & Parrish textures, both weather files and six
//! irrigation schedules over 60 steps, a run either finishes or stops with an
//! `IntegrationError` that names the sampling step, the time, the smallest
//! step size and the cell, within the work limits (it never loops). Either
//! way the water balance closes to 1e-9 m, with runoff booked apart.

use rootzone::soil::{
    FailureKind, Field, FieldSettings, Forcing, IntegrationError, Texture, WorkLimits,
};
use rootzone::weather::{DRY_SCENARIO, RAIN_SCENARIO, WeatherSeries, mm_to_rate};

const STEPS: usize = 60;
const STEP_SECONDS: f64 = 7200.0;
const U_MAX: f64 = 1e-5;

/// The schedules of the issue: irrigation [m/s] at step k, and extra rain [mm].
#[derive(Debug, Clone, Copy)]
enum Schedule {
    None,
    Constant(f64),
    MaxForTwoSteps,
    RainStep,
}

impl Schedule {
    const ALL: [Schedule; 6] = [
        Schedule::None,
        Schedule::Constant(1e-7),
        Schedule::Constant(1e-6),
        Schedule::Constant(1e-5),
        Schedule::MaxForTwoSteps,
        Schedule::RainStep,
    ];

    fn irrigation(self, k: usize) -> f64 {
        match self {
            Schedule::None | Schedule::RainStep => 0.0,
            Schedule::Constant(u) => u,
            Schedule::MaxForTwoSteps if k < 2 => U_MAX,
            Schedule::MaxForTwoSteps => 0.0,
        }
    }

    /// 50 mm of rain added to the weather at step 10.
    fn extra_rain_mm(self, k: usize) -> f64 {
        match self {
            Schedule::RainStep if k == 10 => 50.0,
            _ => 0.0,
        }
    }
}

fn forcing(weather: &WeatherSeries, schedule: Schedule, k: usize) -> Forcing {
    let w = weather.steps()[k];
    Forcing {
        precipitation: mm_to_rate(w.precip_mm + schedule.extra_rain_mm(k), STEP_SECONDS),
        ..w.forcing(schedule.irrigation(k), STEP_SECONDS)
    }
}

struct Outcome {
    texture: Texture,
    weather: &'static str,
    schedule: Schedule,
    error: Option<IntegrationError>,
    max_supply: f64,
}

/// Work limits well below the defaults, so that the runs that give up do so
/// quickly; the mechanism is the same.
const LIMITS: WorkLimits = WorkLimits {
    step_attempts: 200,
    newton_iterations: 4_000,
};

fn run(texture: Texture, name: &'static str, weather: &WeatherSeries, s: Schedule) -> Outcome {
    let mut field = Field::new(FieldSettings {
        soil: texture.parameters(),
        ..FieldSettings::default()
    })
    .expect("a texture is a valid soil");
    field.set_work_limits(LIMITS);
    let mut error = None;
    let mut max_supply: f64 = 0.0;
    for k in 0..STEPS {
        let f = forcing(weather, s, k);
        max_supply = max_supply.max(f.irrigation + f.precipitation);
        if let Err(e) = field.step(f) {
            error = Some(e);
            break;
        }
    }
    let balance = field.water_balance();
    assert!(
        balance.residual().abs() < 1e-9,
        "{texture} / {name} / {s:?}: water balance off by {:e} m",
        balance.residual()
    );
    assert!(balance.runoff >= -1e-15, "runoff is booked as a loss");
    let stats = field.integrator_statistics();
    assert!(
        stats.newton_iterations <= STEPS * (LIMITS.newton_iterations + 200),
        "{texture} / {name} / {s:?}: {} Newton iterations exceed the limits",
        stats.newton_iterations
    );
    Outcome {
        texture,
        weather: name,
        schedule: s,
        error,
        max_supply,
    }
}

#[test]
fn every_texture_and_schedule_finishes_or_names_where_it_stopped() {
    let dry = WeatherSeries::parse(DRY_SCENARIO, "weather-dry.csv").unwrap();
    let rain = WeatherSeries::parse(RAIN_SCENARIO, "weather-rain.csv").unwrap();
    let mut outcomes = Vec::new();
    for texture in Texture::ALL {
        for (name, weather) in [("dry", &dry), ("rain", &rain)] {
            for s in Schedule::ALL {
                outcomes.push(run(texture, name, weather, s));
            }
        }
    }
    let mut stopped = Vec::new();
    for o in &outcomes {
        let soil = o.texture.parameters();
        // the coarse textures, and any run that cannot pond, must finish: a
        // top cell at h ≤ 0 takes at least (Ks + K)/2 ≥ Ks/2 (MODEL.md §1)
        let must_finish = soil.n >= 1.89 || o.max_supply < 0.5 * soil.saturated_conductivity;
        match &o.error {
            None => {}
            Some(e) => {
                assert!(
                    !must_finish,
                    "{} / {} / {:?} must finish: {e}",
                    o.texture, o.weather, o.schedule
                );
                assert!(
                    matches!(
                        e.kind,
                        FailureKind::WorkLimit(_) | FailureKind::StepSizeCollapse
                    ),
                    "{e}"
                );
                let (Some(step), Some(dt), Some(cell)) = (e.step, e.smallest_step, e.cell) else {
                    panic!("the error must name step, smallest step and cell: {e:?}");
                };
                assert!(step < STEPS && dt > 0.0 && cell < 26, "{e:?}");
                assert!(e.time >= step as f64 * STEP_SECONDS, "{e:?}");
                let text = e.to_string();
                assert!(text.contains(&format!("sampling step {step}")), "{text}");
                assert!(text.contains(&format!("cell {cell}")), "{text}");
                stopped.push(format!("{} / {} / {:?}", o.texture, o.weather, o.schedule));
            }
        }
    }
    assert_eq!(outcomes.len(), 144);
    // what still stops (ponding on the textures finer than sandy loam) is
    // printed for the record; see ARCHITECTURE.md, "ponding"
    eprintln!("{} of 144 runs stop at the work limit:", stopped.len());
    for s in &stopped {
        eprintln!("  {s}");
    }
}

#[test]
fn an_interrupt_stops_the_integration_at_once() {
    use rootzone::soil::Interrupt;
    let mut field = Field::new(FieldSettings::default()).unwrap();
    let before = field.state().clone();
    let mut integrator = field.integrator().clone();
    integrator.set_interrupt(Some(Interrupt::new(|| true)));
    let mut state = before.clone();
    let e = integrator
        .advance(&mut state, 0.0, STEP_SECONDS, Forcing::default())
        .unwrap_err();
    assert_eq!(e.kind, FailureKind::Interrupted);
    assert_eq!(
        state, before,
        "an interrupted integration leaves the state alone"
    );
    assert_eq!(integrator.statistics().steps, 0);
    // without one the same step runs
    integrator.set_interrupt(None);
    integrator
        .advance(&mut state, 0.0, STEP_SECONDS, Forcing::default())
        .unwrap();
    field.step(Forcing::default()).unwrap();
}

#[test]
fn ill_posed_soils_are_refused_naming_the_parameter() {
    let base = Texture::Loam.parameters();
    for (name, soil) in [
        (
            "saturated_water_content",
            rootzone::soil::VanGenuchten {
                saturated_water_content: base.residual_water_content,
                ..base
            },
        ),
        ("n", rootzone::soil::VanGenuchten { n: 1.0, ..base }),
        (
            "saturated_conductivity",
            rootzone::soil::VanGenuchten {
                saturated_conductivity: 0.0,
                ..base
            },
        ),
        (
            "alpha",
            rootzone::soil::VanGenuchten {
                alpha: f64::NAN,
                ..base
            },
        ),
    ] {
        let e = soil.validate().unwrap_err();
        assert!(e.starts_with(name), "{e}");
        assert!(
            Field::new(FieldSettings {
                soil,
                ..FieldSettings::default()
            })
            .is_err()
        );
    }
    let e = Field::new(FieldSettings {
        initial_head: f64::INFINITY,
        ..FieldSettings::default()
    })
    .err()
    .unwrap();
    assert!(e.contains("initial head"), "{e}");
}
