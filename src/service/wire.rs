//! JSON wire types of the API and the configuration, validated at the edge
//! and converted to the core's plain types.

use chrono::{DateTime, Utc};
use serde::{Deserialize, Serialize};

use crate::control::{MpcSettings, ZoneSettings};
use crate::soil::{Crop, Texture, VanGenuchten};

/// A field as clients create it (`POST /v1/fields`) and read it back.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FieldSpec {
    pub name: String,
    #[serde(default)]
    pub soil: SoilSpec,
    #[serde(default)]
    pub crop: CropSpec,
    #[serde(default)]
    pub zone: ZoneSpec,
    #[serde(default)]
    pub model: ModelKind,
    /// Largest irrigation rate [m/s].
    #[serde(default = "default_irrigation_max")]
    pub irrigation_max: f64,
    /// Control period [s].
    #[serde(default = "default_period")]
    pub control_period_s: f64,
    /// How long a cycle at a period boundary waits for the measurement
    /// stamped at that boundary before it runs on the latest one [s of
    /// clock time; at most a quarter of the period is used]. Sensors report
    /// a little after the instant they measure.
    #[serde(default = "default_measurement_wait")]
    pub measurement_wait_s: f64,
    #[serde(default)]
    pub actuator: Actuator,
    /// The simulated plant (only with `actuator.kind = "simulated"`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub simulation: Option<SimulationSpec>,
}

fn default_irrigation_max() -> f64 {
    1e-5
}

fn default_period() -> f64 {
    7200.0
}

fn default_measurement_wait() -> f64 {
    300.0
}

impl FieldSpec {
    /// The wait a cycle actually allows for its boundary's measurement [s].
    pub fn effective_measurement_wait(&self) -> f64 {
        self.measurement_wait_s.min(self.control_period_s / 4.0)
    }
}

/// A soil: a preset texture name (Carsel & Parrish 1988) or parameters.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum SoilSpec {
    Preset(String),
    Parameters {
        residual_water_content: f64,
        saturated_water_content: f64,
        alpha: f64,
        n: f64,
        saturated_conductivity: f64,
        #[serde(default = "default_storage")]
        specific_storage: f64,
    },
}

fn default_storage() -> f64 {
    1e-6
}

impl Default for SoilSpec {
    fn default() -> Self {
        SoilSpec::Preset("sandy-loam".into())
    }
}

impl SoilSpec {
    pub fn parameters(&self) -> Result<VanGenuchten, String> {
        match self {
            SoilSpec::Preset(name) => name
                .parse::<Texture>()
                .map(Texture::parameters)
                .map_err(|e| format!("soil: {e}")),
            SoilSpec::Parameters {
                residual_water_content,
                saturated_water_content,
                alpha,
                n,
                saturated_conductivity,
                specific_storage,
            } => {
                let soil = VanGenuchten {
                    residual_water_content: *residual_water_content,
                    saturated_water_content: *saturated_water_content,
                    alpha: *alpha,
                    n: *n,
                    saturated_conductivity: *saturated_conductivity,
                    specific_storage: *specific_storage,
                };
                soil.validate()
                    .map(|()| soil)
                    .map_err(|e| format!("soil: {e}"))
            }
        }
    }

    /// Whether this is the sandy loam the shipped surrogates were trained on.
    pub fn is_sandy_loam(&self) -> bool {
        self.parameters()
            .is_ok_and(|p| p == Texture::SandyLoam.parameters())
    }
}

/// The crop: coefficient Kc and rooting depth [m] (grass by default).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CropSpec {
    pub crop_coefficient: f64,
    pub rooting_depth: f64,
}

impl Default for CropSpec {
    fn default() -> Self {
        let c = Crop::default();
        CropSpec {
            crop_coefficient: c.crop_coefficient,
            rooting_depth: c.rooting_depth,
        }
    }
}

/// The target zone (MODEL.md §4).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ZoneSpec {
    pub low: f64,
    pub up: f64,
    pub terminal_low: f64,
    pub terminal_up: f64,
    pub mu: f64,
}

impl Default for ZoneSpec {
    fn default() -> Self {
        let z = ZoneSettings::default();
        ZoneSpec {
            low: z.low0,
            up: z.up0,
            terminal_low: z.y_low,
            terminal_up: z.y_up,
            mu: z.mu,
        }
    }
}

impl ZoneSpec {
    pub fn settings(&self) -> ZoneSettings {
        ZoneSettings {
            low0: self.low,
            up0: self.up,
            y_low: self.terminal_low,
            y_up: self.terminal_up,
            mu: self.mu,
        }
    }
}

/// The prediction model of a field's controller.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ModelKind {
    #[default]
    TwoLayer,
    Lstm,
    Richards,
}

/// Where setpoints go.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "kebab-case", deny_unknown_fields)]
pub enum Actuator {
    /// Setpoints are only published through the API.
    #[default]
    None,
    /// The built-in simulated field applies them.
    Simulated,
    /// Each new setpoint is POSTed to `url` (with retries).
    Webhook { url: String },
}

/// The simulated plant of a field with a simulated actuator.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SimulationSpec {
    pub scenario: Scenario,
    /// Process noise level per measurement interval.
    pub process_noise: f64,
    pub measurement_noise: f64,
    pub forecast_error: f64,
    pub seed: u64,
    /// Seconds between measurements.
    pub measurement_interval_s: f64,
    /// Uniform initial pressure head [m].
    pub initial_head: f64,
    /// Clock time at which the plant starts from its initial state, with the
    /// scenario's first day beginning at the midnight (UTC) before it.
    /// Unset: when the field is created. Before it, the field is silent.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub start: Option<DateTime<Utc>>,
}

impl Default for SimulationSpec {
    fn default() -> Self {
        SimulationSpec {
            scenario: Scenario::Dry,
            process_noise: 0.0,
            measurement_noise: 0.02,
            forecast_error: 0.2,
            seed: 1,
            measurement_interval_s: 900.0,
            initial_head: -0.2,
            start: None,
        }
    }
}

/// The weather a simulated field lives in (the embedded scenarios, repeated).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Scenario {
    Dry,
    Rain,
}

impl FieldSpec {
    /// The embedded default: one simulated sandy-loam field, two-layer model.
    pub fn demo() -> FieldSpec {
        FieldSpec {
            name: "demo".into(),
            soil: SoilSpec::default(),
            crop: CropSpec::default(),
            zone: ZoneSpec::default(),
            model: ModelKind::TwoLayer,
            irrigation_max: default_irrigation_max(),
            control_period_s: default_period(),
            measurement_wait_s: default_measurement_wait(),
            actuator: Actuator::Simulated,
            simulation: Some(SimulationSpec::default()),
        }
    }

    /// What is wrong with the field, if anything (the message names the value).
    pub fn validate(&self) -> Result<(), String> {
        if self.name.trim().is_empty() || self.name.len() > 200 {
            return Err("name must have 1 to 200 characters".into());
        }
        self.soil.parameters()?;
        if self.model != ModelKind::Richards && !self.soil.is_sandy_loam() {
            return Err(format!(
                "model '{}' is trained for sandy-loam only; use model 'richards' for another soil",
                self.model.name()
            ));
        }
        let c = self.crop;
        if !(c.crop_coefficient.is_finite() && c.crop_coefficient >= 0.0) {
            return Err(format!(
                "crop.crop_coefficient must be ≥ 0, got {}",
                c.crop_coefficient
            ));
        }
        if !(c.rooting_depth.is_finite() && c.rooting_depth > 0.0 && c.rooting_depth <= 0.5) {
            return Err(format!(
                "crop.rooting_depth must be in (0, 0.5] m, got {}",
                c.rooting_depth
            ));
        }
        let z = self.zone;
        if [z.low, z.up, z.terminal_low, z.terminal_up]
            .iter()
            .any(|v| !(0.0..=1.0).contains(v))
        {
            return Err("zone bounds must lie in [0, 1]".into());
        }
        if let Some(problem) = z.settings().problem() {
            return Err(format!("zone: {problem}"));
        }
        if !(self.irrigation_max.is_finite() && self.irrigation_max > 0.0) {
            return Err(format!(
                "irrigation_max must be > 0 m/s, got {}",
                self.irrigation_max
            ));
        }
        if !(self.control_period_s.is_finite() && self.control_period_s >= 60.0) {
            return Err(format!(
                "control_period_s must be ≥ 60, got {}",
                self.control_period_s
            ));
        }
        let wait = self.measurement_wait_s;
        if !(wait.is_finite() && wait >= 0.0) {
            return Err(format!("measurement_wait_s must be ≥ 0, got {wait}"));
        }
        if let Actuator::Webhook { url } = &self.actuator
            && !(url.starts_with("http://") || url.starts_with("https://"))
        {
            return Err(format!("actuator.url must be an http(s) URL, got '{url}'"));
        }
        match (&self.actuator, &self.simulation) {
            (Actuator::Simulated, Some(sim)) => {
                for (name, v) in [
                    ("process_noise", sim.process_noise),
                    ("measurement_noise", sim.measurement_noise),
                    ("forecast_error", sim.forecast_error),
                ] {
                    if !(v.is_finite() && (0.0..0.5).contains(&v)) {
                        return Err(format!("simulation.{name} must be in [0, 0.5), got {v}"));
                    }
                }
                if !(sim.measurement_interval_s.is_finite()
                    && sim.measurement_interval_s >= 60.0
                    && sim.measurement_interval_s <= self.control_period_s)
                {
                    return Err(format!(
                        "simulation.measurement_interval_s must be in [60, control_period_s], got {}",
                        sim.measurement_interval_s
                    ));
                }
                if !(sim.initial_head.is_finite() && sim.initial_head < 0.0) {
                    return Err(format!(
                        "simulation.initial_head must be < 0 m, got {}",
                        sim.initial_head
                    ));
                }
            }
            (Actuator::Simulated, None) => {
                return Err("a simulated actuator needs a 'simulation' section".into());
            }
            (_, Some(_)) => {
                return Err("'simulation' needs actuator.kind = \"simulated\"".into());
            }
            _ => {}
        }
        Ok(())
    }

    /// The zone-MPC settings of this field.
    pub fn mpc_settings(&self) -> MpcSettings {
        let soil = self.soil.parameters().unwrap_or(VanGenuchten::SANDY_LOAM);
        MpcSettings {
            u_max: self.irrigation_max,
            zone: self.zone.settings(),
            theta_r: soil.residual_water_content,
            theta_s: soil.saturated_water_content,
            ..MpcSettings::default()
        }
    }

    pub fn crop(&self) -> Crop {
        Crop {
            crop_coefficient: self.crop.crop_coefficient,
            rooting_depth: self.crop.rooting_depth,
            ..Crop::default()
        }
    }
}

impl ModelKind {
    pub fn name(self) -> &'static str {
        match self {
            ModelKind::TwoLayer => "two-layer",
            ModelKind::Lstm => "lstm",
            ModelKind::Richards => "richards",
        }
    }
}

/// A stored field.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Field {
    pub id: i64,
    pub created_at: DateTime<Utc>,
    #[serde(flatten)]
    pub spec: FieldSpec,
}

/// One soil-moisture reading.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Measurement {
    pub time: DateTime<Utc>,
    /// Volumetric water content [m³/m³].
    pub theta: f64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sensor: Option<String>,
    /// The noise-free θ, for the built-in simulated fields only.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub true_theta: Option<f64>,
}

/// One measurement or a batch.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(untagged)]
pub enum Measurements {
    One(Measurement),
    Many(Vec<Measurement>),
}

/// A weather forecast: amounts per step of `step_s` seconds from `start`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Forecast {
    pub issued_at: DateTime<Utc>,
    pub start: DateTime<Utc>,
    pub step_s: f64,
    pub et0_mm: Vec<f64>,
    pub precip_mm: Vec<f64>,
}

impl Forecast {
    /// What is wrong with the forecast, naming the value.
    pub fn validate(&self) -> Result<(), String> {
        if !(self.step_s.is_finite() && self.step_s >= 60.0) {
            return Err(format!("step_s must be ≥ 60, got {}", self.step_s));
        }
        if self.et0_mm.len() != self.precip_mm.len() {
            return Err(format!(
                "et0_mm has {} entries but precip_mm has {}: they must be equal",
                self.et0_mm.len(),
                self.precip_mm.len()
            ));
        }
        if self.et0_mm.is_empty() || self.et0_mm.len() > 10_000 {
            return Err("a forecast needs 1 to 10000 steps".into());
        }
        for (name, values) in [("et0_mm", &self.et0_mm), ("precip_mm", &self.precip_mm)] {
            if let Some((i, v)) = values
                .iter()
                .enumerate()
                .find(|(_, v)| !(v.is_finite() && **v >= 0.0))
            {
                return Err(format!("{name}[{i}] = {v}: amounts must be finite and ≥ 0"));
            }
        }
        Ok(())
    }
}

/// A published setpoint with what the controller planned and predicted.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Setpoint {
    pub field_id: i64,
    /// When the control cycle ran (a period boundary for scheduled cycles).
    pub time: DateTime<Utc>,
    pub valid_from: DateTime<Utc>,
    pub valid_until: DateTime<Utc>,
    /// Irrigation rate over the period [m/s].
    pub rate: f64,
    /// Irrigation amount over the period [mm].
    pub amount_mm: f64,
    /// Planned rates over the horizon [m/s].
    pub plan: Vec<f64>,
    /// Predicted θ at the end of each horizon step.
    pub predicted_theta: Vec<f64>,
    /// (low, up) of each horizon step.
    pub zone: Vec<[f64; 2]>,
    pub model: ModelKind,
    /// converged | iteration-cap | time-budget | fallback.
    pub status: String,
    /// Why the solver fell back, if it did.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fallback_reason: Option<String>,
    pub iterations: usize,
    pub solve_ms: f64,
    /// Degraded modes: stale-measurement, no-measurement, default-forecast,
    /// solver-fallback.
    pub degraded: Vec<String>,
    /// Time of the measurement the cycle started from (absent when it
    /// started from a prediction or from nothing).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub measured_at: Option<DateTime<Utc>>,
    /// The bias correction in force.
    pub bias: f64,
    /// The bias-free prediction of θ at `valid_until` (for the next bias
    /// fit); absent when the cycle made none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub predicted_next: Option<f64>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_short_period_keeps_the_default_wait_valid_and_caps_it() {
        let spec = FieldSpec {
            control_period_s: 600.0,
            actuator: Actuator::None,
            simulation: None,
            ..FieldSpec::demo()
        };
        assert_eq!(spec.validate(), Ok(()));
        assert_eq!(spec.effective_measurement_wait(), 150.0);
        assert_eq!(FieldSpec::demo().effective_measurement_wait(), 300.0);
        let negative = FieldSpec {
            measurement_wait_s: -1.0,
            ..FieldSpec::demo()
        };
        assert!(
            negative
                .validate()
                .unwrap_err()
                .contains("measurement_wait_s")
        );
    }
}
