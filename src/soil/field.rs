//! A simulated field: one column advanced a sampling step at a time, with the
//! process and measurement noise of MODEL.md §2 and a running water balance.

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::column::{AMOUNTS, Column, DRAINAGE, Forcing, INFILTRATION, RUNOFF, UPTAKE};
use super::hydraulics::VanGenuchten;
use super::integrator::{
    ColumnState, IntegrationError, Integrator, IntegratorStatistics, Tolerances, WorkLimits,
};
use super::uptake::Crop;

/// Everything that defines a simulated field. Defaults: MODEL.md §1–2.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FieldSettings {
    /// Soil hydraulic parameters.
    pub soil: VanGenuchten,
    /// Crop coefficient, rooting depth, stress response.
    pub crop: Crop,
    /// Column depth L [m].
    pub depth: f64,
    /// Number of cells n.
    pub cells: usize,
    /// Uniform initial pressure head [m].
    pub initial_head: f64,
    /// Sampling time Δ [s].
    pub sampling_time: f64,
    /// Process noise level p: heads are multiplied by (1 + U(−p, p)) after each step.
    pub process_noise: f64,
    /// Measurement noise level m: y_meas = y·(1 + U(−m, m)).
    pub measurement_noise: f64,
    /// Seed of the noise generators.
    pub seed: u64,
    /// Integrator tolerances.
    pub tolerances: Tolerances,
}

impl Default for FieldSettings {
    fn default() -> Self {
        FieldSettings {
            soil: VanGenuchten::SANDY_LOAM,
            crop: Crop::default(),
            depth: 0.5,
            cells: 26,
            initial_head: -0.2,
            sampling_time: 7200.0,
            process_noise: 0.0,
            measurement_noise: 0.0,
            seed: 0,
            tolerances: Tolerances::default(),
        }
    }
}

impl FieldSettings {
    pub fn validate(&self) -> Result<(), String> {
        if !(self.initial_head.is_finite()) {
            return Err(format!(
                "initial head must be finite, got {}",
                self.initial_head
            ));
        }
        if !(self.sampling_time.is_finite() && self.sampling_time > 0.0) {
            return Err(format!(
                "sampling time must be > 0 s, got {}",
                self.sampling_time
            ));
        }
        for (name, v) in [
            ("process noise", self.process_noise),
            ("measurement noise", self.measurement_noise),
        ] {
            if !(v.is_finite() && (0.0..1.0).contains(&v)) {
                return Err(format!("{name} must be in [0, 1), got {v}"));
            }
        }
        self.tolerances.validate()
    }
}

/// Cumulative water amounts since the start, in m of water.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct WaterBalance {
    /// Water stored in the column at the start, Σ w·dz.
    pub initial_storage: f64,
    /// Water stored now.
    pub storage: f64,
    /// Water that entered at the surface.
    pub infiltration: f64,
    /// Water that left at the bottom.
    pub drainage: f64,
    /// Water taken up by roots.
    pub uptake: f64,
    /// Supply that did not infiltrate.
    pub runoff: f64,
    /// Storage change caused by process noise (not a physical flux).
    pub noise: f64,
}

impl WaterBalance {
    /// Δstorage − (infiltration − drainage − uptake + noise): zero for a conservative model.
    pub fn residual(&self) -> f64 {
        (self.storage - self.initial_storage)
            - (self.infiltration - self.drainage - self.uptake + self.noise)
    }
}

/// What one step produced.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepReport {
    /// Index of the step just completed (0-based).
    pub step: usize,
    /// Simulated time at the end of the step [s].
    pub time: f64,
    /// True water content at the sensor after the step.
    pub water_content: f64,
    /// What the sensor reads, with measurement noise.
    pub measured_water_content: f64,
}

/// A simulated field.
pub struct Field {
    settings: FieldSettings,
    integrator: Integrator,
    state: ColumnState,
    initial_storage: f64,
    noise_storage: f64,
    time: f64,
    steps: usize,
    process_rng: ChaCha8Rng,
    measurement_rng: ChaCha8Rng,
}

impl Field {
    pub fn new(settings: FieldSettings) -> Result<Self, String> {
        settings.validate()?;
        let column = Column::new(settings.soil, settings.crop, settings.depth, settings.cells)?;
        let integrator = Integrator::new(column, settings.tolerances)?;
        let state = ColumnState {
            heads: vec![settings.initial_head; settings.cells],
            amounts: [0.0; AMOUNTS],
        };
        let mut process_rng = ChaCha8Rng::seed_from_u64(settings.seed);
        process_rng.set_stream(1);
        let mut measurement_rng = ChaCha8Rng::seed_from_u64(settings.seed);
        measurement_rng.set_stream(2);
        let mut field = Field {
            settings,
            integrator,
            state,
            initial_storage: 0.0,
            noise_storage: 0.0,
            time: 0.0,
            steps: 0,
            process_rng,
            measurement_rng,
        };
        field.initial_storage = field.storage();
        Ok(field)
    }

    pub fn settings(&self) -> &FieldSettings {
        &self.settings
    }

    pub fn column(&self) -> &Column {
        self.integrator.column()
    }

    /// Simulated time since the start [s].
    pub fn time(&self) -> f64 {
        self.time
    }

    /// Number of completed steps.
    pub fn steps(&self) -> usize {
        self.steps
    }

    /// Puts the field in a stored state: heads and amounts, the simulated
    /// time and the number of completed steps. The noise generators restart
    /// from the seed and the step count, so a resumed field draws a
    /// reproducible, but not the same, noise sequence as one never stopped.
    pub fn restore(&mut self, state: ColumnState, time: f64, steps: usize) -> Result<(), String> {
        if state.heads.len() != self.state.heads.len() || state.heads.iter().any(|h| !h.is_finite())
        {
            return Err("a stored state needs one finite head per cell".into());
        }
        self.state = state;
        self.time = time;
        self.steps = steps;
        let seed = self.settings.seed ^ (steps as u64).rotate_left(32);
        self.process_rng = ChaCha8Rng::seed_from_u64(seed);
        self.process_rng.set_stream(1);
        self.measurement_rng = ChaCha8Rng::seed_from_u64(seed);
        self.measurement_rng.set_stream(2);
        Ok(())
    }

    /// The field's integrator (with its column), e.g. to predict from
    /// [`Field::state`] without advancing the field.
    pub fn integrator(&self) -> &Integrator {
        &self.integrator
    }

    /// Replaces the bounds on the integrator's work per sampling step.
    pub fn set_work_limits(&mut self, limits: WorkLimits) {
        self.integrator.set_limits(limits);
    }

    pub fn integrator_statistics(&self) -> IntegratorStatistics {
        self.integrator.statistics()
    }

    /// Pressure head of every cell, top first [m].
    pub fn pressure_heads(&self) -> &[f64] {
        &self.state.heads
    }

    /// The integrator's state: heads and water amounts.
    pub fn state(&self) -> &ColumnState {
        &self.state
    }

    /// Water content of every cell, top first.
    pub fn water_contents(&self) -> Vec<f64> {
        let soil = self.settings.soil;
        self.pressure_heads()
            .iter()
            .map(|&h| soil.water_content(h))
            .collect()
    }

    /// True water content at the sensor: θ of the cell holding the rooting depth.
    pub fn water_content(&self) -> f64 {
        let h = self.pressure_heads()[self.column().sensor_cell()];
        self.settings.soil.water_content(h)
    }

    /// What the sensor reads now: the true water content with measurement
    /// noise (a draw from the measurement stream).
    pub fn measure(&mut self) -> f64 {
        let m = self.settings.measurement_noise;
        let v = m * (2.0 * self.measurement_rng.random::<f64>() - 1.0);
        self.water_content() * (1.0 + v)
    }

    /// Water stored in the column, Σ (θ + Ss·h)·dz [m].
    pub fn storage(&self) -> f64 {
        let soil = self.settings.soil;
        let cells: f64 = self.state.heads.iter().map(|&h| soil.storage(h)).sum();
        cells * self.column().cell_thickness()
    }

    pub fn water_balance(&self) -> WaterBalance {
        let amounts = &self.state.amounts;
        WaterBalance {
            initial_storage: self.initial_storage,
            storage: self.storage(),
            infiltration: amounts[INFILTRATION],
            drainage: amounts[DRAINAGE],
            uptake: amounts[UPTAKE],
            runoff: amounts[RUNOFF],
            noise: self.noise_storage,
        }
    }

    /// Advances one sampling step under `forcing`, then applies process noise and
    /// reads the sensor.
    pub fn step(&mut self, forcing: Forcing) -> Result<StepReport, IntegrationError> {
        let step = self.steps;
        forcing
            .validate()
            .map_err(|message| IntegrationError::invalid(self.time, message).in_step(step))?;
        let dt = self.settings.sampling_time;
        self.integrator
            .advance(&mut self.state, self.time, dt, forcing)
            .map_err(|e| e.in_step(step))?;
        self.time += dt;
        self.steps += 1;
        self.apply_process_noise();
        let water_content = self.water_content();
        let measured_water_content = self.measure();
        Ok(StepReport {
            step: self.steps - 1,
            time: self.time,
            water_content,
            measured_water_content,
        })
    }

    fn apply_process_noise(&mut self) {
        let p = self.settings.process_noise;
        let before = self.storage();
        for h in &mut self.state.heads {
            // Draw for every cell even at p = 0, so that the stream does not depend on p.
            let factor = 1.0 + p * (2.0 * self.process_rng.random::<f64>() - 1.0);
            *h *= factor;
        }
        self.noise_storage += self.storage() - before;
    }
}
