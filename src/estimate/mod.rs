//! State and parameter estimation for the Richards column: an ensemble
//! Kalman filter on the augmented state (the 26 cell heads and five soil
//! parameters), pure (no I/O, no clock, no async; randomness only from a
//! `ChaCha8Rng` seeded by the caller).
//!
//! * Forecast: every member is the column of MODEL.md §1 with its own soil,
//!   advanced by the soil module's [`Integrator`] under the applied irrigation
//!   and the observed weather, within [`WorkLimits`]. A member whose
//!   integration fails is replaced by a copy of a randomly chosen member that
//!   succeeded (counted in [`Statistics::replaced_members`]); while the
//!   "unknown" prior selects its texture, one of the same texture, and a
//!   texture none of whose members succeeded leaves the selection. Model error
//!   enters as MODEL.md §2's process noise: every head is multiplied by
//!   `1 + σ_p·N(0, 1)` after each step (σ_p = 0.02/√3, the standard deviation
//!   of the plant's 2 % uniform noise, scaled by √(duration / 2 h)).
//! * Analysis: in the members' water contents θ(h) by default
//!   ([`AnalysisVariable`]; heads are recovered with each member's updated
//!   soil), [`analysis::analysis`], the serial square-root filter
//!   (Whitaker & Hamill 2002) by default, or the perturbed-observation EnKF
//!   (Evensen 2003; Burgers et al. 1998); observation operator θ(h) of the
//!   member's own soil in the sensor's cell. Before each analysis the
//!   deviations from the mean are inflated by a constant factor
//!   (multiplicative inflation, Anderson & Anderson 1999, Mon. Wea. Rev. 127,
//!   2741–2758), the cells and the parameters with their own factors: the parameters
//!   have no dynamics of their own, and without inflation their spread would
//!   only shrink. After the analysis every member's parameters are clamped to
//!   the physical bounds of [`prior::BOUNDS`] and its heads to
//!   [`HEAD_BOUNDS`].
//! * Divergence: non-finite members, an innovation covariance that is not
//!   positive definite, or a normalised innovation |d|/√(HPHᵀ + R) above
//!   [`EstimatorSettings::max_normalised_innovation`] are
//!   [`EstimateError::Diverged`]; [`Estimator::reset_to_prior`] starts over
//!   at the readings that came.
//!
//! # Why an EnKF, and these settings (measured)
//!
//! See ARCHITECTURE.md, "Decisions": the measurements that chose the
//! method, the scheme, the ensemble size and the inflation are recorded
//! there and in `tests/estimate.rs` / `benches/estimate.rs`.

// Index loops over cells and members read like the equations they implement.
#![allow(clippy::needless_range_loop)]

pub mod analysis;
pub mod prior;

use nalgebra::DMatrix;
use rand::{Rng, RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::soil::{
    Column, ColumnState, Crop, Feddes, Forcing, Integrator, Texture, Tolerances, VanGenuchten,
    WorkLimits,
};

pub use analysis::Scheme;
pub use prior::{PARAMETERS, Prior};

/// Most sensors a field's estimate assimilates (a daemon field's and a
/// `closed-loop` run's): each adds a row to every analysis.
pub const MAX_SENSORS: usize = 16;

/// Heads are kept within these bounds [m] after an analysis.
pub const HEAD_BOUNDS: (f64, f64) = (-1.0e4, 0.5);

/// A standard normal draw (Box–Muller).
pub(crate) fn normal(rng: &mut impl Rng) -> f64 {
    let u1: f64 = 1.0 - rng.random::<f64>(); // (0, 1]
    let u2: f64 = rng.random::<f64>();
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

/// A soil-moisture sensor.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Sensor {
    pub id: String,
    /// Depth below the surface [m], within the column.
    pub depth: f64,
    /// Standard deviation of its θ error [m³/m³].
    pub noise: f64,
}

/// Where the members start.
#[derive(Debug, Clone, PartialEq)]
pub enum InitialGuess {
    /// The same head [m] in every cell of every member.
    UniformHead(f64),
    /// A uniform head in each member that gives θ = `theta` in its own soil
    /// (the quasi-steady drainage profile of a free-draining column, unit
    /// gradient: the column at rest), spread over the members by a factor
    /// `exp(0.2·N(0, 1))` on the head. `theta` is usually the first reading.
    Reading(f64),
    /// Given heads, top first, for every member.
    Heads(Vec<f64>),
}

/// Settings of the filter. Defaults: measured, see the module documentation.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct EstimatorSettings {
    /// Ensemble size N.
    pub members: usize,
    /// Seed of every random draw.
    pub seed: u64,
    /// Column depth [m] and cells (MODEL.md §1: 0.5 m, 26).
    pub depth: f64,
    pub cells: usize,
    pub scheme: Scheme,
    /// Multiplicative inflation of the head deviations before an analysis.
    pub head_inflation: f64,
    /// Multiplicative inflation of the parameter deviations before an analysis.
    pub parameter_inflation: f64,
    /// Relative head noise σ_p per 2 h added after every forecast.
    pub process_noise: f64,
    /// Gaspari–Cohn half-width [m] of the localisation of head updates
    /// around a sensor (None: no localisation).
    pub localisation: Option<f64>,
    /// Normalised innovation beyond which the filter has diverged.
    pub max_normalised_innovation: f64,
    /// Tolerances of the members' integrations.
    pub relative_tolerance: f64,
    pub absolute_tolerance: f64,
    /// Work limits of one member's integration of one forecast.
    pub step_attempts: usize,
    pub newton_iterations: usize,
    /// For the "unknown" prior: updates during which every texture runs as
    /// its own sub-ensemble before the most likely one is kept.
    pub selection_updates: usize,
    /// For the "unknown" prior: members per texture while selecting.
    pub members_per_texture: usize,
    /// The variable the analysis moves the cells in (estimates stored before
    /// this setting existed analysed heads).
    #[serde(default = "AnalysisVariable::stored_default")]
    pub analysis_variable: AnalysisVariable,
    /// For the "unknown" prior: a texture whose log-likelihood falls this
    /// far behind the leader's is dropped from the selection, its members
    /// with it (None: every texture runs to the end of the selection, as
    /// estimates stored before this setting existed do).
    #[serde(default)]
    pub selection_prune: Option<f64>,
    /// The mean normalised innovation squared over the last
    /// `selection_updates` updates beyond which the texture in use (the
    /// "unknown" prior's selected one, or a declared one after its first
    /// `selection_updates` updates) is taken not to explain the readings,
    /// and the "unknown" prior's selection runs (None: never, as estimates
    /// stored before this setting existed).
    #[serde(default)]
    pub reselect_nis: Option<f64>,
}

/// The variable in which the analysis updates the cells of a member.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum AnalysisVariable {
    /// The pressure head itself.
    Head,
    /// The water content θ(h) of the member's own soil: the sensors'
    /// observation operator is then linear, and a reading on the flat dry
    /// end of θ(h) cannot move a member's head by metres (a head update
    /// there, on a sand, threw members to saturation). Heads are recovered
    /// with the member's updated soil, θ kept within (θr, θs].
    WaterContent,
}

impl AnalysisVariable {
    fn stored_default() -> Self {
        AnalysisVariable::Head
    }
}

impl Default for EstimatorSettings {
    fn default() -> Self {
        EstimatorSettings {
            members: 16,
            seed: 0,
            depth: 0.5,
            cells: 26,
            scheme: Scheme::SquareRoot,
            head_inflation: 1.02,
            parameter_inflation: 1.02,
            process_noise: 0.02 / 3f64.sqrt(),
            localisation: None,
            max_normalised_innovation: 12.0,
            relative_tolerance: 3e-3,
            absolute_tolerance: 3e-5,
            step_attempts: 500,
            newton_iterations: 10_000,
            selection_updates: 12,
            members_per_texture: 8,
            analysis_variable: AnalysisVariable::WaterContent,
            selection_prune: Some(6.0),
            reselect_nis: Some(4.0),
        }
    }
}

impl EstimatorSettings {
    pub fn validate(&self) -> Result<(), String> {
        if self.members < 4 {
            return Err(format!(
                "an ensemble needs at least 4 members, got {}",
                self.members
            ));
        }
        if self.members_per_texture < 2 {
            return Err(format!(
                "members_per_texture must be at least 2, got {}",
                self.members_per_texture
            ));
        }
        for (name, v, lo) in [
            ("head_inflation", self.head_inflation, 1.0),
            ("parameter_inflation", self.parameter_inflation, 1.0),
        ] {
            if !(v.is_finite() && v >= lo) {
                return Err(format!("{name} must be finite and >= {lo}, got {v}"));
            }
        }
        for (name, v) in [
            ("process_noise", self.process_noise),
            ("max_normalised_innovation", self.max_normalised_innovation),
            ("relative_tolerance", self.relative_tolerance),
            ("absolute_tolerance", self.absolute_tolerance),
            ("depth", self.depth),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!("{name} must be finite and >= 0, got {v}"));
            }
        }
        if let Some(gap) = self.selection_prune
            && !(gap.is_finite() && gap > 0.0)
        {
            return Err(format!("selection_prune must be finite and > 0, got {gap}"));
        }
        if let Some(limit) = self.reselect_nis
            && !(limit.is_finite() && limit > 1.0)
        {
            return Err(format!("reselect_nis must be finite and > 1, got {limit}"));
        }
        if let Some(c) = self.localisation
            && !(c.is_finite() && c > 0.0)
        {
            return Err(format!("localisation half-width must be > 0, got {c}"));
        }
        Ok(())
    }
}

/// The filter could not go on.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum EstimateError {
    #[error("unknown sensor {0}")]
    UnknownSensor(String),
    #[error("reading of sensor '{sensor}' is not a water content: {value}")]
    InvalidReading { sensor: String, value: f64 },
    #[error("invalid forcing: {0}")]
    InvalidForcing(String),
    /// The estimate is no longer trustworthy: reset it.
    #[error("estimator diverged: {0}")]
    Diverged(String),
}

/// One reading's innovation.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Innovation {
    pub sensor: String,
    pub observed: f64,
    /// The ensemble mean of the predicted θ, before the update.
    pub predicted: f64,
    /// observed − predicted.
    pub innovation: f64,
    /// innovation / √(HPHᵀ + R).
    pub normalised: f64,
}

/// What an update did.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct UpdateReport {
    pub innovations: Vec<Innovation>,
}

/// An estimated parameter.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ParameterEstimate {
    /// `ks`, `alpha`, `n`, `theta_r`, `theta_s`.
    pub name: String,
    pub unit: String,
    /// The natural value of the mean of the transformed parameter (for Ks
    /// and α the geometric mean).
    pub mean: f64,
    /// Ensemble standard deviation of the natural value.
    pub sd: f64,
    /// Mean and standard deviation of the transformed parameter
    /// (`ln_ks`, `ln_alpha`, `ln_n_minus_1`, `theta_r`, `theta_s`).
    pub transformed_name: String,
    pub transformed_mean: f64,
    pub transformed_sd: f64,
}

/// The estimated water content of one cell.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ProfilePoint {
    /// Cell centre depth [m].
    pub depth: f64,
    pub theta_mean: f64,
    pub theta_sd: f64,
}

/// Counters of the filter's work.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Statistics {
    pub forecasts: u64,
    pub updates: u64,
    /// Members replaced after a failed integration.
    pub replaced_members: u64,
    pub resets: u64,
    /// Selections run because the texture in use (selected or declared)
    /// did not explain the readings (`EstimatorSettings::reselect_nis`).
    #[serde(default)]
    pub reselections: u64,
}

/// The prior, as stored in a snapshot.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum PriorSnapshot {
    Texture(String),
    Unknown,
    Soil {
        ks: f64,
        alpha: f64,
        n: f64,
        theta_r: f64,
        theta_s: f64,
    },
}

/// Everything needed to resume a filter: the ensemble, the random
/// generator's position, the prior (for a reset) and the setting.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EstimatorSnapshot {
    pub version: u32,
    pub settings: EstimatorSettings,
    pub prior: PriorSnapshot,
    pub initial_heads: Vec<Vec<f64>>,
    pub crop: (f64, f64, [f64; 4]),
    pub sensors: Vec<Sensor>,
    /// Members, each the heads then the transformed parameters.
    pub members: Vec<Vec<f64>>,
    pub time: f64,
    pub statistics: Statistics,
    /// The generator's stream and word position.
    pub rng_stream: u64,
    pub rng_word_pos: u128,
    pub last_update: Option<UpdateReport>,
    pub selection: Option<Selection>,
    pub selected: Option<String>,
    #[serde(default)]
    pub recent_nis: Vec<f64>,
    #[serde(default)]
    pub since_reset: u64,
}

/// The ensemble filter.
#[derive(Debug, Clone)]
pub struct Estimator {
    settings: EstimatorSettings,
    prior: Prior,
    crop: Crop,
    sensors: Vec<Sensor>,
    /// The heads every member started from (for a reset).
    initial_heads: Vec<Vec<f64>>,
    /// (cells + 5) × N: heads, then the transformed parameters.
    ensemble: DMatrix<f64>,
    time: f64,
    rng: ChaCha8Rng,
    statistics: Statistics,
    last_update: Option<UpdateReport>,
    /// While selecting a texture (the "unknown" prior): the group (texture
    /// index) of every member and each group's log-likelihood so far.
    selection: Option<Selection>,
    selected: Option<Texture>,
    /// The normalised innovations squared (mean over the readings) of the
    /// updates since the selection ended, at most `selection_updates`.
    recent_nis: Vec<f64>,
    /// Updates since the start or the last reset.
    since_reset: u64,
}

/// The texture selection of the "unknown" prior: every texture's
/// sub-ensemble is analysed on its own and scored by the marginal likelihood
/// of the readings, `Σ log N(y; ȳ_g, s_g)` with the sub-ensemble's predicted
/// mean ȳ_g and innovation variance s_g (Bayesian model selection over the
/// twelve texture models, as in multiple-model adaptive estimation, Magill
/// 1965, IEEE Trans. Autom. Control 10, 434–439). After
/// [`EstimatorSettings::selection_updates`] updates the most likely texture
/// is kept: its members stay and the ensemble is refilled to `members` with
/// copies of them whose parameters are jittered by half the prior spread.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Selection {
    pub groups: Vec<usize>,
    pub log_likelihood: Vec<f64>,
    pub updates: usize,
}

impl Selection {
    /// The most likely texture group so far.
    pub fn leader(&self) -> usize {
        (0..self.log_likelihood.len())
            .filter(|g| self.groups.contains(g))
            .max_by(|&a, &b| self.log_likelihood[a].total_cmp(&self.log_likelihood[b]))
            .unwrap_or(0)
    }

    /// Keeps only the members `keep` (indices into `ensemble`'s columns,
    /// rising), in the ensemble and in the groups.
    fn retain(&mut self, ensemble: &mut DMatrix<f64>, keep: &[usize]) {
        *ensemble = ensemble.select_columns(keep.iter());
        self.groups = keep.iter().map(|&j| self.groups[j]).collect();
    }

    /// Whether one texture group is left.
    fn single(&self) -> bool {
        self.groups.windows(2).all(|w| w[0] == w[1])
    }
}

impl Estimator {
    /// A filter from `prior` with members started at `initial`. Refuses a
    /// sensor outside the column or with a noise that is not finite and > 0,
    /// naming it.
    pub fn new(
        prior: Prior,
        crop: Crop,
        sensors: Vec<Sensor>,
        initial: InitialGuess,
        settings: EstimatorSettings,
    ) -> Result<Self, String> {
        settings.validate()?;
        crop.validate()?;
        if let Prior::Soil(s) = &prior {
            s.validate()?;
        }
        // the geometry must be a valid column
        Column::new(
            VanGenuchten::SANDY_LOAM,
            crop,
            settings.depth,
            settings.cells,
        )?;
        if sensors.is_empty() {
            return Err("the estimator needs at least one sensor".into());
        }
        for (k, s) in sensors.iter().enumerate() {
            if !(s.depth.is_finite() && s.depth >= 0.0 && s.depth <= settings.depth) {
                return Err(format!(
                    "sensor '{}' ({k}) at depth {} m is outside the column (0 … {} m)",
                    s.id, s.depth, settings.depth
                ));
            }
            if !(s.noise.is_finite() && s.noise > 0.0) {
                return Err(format!(
                    "sensor '{}' ({k}) has noise {}: it must be finite and > 0",
                    s.id, s.noise
                ));
            }
            if sensors[..k].iter().any(|o| o.id == s.id) {
                return Err(format!("sensor id '{}' is used twice", s.id));
            }
        }
        let mut rng = ChaCha8Rng::seed_from_u64(settings.seed);
        let n = settings.cells;
        let textures = Texture::ALL.len();
        let (size, selection) = initial_members(&prior, &settings);
        let mut ensemble = DMatrix::zeros(n + PARAMETERS, size);
        let mut initial_heads = Vec::with_capacity(size);
        for j in 0..size {
            let p = prior.sample(j, &mut rng);
            let soil = prior::to_soil(&p);
            let heads = match &initial {
                InitialGuess::UniformHead(h) => {
                    if !h.is_finite() {
                        return Err(format!("initial head must be finite, got {h}"));
                    }
                    vec![*h; n]
                }
                InitialGuess::Heads(h) => {
                    if h.len() != n || h.iter().any(|v| !v.is_finite()) {
                        return Err(format!("initial heads must be {n} finite values"));
                    }
                    h.clone()
                }
                InitialGuess::Reading(theta) => {
                    if !theta.is_finite() {
                        return Err(format!("initial reading must be finite, got {theta}"));
                    }
                    heads_at_reading(&soil, *theta, n, &mut rng)
                }
            };
            for i in 0..n {
                ensemble[(i, j)] = heads[i];
            }
            for q in 0..PARAMETERS {
                ensemble[(n + q, j)] = p[q];
            }
            initial_heads.push(heads);
        }
        Ok(Estimator {
            settings,
            prior,
            crop,
            sensors,
            initial_heads,
            ensemble,
            time: 0.0,
            rng,
            statistics: Statistics::default(),
            last_update: None,
            selection: selection.then(|| Selection {
                groups: (0..size).map(|j| j % textures).collect(),
                log_likelihood: vec![0.0; textures],
                updates: 0,
            }),
            selected: None,
            recent_nis: Vec::new(),
            since_reset: 0,
        })
    }

    pub fn settings(&self) -> &EstimatorSettings {
        &self.settings
    }

    pub fn sensors(&self) -> &[Sensor] {
        &self.sensors
    }

    pub fn statistics(&self) -> Statistics {
        self.statistics
    }

    pub fn prior(&self) -> &Prior {
        &self.prior
    }

    /// Time advanced since the start [s].
    pub fn time(&self) -> f64 {
        self.time
    }

    /// The last update's innovations.
    pub fn last_update(&self) -> Option<&UpdateReport> {
        self.last_update.as_ref()
    }

    /// The index of a sensor by id.
    pub fn sensor_index(&self, id: &str) -> Option<usize> {
        self.sensors.iter().position(|s| s.id == id)
    }

    fn cells(&self) -> usize {
        self.settings.cells
    }

    fn member_soil(&self, j: usize) -> VanGenuchten {
        let n = self.cells();
        let p: Vec<f64> = (0..PARAMETERS).map(|q| self.ensemble[(n + q, j)]).collect();
        prior::to_soil(&p)
    }

    /// Propagates every member over `duration_s` under `forcing` (the
    /// applied irrigation and the observed weather), then adds the process
    /// noise.
    pub fn predict(&mut self, forcing: Forcing, duration_s: f64) -> Result<(), EstimateError> {
        forcing.validate().map_err(EstimateError::InvalidForcing)?;
        if !(duration_s.is_finite() && duration_s > 0.0) {
            return Err(EstimateError::InvalidForcing(format!(
                "duration must be > 0 s, got {duration_s}"
            )));
        }
        self.check_finite()?;
        let n = self.cells();
        let members = self.ensemble.ncols();
        let tolerances = Tolerances {
            relative: self.settings.relative_tolerance,
            absolute: self.settings.absolute_tolerance,
        };
        let limits = WorkLimits {
            step_attempts: self.settings.step_attempts,
            newton_iterations: self.settings.newton_iterations,
        };
        // the members are independent: integrated in parallel (rayon's
        // pool), each with its own integrator, so the result does not
        // depend on the number of threads
        let forecasts: Vec<Result<Option<Vec<f64>>, String>> = (0..members)
            .into_par_iter()
            .map(|j| {
                let soil = self.member_soil(j);
                let column = Column::new(soil, self.crop, self.settings.depth, n)?;
                let mut integrator = Integrator::new(column, tolerances)?.continuing();
                integrator.set_limits(limits);
                let mut state = ColumnState {
                    heads: (0..n).map(|i| self.ensemble[(i, j)]).collect(),
                    amounts: [0.0; 4],
                };
                Ok(integrator
                    .advance(&mut state, self.time, duration_s, forcing)
                    .ok()
                    .map(|()| state.heads))
            })
            .collect();
        let mut ok = vec![true; members];
        for (j, forecast) in forecasts.into_iter().enumerate() {
            match forecast.map_err(EstimateError::Diverged)? {
                Some(heads) => {
                    for (i, h) in heads.into_iter().enumerate() {
                        self.ensemble[(i, j)] = h;
                    }
                }
                None => ok[j] = false,
            }
        }
        let good: Vec<usize> = (0..members).filter(|&j| ok[j]).collect();
        if good.is_empty() {
            return Err(EstimateError::Diverged(
                "every member's integration failed".into(),
            ));
        }
        // while the "unknown" prior selects, a member is replaced from its
        // own texture (a copy of another texture's member would score that
        // texture's model under this one's name); a texture none of whose
        // members could be integrated leaves the selection
        if let Some(selection) = self.selection.as_mut() {
            let keep: Vec<usize> = (0..members)
                .filter(|&j| {
                    good.iter()
                        .any(|&i| selection.groups[i] == selection.groups[j])
                })
                .collect();
            if keep.len() < members {
                selection.retain(&mut self.ensemble, &keep);
                ok = keep.iter().map(|&j| ok[j]).collect();
            }
        }
        let members = self.ensemble.ncols();
        let good: Vec<usize> = (0..members).filter(|&j| ok[j]).collect();
        for j in 0..members {
            if !ok[j] {
                let pool: Vec<usize> = match &self.selection {
                    Some(selection) => good
                        .iter()
                        .copied()
                        .filter(|&i| selection.groups[i] == selection.groups[j])
                        .collect(),
                    None => good.clone(),
                };
                let from = pool[self.rng.random_range(0..pool.len())];
                let column = self.ensemble.column(from).clone_owned();
                self.ensemble.set_column(j, &column);
                self.statistics.replaced_members += 1;
            }
        }
        let sigma = self.settings.process_noise * (duration_s / 7200.0).sqrt();
        for j in 0..members {
            for i in 0..n {
                let w = sigma * normal(&mut self.rng);
                self.ensemble[(i, j)] *= 1.0 + w;
            }
        }
        self.time += duration_s;
        self.statistics.forecasts += 1;
        self.check_finite()
    }

    fn check_finite(&self) -> Result<(), EstimateError> {
        if let Some(k) = self.ensemble.iter().position(|v| !v.is_finite()) {
            let (rows, _) = self.ensemble.shape();
            return Err(EstimateError::Diverged(format!(
                "member {} holds a non-finite value in row {}",
                k / rows,
                k % rows
            )));
        }
        Ok(())
    }

    /// Assimilates `readings` (sensor index, θ) taken now.
    pub fn update(&mut self, readings: &[(usize, f64)]) -> Result<UpdateReport, EstimateError> {
        for &(k, theta) in readings {
            let sensor = self
                .sensors
                .get(k)
                .ok_or_else(|| EstimateError::UnknownSensor(format!("index {k}")))?;
            if !theta.is_finite() || !(-0.05..=1.05).contains(&theta) {
                return Err(EstimateError::InvalidReading {
                    sensor: sensor.id.clone(),
                    value: theta,
                });
            }
        }
        self.check_finite()?;
        if readings.is_empty() {
            return Ok(UpdateReport {
                innovations: Vec::new(),
            });
        }
        let theta_space = self.settings.analysis_variable == AnalysisVariable::WaterContent;
        if theta_space {
            self.heads_to_water_contents();
        }
        let outcome = self.analyse(readings, theta_space);
        if theta_space {
            self.water_contents_to_heads();
        }
        let (variances, predicted_mean) = outcome?;
        let innovations: Vec<Innovation> = readings
            .iter()
            .enumerate()
            .map(|(l, &(k, theta))| {
                let d = theta - predicted_mean[l];
                Innovation {
                    sensor: self.sensors[k].id.clone(),
                    observed: theta,
                    predicted: predicted_mean[l],
                    innovation: d,
                    normalised: d / variances[l].sqrt(),
                }
            })
            .collect();
        self.clamp_members();
        self.check_finite()?;
        self.statistics.updates += 1;
        self.check_selected_texture(&innovations, readings);
        let report = UpdateReport { innovations };
        self.last_update = Some(report.clone());
        if let Some(bad) = report.innovations.iter().find(|i| {
            i.normalised.is_nan() || i.normalised.abs() > self.settings.max_normalised_innovation
        }) {
            return Err(EstimateError::Diverged(format!(
                "sensor '{}': normalised innovation {:.1} beyond {}",
                bad.sensor, bad.normalised, self.settings.max_normalised_innovation
            )));
        }
        Ok(report)
    }

    /// Inflation and the analysis of `readings` (checked), on the ensemble
    /// whose cell rows hold heads, or water contents when `theta_space`.
    /// Returns the innovation variances and the forecast's mean predicted
    /// readings.
    fn analyse(
        &mut self,
        readings: &[(usize, f64)],
        theta_space: bool,
    ) -> Result<(Vec<f64>, Vec<f64>), EstimateError> {
        let n = self.cells();
        let members = self.ensemble.ncols();
        // inflate, around each texture group's own mean while selecting
        let groups: Vec<usize> = match &self.selection {
            Some(sel) => sel.groups.clone(),
            None => vec![0; members],
        };
        let group_count = groups.iter().max().map_or(1, |g| g + 1);
        for g in 0..group_count {
            let cols: Vec<usize> = (0..members).filter(|&j| groups[j] == g).collect();
            if cols.len() < 2 {
                continue;
            }
            for i in 0..n + PARAMETERS {
                let factor = if i < n {
                    self.settings.head_inflation
                } else {
                    self.settings.parameter_inflation
                };
                if factor != 1.0 {
                    let mean = cols.iter().map(|&j| self.ensemble[(i, j)]).sum::<f64>()
                        / cols.len() as f64;
                    for &j in &cols {
                        self.ensemble[(i, j)] = mean + factor * (self.ensemble[(i, j)] - mean);
                    }
                }
            }
        }
        if theta_space {
            self.clamp_parameters();
            self.clamp_water_contents();
        } else {
            self.clamp_members();
        }
        let m = readings.len();
        let cells: Vec<usize> = readings
            .iter()
            .map(|&(k, _)| cell_of(self.sensors[k].depth, self.settings.depth, n))
            .collect();
        let mut predicted = DMatrix::zeros(m, members);
        for j in 0..members {
            let soil = self.member_soil(j);
            for (l, &c) in cells.iter().enumerate() {
                let v = self.ensemble[(c, j)];
                predicted[(l, j)] = if theta_space {
                    v
                } else {
                    soil.water_content(v)
                };
            }
        }
        let y: Vec<f64> = readings.iter().map(|r| r.1).collect();
        let r: Vec<f64> = readings
            .iter()
            .map(|&(k, _)| self.sensors[k].noise.powi(2))
            .collect();
        let predicted_mean = analysis::row_means(&predicted);
        let dz = self.settings.depth / n as f64;
        let localisation = self.settings.localisation;
        let taper = |i: usize, k: usize| match localisation {
            Some(c) if i < n => analysis::gaspari_cohn((i as f64 - cells[k] as f64).abs() * dz, c),
            _ => 1.0,
        };
        let variances = match self.selection.take() {
            None => analysis::analysis(
                &mut self.ensemble,
                &mut predicted,
                &y,
                &r,
                self.settings.scheme,
                &taper,
                &mut self.rng,
            )
            .map_err(|e| EstimateError::Diverged(format!("{e:?}")))?,
            Some(mut selection) => {
                // every texture's sub-ensemble on its own, scored by the
                // marginal likelihood of the readings
                let groups = selection.log_likelihood.len();
                for g in 0..groups {
                    let cols: Vec<usize> =
                        (0..members).filter(|&j| selection.groups[j] == g).collect();
                    if cols.len() < 2 {
                        continue;
                    }
                    let mut xg = self.ensemble.select_columns(cols.iter());
                    let mut yg = predicted.select_columns(cols.iter());
                    let yg_mean = analysis::row_means(&yg);
                    let v = analysis::analysis(
                        &mut xg,
                        &mut yg,
                        &y,
                        &r,
                        self.settings.scheme,
                        &taper,
                        &mut self.rng,
                    )
                    .map_err(|e| EstimateError::Diverged(format!("texture group {g}: {e:?}")))?;
                    for l in 0..m {
                        let d = y[l] - yg_mean[l];
                        selection.log_likelihood[g] +=
                            -0.5 * (d * d / v[l] + v[l].ln() + std::f64::consts::TAU.ln());
                    }
                    for (c, &j) in cols.iter().enumerate() {
                        self.ensemble.set_column(j, &xg.column(c));
                    }
                }
                selection.updates += 1;
                if let Some(gap) = self.settings.selection_prune {
                    // textures far behind the leader leave with their members
                    let best = selection.log_likelihood[selection.leader()];
                    let keep: Vec<usize> = (0..members)
                        .filter(|&j| selection.log_likelihood[selection.groups[j]] >= best - gap)
                        .collect();
                    if keep.len() < members {
                        selection.retain(&mut self.ensemble, &keep);
                    }
                }
                // the innovation statistics of the whole mixture
                let scale = 1.0 / (members as f64 - 1.0);
                let overall: Vec<f64> = (0..m)
                    .map(|l| {
                        let ss: f64 = predicted
                            .row(l)
                            .iter()
                            .map(|v| (v - predicted_mean[l]).powi(2))
                            .sum();
                        ss * scale + r[l]
                    })
                    .collect();
                if selection.updates >= self.settings.selection_updates || selection.single() {
                    self.finish_selection(&selection);
                } else {
                    self.selection = Some(selection);
                }
                overall
            }
        };
        Ok((variances, predicted_mean.iter().copied().collect()))
    }

    /// Assimilates readings named by sensor id.
    pub fn update_by_id(
        &mut self,
        readings: &[(&str, f64)],
    ) -> Result<UpdateReport, EstimateError> {
        let mut indexed = Vec::with_capacity(readings.len());
        for &(id, theta) in readings {
            let k = self
                .sensor_index(id)
                .ok_or_else(|| EstimateError::UnknownSensor(format!("'{id}'")))?;
            indexed.push((k, theta));
        }
        self.update(&indexed)
    }

    /// Keeps the most likely texture's members and refills the ensemble
    /// to `members` with jittered copies of them.
    fn finish_selection(&mut self, selection: &Selection) {
        let best = selection.leader();
        let keep: Vec<usize> = (0..self.ensemble.ncols())
            .filter(|&j| selection.groups[j] == best)
            .collect();
        let n = self.cells();
        let size = self.settings.members.max(keep.len());
        let mut next = DMatrix::zeros(self.ensemble.nrows(), size);
        for j in 0..size {
            let from = keep[j % keep.len()];
            next.set_column(j, &self.ensemble.column(from));
            if j >= keep.len() {
                for q in 0..PARAMETERS {
                    next[(n + q, j)] += 0.5 * prior::TEXTURE_SD[q] * normal(&mut self.rng);
                }
            }
        }
        self.ensemble = next;
        self.selected = Some(Texture::ALL[best % Texture::ALL.len()]);
        self.clamp_members();
    }

    /// Checks the texture the "unknown" prior's selection kept, or the
    /// texture a field was declared, against the readings: when the mean
    /// normalised innovation squared over the last `selection_updates`
    /// updates exceeds [`EstimatorSettings::reselect_nis`] (its expectation
    /// is 1 where the model explains the readings), the "unknown" prior's
    /// selection runs from the readings of now ([`Estimator::restart`],
    /// counted in [`Statistics::reselections`], not as a reset). A single
    /// day of dry-down can leave two unlike textures nearly tied (a loamy
    /// sand read as a silt at 0.13), and a grower's guess can be wrong (a
    /// sandy loam declared clay was left to dry out); the days after it,
    /// with the soil wrongly taken, tell them apart.
    fn check_selected_texture(&mut self, innovations: &[Innovation], readings: &[(usize, f64)]) {
        let Some(limit) = self.settings.reselect_nis else {
            return;
        };
        self.since_reset += 1;
        // a declared texture's parameters get the day the "unknown" prior
        // spends selecting to settle before they are judged
        let declared = matches!(self.prior, Prior::Texture(_))
            && self.since_reset > self.settings.selection_updates as u64;
        if !(self.selected.is_some() || declared)
            || self.selection.is_some()
            || innovations.is_empty()
        {
            return;
        }
        let nis = innovations
            .iter()
            .map(|i| i.normalised.powi(2))
            .sum::<f64>()
            / innovations.len() as f64;
        let window = self.settings.selection_updates.max(1);
        self.recent_nis.push(nis);
        if self.recent_nis.len() > window {
            self.recent_nis.drain(..self.recent_nis.len() - window);
        }
        let mean = self.recent_nis.iter().sum::<f64>() / window as f64;
        if self.recent_nis.len() == window && mean > limit {
            tracing::debug!(
                selected = ?self.selected,
                mean_nis = mean,
                "the selected texture does not explain the readings: selecting again"
            );
            if declared {
                // the declared texture is a belief the readings refute
                self.prior = Prior::Unknown;
            }
            self.restart(readings);
            self.statistics.reselections += 1;
        }
    }

    /// The texture the "unknown" prior's selection kept, once it has.
    pub fn selected_texture(&self) -> Option<Texture> {
        self.selected
    }

    /// The running texture selection, if any.
    pub fn selection(&self) -> Option<&Selection> {
        self.selection.as_ref()
    }

    /// Whether the "unknown" prior is still selecting a texture.
    pub fn selecting(&self) -> bool {
        self.selection.is_some()
    }

    /// The smallest effective saturation a member's cell is given when its
    /// water content comes back from the analysis.
    const SE_FLOOR: f64 = 1e-9;

    /// Replaces every cell value v of every member with `f(soil, v)`, the
    /// member's own soil given.
    fn map_cells(&mut self, f: impl Fn(&VanGenuchten, f64) -> f64) {
        let n = self.cells();
        for j in 0..self.ensemble.ncols() {
            let soil = self.member_soil(j);
            for i in 0..n {
                self.ensemble[(i, j)] = f(&soil, self.ensemble[(i, j)]);
            }
        }
    }

    /// Replaces every member's cell heads with their water contents θ(h) in
    /// the member's own soil.
    fn heads_to_water_contents(&mut self) {
        self.map_cells(|soil, h| soil.water_content(h));
    }

    /// Keeps every member's cell water contents within its soil's range
    /// [θr + ε, θs] (rows hold water contents; non-finite values stay).
    fn clamp_water_contents(&mut self) {
        self.map_cells(|soil, v| {
            let (lo, hi) = Self::water_content_range(soil);
            if v.is_finite() { v.clamp(lo, hi) } else { v }
        });
    }

    fn water_content_range(soil: &VanGenuchten) -> (f64, f64) {
        let range = soil.saturated_water_content - soil.residual_water_content;
        (
            soil.residual_water_content + Self::SE_FLOOR * range,
            soil.saturated_water_content,
        )
    }

    /// The inverse of [`Self::heads_to_water_contents`], with the members'
    /// (updated) soils; parameters are clamped to their bounds first, water
    /// contents to the soil's range, heads to [`HEAD_BOUNDS`]. A non-finite
    /// value stays non-finite (for [`Self::check_finite`]).
    fn water_contents_to_heads(&mut self) {
        self.clamp_parameters();
        self.map_cells(|soil, v| {
            let (lo, hi) = Self::water_content_range(soil);
            if v.is_finite() {
                soil.pressure_head_at(v.clamp(lo, hi))
                    .clamp(HEAD_BOUNDS.0, HEAD_BOUNDS.1)
            } else {
                v
            }
        });
    }

    fn clamp_parameters(&mut self) {
        let n = self.cells();
        for j in 0..self.ensemble.ncols() {
            let mut p: Vec<f64> = (0..PARAMETERS).map(|q| self.ensemble[(n + q, j)]).collect();
            prior::clamp(&mut p);
            for q in 0..PARAMETERS {
                self.ensemble[(n + q, j)] = p[q];
            }
        }
    }

    /// Keeps every member's heads within [`HEAD_BOUNDS`] and its parameters
    /// within their bounds (non-finite values stay, for
    /// [`Self::check_finite`]).
    fn clamp_members(&mut self) {
        let n = self.cells();
        for j in 0..self.ensemble.ncols() {
            for i in 0..n {
                let h = self.ensemble[(i, j)];
                if h.is_finite() {
                    self.ensemble[(i, j)] = h.clamp(HEAD_BOUNDS.0, HEAD_BOUNDS.1);
                }
            }
        }
        self.clamp_parameters();
    }

    /// Starts over from the prior, keeping the time, the sensors and the
    /// generator's position. The members' heads are those of
    /// [`InitialGuess::Reading`] at the first of `readings` (sensor index,
    /// θ) that is a valid reading, taken now: the column at rest at the
    /// water content the field shows now, in each member's soil; with none,
    /// the heads the filter started from (a reset long after the start
    /// would otherwise begin from a water content the field left days ago).
    pub fn reset_to_prior(&mut self, readings: &[(usize, f64)]) {
        self.restart(readings);
        self.statistics.resets += 1;
    }

    /// [`Estimator::reset_to_prior`] without counting it: the members
    /// drawn afresh from the prior, the selection (if the prior has one)
    /// started, the last update forgotten.
    fn restart(&mut self, readings: &[(usize, f64)]) {
        let reading = readings
            .iter()
            .find(|&&(k, theta)| k < self.sensors.len() && (0.0..=1.0).contains(&theta))
            .map(|&(_, theta)| theta);
        let n = self.cells();
        // the prior's own size: a declared texture the readings contradict
        // is followed by the "unknown" prior's larger ensemble
        let (size, selecting) = initial_members(&self.prior, &self.settings);
        let resized = size != self.initial_heads.len();
        self.ensemble = DMatrix::zeros(n + PARAMETERS, size);
        let mut started = Vec::with_capacity(if resized { size } else { 0 });
        for j in 0..size {
            let p = self.prior.sample(j, &mut self.rng);
            let heads = match reading {
                Some(theta) => heads_at_reading(&prior::to_soil(&p), theta, n, &mut self.rng),
                None => self.initial_heads[j % self.initial_heads.len()].clone(),
            };
            for i in 0..n {
                self.ensemble[(i, j)] = heads[i];
            }
            for q in 0..PARAMETERS {
                self.ensemble[(n + q, j)] = p[q];
            }
            if resized {
                started.push(heads);
            }
        }
        if resized {
            self.initial_heads = started;
        }
        let textures = Texture::ALL.len();
        self.selection = selecting.then(|| Selection {
            groups: (0..size).map(|j| j % textures).collect(),
            log_likelihood: vec![0.0; textures],
            updates: 0,
        });
        self.selected = None;
        self.recent_nis.clear();
        self.since_reset = 0;
        self.last_update = None;
    }

    /// The mean soil (transformed parameters averaged, clamped to the bounds).
    pub fn soil(&self) -> VanGenuchten {
        let n = self.cells();
        let mean = analysis::row_means(&self.ensemble);
        let p: Vec<f64> = (0..PARAMETERS).map(|q| mean[n + q]).collect();
        prior::to_soil(&p)
    }

    /// The heads for a Richards model with [`Estimator::soil`]: in every
    /// cell, the head of the mean soil at the ensemble-mean water content, so
    /// the model's θ is the estimated θ.
    pub fn mean_heads(&self) -> Vec<f64> {
        let soil = self.soil();
        let lo = soil.residual_water_content + 1e-4;
        let hi = soil.saturated_water_content;
        self.profile()
            .iter()
            .map(|p| {
                soil.pressure_head_at(p.theta_mean.clamp(lo, hi))
                    .clamp(HEAD_BOUNDS.0, 0.0)
            })
            .collect()
    }

    /// Ensemble mean of the heads, cell by cell.
    pub fn mean_member_heads(&self) -> Vec<f64> {
        let mean = analysis::row_means(&self.ensemble);
        mean.iter().take(self.cells()).copied().collect()
    }

    /// The parameters with their ensemble standard deviations.
    pub fn parameters(&self) -> Vec<ParameterEstimate> {
        let n = self.cells();
        let members = self.ensemble.ncols();
        let mean = analysis::row_means(&self.ensemble);
        (0..PARAMETERS)
            .map(|q| {
                let row = self.ensemble.row(n + q);
                let transformed_sd = sd(row.iter().copied(), mean[n + q], members);
                let naturals: Vec<f64> = row.iter().map(|&v| prior::natural(q, v)).collect();
                let natural_mean = naturals.iter().sum::<f64>() / members as f64;
                ParameterEstimate {
                    name: prior::NAMES[q].into(),
                    unit: prior::UNITS[q].into(),
                    mean: prior::natural(q, mean[n + q]),
                    sd: sd(naturals.iter().copied(), natural_mean, members),
                    transformed_name: prior::TRANSFORMED_NAMES[q].into(),
                    transformed_mean: mean[n + q],
                    transformed_sd,
                }
            })
            .collect()
    }

    /// θ mean and standard deviation of every cell, top first.
    pub fn profile(&self) -> Vec<ProfilePoint> {
        let n = self.cells();
        let members = self.ensemble.ncols();
        let soils: Vec<VanGenuchten> = (0..members).map(|j| self.member_soil(j)).collect();
        let dz = self.settings.depth / n as f64;
        (0..n)
            .map(|i| {
                let theta: Vec<f64> = (0..members)
                    .map(|j| soils[j].water_content(self.ensemble[(i, j)]))
                    .collect();
                let mean = theta.iter().sum::<f64>() / members as f64;
                ProfilePoint {
                    depth: (i as f64 + 0.5) * dz,
                    theta_mean: mean,
                    theta_sd: sd(theta.iter().copied(), mean, members),
                }
            })
            .collect()
    }

    /// The standard deviation of the estimated θ in the cell a Richards
    /// model reads its output from (the rooting depth, MODEL.md §1).
    pub fn output_sd(&self) -> f64 {
        let n = self.cells();
        self.profile()[cell_of(self.crop.rooting_depth, self.settings.depth, n)].theta_sd
    }

    /// The estimated θ at a sensor (ensemble mean).
    pub fn sensor_theta(&self, k: usize) -> Option<f64> {
        let s = self.sensors.get(k)?;
        let c = cell_of(s.depth, self.settings.depth, self.cells());
        Some(self.profile()[c].theta_mean)
    }

    /// Everything needed to resume.
    pub fn snapshot(&self) -> EstimatorSnapshot {
        let prior = match self.prior {
            Prior::Texture(t) => PriorSnapshot::Texture(t.name().into()),
            Prior::Unknown => PriorSnapshot::Unknown,
            Prior::Soil(s) => PriorSnapshot::Soil {
                ks: s.saturated_conductivity,
                alpha: s.alpha,
                n: s.n,
                theta_r: s.residual_water_content,
                theta_s: s.saturated_water_content,
            },
        };
        let f = self.crop.stress;
        EstimatorSnapshot {
            version: 1,
            settings: self.settings,
            prior,
            initial_heads: self.initial_heads.clone(),
            crop: (
                self.crop.crop_coefficient,
                self.crop.rooting_depth,
                [f.h1, f.h2, f.h3, f.h4],
            ),
            sensors: self.sensors.clone(),
            members: self
                .ensemble
                .column_iter()
                .map(|c| c.iter().copied().collect())
                .collect(),
            time: self.time,
            statistics: self.statistics,
            rng_stream: self.rng.get_stream(),
            rng_word_pos: self.rng.get_word_pos(),
            last_update: self.last_update.clone(),
            selection: self.selection.clone(),
            selected: self.selected.map(|t| t.name().to_string()),
            recent_nis: self.recent_nis.clone(),
            since_reset: self.since_reset,
        }
    }

    /// A filter resumed from a snapshot: the same subsequent results as the
    /// filter it was taken from.
    pub fn restore(snapshot: EstimatorSnapshot) -> Result<Self, String> {
        if snapshot.version != 1 {
            return Err(format!("unknown snapshot version {}", snapshot.version));
        }
        let settings = snapshot.settings;
        settings.validate()?;
        let prior = match &snapshot.prior {
            PriorSnapshot::Texture(name) => {
                Prior::Texture(name.parse::<Texture>().map_err(|e| e.to_string())?)
            }
            PriorSnapshot::Unknown => Prior::Unknown,
            PriorSnapshot::Soil {
                ks,
                alpha,
                n,
                theta_r,
                theta_s,
            } => Prior::Soil(VanGenuchten {
                saturated_conductivity: *ks,
                alpha: *alpha,
                n: *n,
                residual_water_content: *theta_r,
                saturated_water_content: *theta_s,
                specific_storage: 1e-6,
            }),
        };
        let (kc, rooting, [h1, h2, h3, h4]) = snapshot.crop;
        let crop = Crop {
            crop_coefficient: kc,
            rooting_depth: rooting,
            stress: Feddes { h1, h2, h3, h4 },
        };
        let rows = settings.cells + PARAMETERS;
        let size = snapshot.members.len();
        if size < 2
            || snapshot.members.iter().any(|m| m.len() != rows)
            || snapshot
                .initial_heads
                .iter()
                .any(|h| h.len() != settings.cells)
            || snapshot
                .selection
                .as_ref()
                .is_some_and(|s| s.groups.len() != size)
        {
            return Err(format!(
                "a snapshot needs members of {rows} values and initial heads of {}",
                settings.cells
            ));
        }
        // validate the sensors the same way as `new`
        let mut check = Estimator::new(
            prior,
            crop,
            snapshot.sensors.clone(),
            InitialGuess::UniformHead(-1.0),
            settings,
        )?;
        if check.initial_heads.len() != snapshot.initial_heads.len() {
            return Err("the snapshot's initial heads do not match its settings".into());
        }
        check.ensemble = DMatrix::from_fn(rows, size, |i, j| snapshot.members[j][i]);
        check.initial_heads = snapshot.initial_heads;
        check.time = snapshot.time;
        check.statistics = snapshot.statistics;
        check.rng = ChaCha8Rng::seed_from_u64(settings.seed);
        check.rng.set_stream(snapshot.rng_stream);
        check.rng.set_word_pos(snapshot.rng_word_pos);
        check.last_update = snapshot.last_update;
        check.selection = snapshot.selection;
        check.recent_nis = snapshot.recent_nis;
        check.since_reset = snapshot.since_reset;
        check.selected = match snapshot.selected {
            Some(name) => Some(name.parse::<Texture>().map_err(|e| e.to_string())?),
            None => None,
        };
        Ok(check)
    }

    /// The ensemble, (cells + 5) × N (for tests and diagnostics).
    pub fn ensemble(&self) -> &DMatrix<f64> {
        &self.ensemble
    }

    /// Replaces one value of the ensemble (for tests of divergence detection).
    pub fn inject(&mut self, row: usize, member: usize, value: f64) {
        if row < self.ensemble.nrows() && member < self.ensemble.ncols() {
            self.ensemble[(row, member)] = value;
        }
    }
}

/// The ensemble size at the start, and whether a texture selection runs.
fn initial_members(prior: &Prior, settings: &EstimatorSettings) -> (usize, bool) {
    match prior {
        Prior::Unknown if settings.selection_updates > 0 => {
            (Texture::ALL.len() * settings.members_per_texture, true)
        }
        _ => (settings.members, false),
    }
}

/// A member's heads for [`InitialGuess::Reading`]: the uniform head that
/// gives θ = `theta` in `soil`, spread by a factor `exp(0.2·N(0, 1))`.
fn heads_at_reading(soil: &VanGenuchten, theta: f64, n: usize, rng: &mut impl Rng) -> Vec<f64> {
    let lo = soil.residual_water_content + 1e-3;
    let hi = soil.saturated_water_content - 1e-3;
    let h = soil
        .pressure_head_at(theta.clamp(lo, hi))
        .max(HEAD_BOUNDS.0);
    let factor = (0.2 * normal(rng)).exp();
    vec![(h * factor).clamp(HEAD_BOUNDS.0, -1e-3); n]
}

/// The cell holding depth `d` in a column of `depth` m and `n` cells.
pub fn cell_of(d: f64, depth: f64, n: usize) -> usize {
    ((d / (depth / n as f64)) as usize).min(n - 1)
}

fn sd(values: impl Iterator<Item = f64>, mean: f64, n: usize) -> f64 {
    let ss: f64 = values.map(|v| (v - mean).powi(2)).sum();
    (ss / (n.max(2) - 1) as f64).sqrt()
}
