//! JSON wire types of the API and the configuration, validated at the edge
//! and converted to the core's plain types.

use chrono::{DateTime, Utc};
use serde::{Deserialize, Serialize};

use crate::control::{MpcSettings, ZoneSettings};
use crate::soil::{Crop, Texture, VanGenuchten};

/// The documented ranges of what comes in (`openapi.yaml` states the same).
/// Longest field or sensor name [characters].
pub const MAX_NAME_CHARS: usize = 200;
/// Irrigation rate limit [m/s]: (0, 1e-4], i.e. up to 360 mm/h (the
/// largest rate of an irrigation file too).
pub const IRRIGATION_MAX: (f64, f64) = (0.0, crate::simulate::MAX_IRRIGATION);
/// Control period [s]: one minute to one day.
pub const CONTROL_PERIOD_S: (f64, f64) = (60.0, 86_400.0);
/// Wait for a boundary's measurement [s].
pub const MEASUREMENT_WAIT_S: (f64, f64) = (0.0, 3_600.0);
/// Crop coefficient Kc.
pub const CROP_COEFFICIENT: (f64, f64) = (0.0, 2.0);
/// Initial head of a simulated plant [m].
pub const INITIAL_HEAD: (f64, f64) = (-100.0, -1e-3);
/// Forecast step [s].
pub const FORECAST_STEP_S: (f64, f64) = (60.0, 86_400.0);
/// Largest forecast span [s]: 30 days.
pub const FORECAST_SPAN_S: f64 = 30.0 * 86_400.0;
/// Largest ET0 and precipitation rates of a forecast [mm/h]: those of a
/// weather file (defined beside it, where the CLI checks them too).
pub use crate::weather::{MAX_ET0_MM_PER_H, MAX_PRECIP_MM_PER_H};
/// Every timestamp lies in the years 2000 … 2199.
pub const EARLIEST_YEAR: i32 = 2000;
pub const LATEST_YEAR: i32 = 2199;

/// `value` in [lo, hi], or a message naming `name` and the range.
pub fn check_range(name: &str, value: f64, (lo, hi): (f64, f64)) -> Result<(), String> {
    if value.is_finite() && (lo..=hi).contains(&value) {
        Ok(())
    } else {
        Err(format!("{name} = {value} must lie in [{lo}, {hi}]"))
    }
}

/// A timestamp in the years 2000 … 2199, or a message naming `name`.
pub fn check_time(name: &str, t: DateTime<Utc>) -> Result<(), String> {
    use chrono::Datelike;
    if (EARLIEST_YEAR..=LATEST_YEAR).contains(&t.year()) {
        Ok(())
    } else {
        Err(format!(
            "{name} = {} must lie in the years {EARLIEST_YEAR} to {LATEST_YEAR}",
            t.to_rfc3339()
        ))
    }
}

/// The syntax of a webhook URL: http(s), a host, at most 2000 characters.
/// Where it may point is checked again at each delivery
/// (`service::webhook`), after name resolution.
pub fn validate_webhook_url(url: &str) -> Result<(), String> {
    if url.len() > 2000 {
        return Err("actuator.url must have at most 2000 characters".into());
    }
    if !(url.starts_with("http://") || url.starts_with("https://")) {
        return Err(format!(
            "actuator.url must start with http:// or https://, got '{url}'"
        ));
    }
    // the characters of RFC 3986 only (no spaces, no unencoded Unicode)
    const ALLOWED: &str = "-._~:/?#[]@!$&'()*+,;=%";
    if let Some(c) = url
        .chars()
        .find(|c| !(c.is_ascii_alphanumeric() || ALLOWED.contains(*c)))
    {
        return Err(format!(
            "actuator.url holds {c:?}, which a URI does not (percent-encode it)"
        ));
    }
    let parsed = reqwest::Url::parse(url)
        .map_err(|e| format!("actuator.url = '{url}' is not a URL ({e})"))?;
    if !matches!(parsed.scheme(), "http" | "https") {
        return Err(format!("actuator.url must be an http(s) URL, got '{url}'"));
    }
    if parsed.host_str().is_none_or(str::is_empty) {
        return Err(format!("actuator.url = '{url}' has no host"));
    }
    if !parsed.username().is_empty() || parsed.password().is_some() {
        return Err("actuator.url must not carry credentials (the secret signs deliveries)".into());
    }
    Ok(())
}

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
    /// The field's soil-moisture sensors; the first is the primary one (the
    /// surrogate controllers read it, and measurements that name no sensor
    /// are its). Empty: one sensor `default` at the rooting depth.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub sensors: Vec<SensorSpec>,
    /// The simulated plant (only with `actuator.kind = "simulated"`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub simulation: Option<SimulationSpec>,
    /// Area and emitter rate: setpoints then also carry valve minutes,
    /// litres and a cycle-and-soak split ([`super::valve`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub irrigation_system: Option<super::valve::IrrigationSystem>,
    /// A forecast provider the daemon polls for this field (instead of
    /// forecasts sent to it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub forecast_source: Option<crate::adapters::forecast::SourceSpec>,
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
#[serde(untagged, deny_unknown_fields)]
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

/// The soil name of a field whose soil nobody has measured.
pub const UNKNOWN_SOIL: &str = "unknown";

impl SoilSpec {
    /// Whether the field's soil is `unknown`: the estimator starts from the
    /// mixture of the twelve texture priors.
    pub fn is_unknown(&self) -> bool {
        matches!(self, SoilSpec::Preset(name) if name == UNKNOWN_SOIL)
    }

    /// The soil the field is planned on before its estimate exists: the
    /// declared one, or for `unknown` the mean of the twelve textures in
    /// the estimator's parameters (ln Ks, ln α, ln(n − 1), θr, θs).
    pub fn nominal(&self) -> Result<VanGenuchten, String> {
        if self.is_unknown() {
            let mut mean = [0.0; crate::estimate::prior::PARAMETERS];
            for t in Texture::ALL {
                let p = crate::estimate::prior::to_transformed(&t.parameters());
                for (m, v) in mean.iter_mut().zip(p) {
                    *m += v / Texture::ALL.len() as f64;
                }
            }
            return Ok(crate::estimate::prior::to_soil(&mean));
        }
        self.parameters()
    }

    /// The declared soil's parameters (an error for `unknown`).
    pub fn parameters(&self) -> Result<VanGenuchten, String> {
        match self {
            SoilSpec::Preset(name) if name == UNKNOWN_SOIL => {
                Err("soil 'unknown' has no parameters until it is estimated".into())
            }
            // the API takes the names exactly as written (the CLI is lenient)
            SoilSpec::Preset(name) => match Texture::ALL.into_iter().find(|t| t.name() == name) {
                Some(t) => Ok(t.parameters()),
                None => Err(format!(
                    "soil: '{name}' is not a texture; one of {} or '{UNKNOWN_SOIL}'",
                    Texture::ALL.map(Texture::name).join(", ")
                )),
            },
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
                soil.validate().map_err(|e| format!("soil: {e}"))?;
                for (name, v, most) in [
                    ("alpha", soil.alpha, 100.0),
                    ("n", soil.n, 10.0),
                    ("saturated_conductivity", soil.saturated_conductivity, 1e-2),
                    ("specific_storage", soil.specific_storage, 1e-2),
                ] {
                    if v > most {
                        return Err(format!("soil.{name} = {v} must be at most {most}"));
                    }
                }
                Ok(soil)
            }
        }
    }

    /// Whether this is the sandy loam the shipped surrogates were trained on.
    pub fn is_sandy_loam(&self) -> bool {
        self.parameters()
            .is_ok_and(|p| p == Texture::SandyLoam.parameters())
    }
}

/// The crop: coefficient Kc and rooting depth [m] (grass by default; each
/// key defaults on its own).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
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

/// The target zone (MODEL.md §4), each bound in water content [m³/m³] or in
/// pressure head [m] (not both). Every key is optional: a missing `low`/`up`
/// is the soil's default zone ([0.18, 0.23] for sandy loam, else the water
/// contents of the heads −0.43 … −0.27 m), a missing terminal bound is the
/// initial one, and μ defaults to 0 (a time-invariant zone).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ZoneSpec {
    #[serde(skip_serializing_if = "Option::is_none")]
    pub low: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub up: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub terminal_low: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub terminal_up: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub low_head: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub up_head: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub terminal_low_head: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub terminal_up_head: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub mu: Option<f64>,
}

/// Range of a zone given in pressure head [m].
pub const ZONE_HEAD_RANGE: (f64, f64) = (-1000.0, 0.0);

/// A field's zone as the controller uses it, in both forms.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct EffectiveZone {
    pub low: f64,
    pub up: f64,
    pub terminal_low: f64,
    pub terminal_up: f64,
    pub mu: f64,
    pub low_head: f64,
    pub up_head: f64,
    pub terminal_low_head: f64,
    pub terminal_up_head: f64,
}

impl ZoneSpec {
    /// A zone given in water content.
    pub fn water_content(low: f64, up: f64) -> ZoneSpec {
        ZoneSpec {
            low: Some(low),
            up: Some(up),
            ..ZoneSpec::default()
        }
    }

    /// The zone in force on `soil`, or what is wrong with it (naming the key).
    pub fn resolve(&self, soil: &VanGenuchten) -> Result<ZoneSettings, String> {
        let default = ZoneSettings::default_for(soil);
        let (r, s) = (soil.residual_water_content, soil.saturated_water_content);
        let bound =
            |name: &str, theta: Option<f64>, head: Option<f64>| -> Result<Option<f64>, String> {
                match (theta, head) {
                    (Some(_), Some(_)) => Err(format!(
                        "zone.{name} and zone.{name}_head are both given: give one form"
                    )),
                    (Some(t), None) if t.is_finite() && (r..=s).contains(&t) => Ok(Some(t)),
                    (Some(t), None) => Err(format!(
                        "zone.{name} = {t} must lie in [θr, θs] = [{r}, {s}] of the soil"
                    )),
                    (None, Some(h))
                        if h.is_finite()
                            && (ZONE_HEAD_RANGE.0..=ZONE_HEAD_RANGE.1).contains(&h) =>
                    {
                        Ok(Some(soil.water_content(h)))
                    }
                    (None, Some(h)) => Err(format!(
                        "zone.{name}_head = {h} m must lie in [{}, {}] m",
                        ZONE_HEAD_RANGE.0, ZONE_HEAD_RANGE.1
                    )),
                    (None, None) => Ok(None),
                }
            };
        let low = bound("low", self.low, self.low_head)?.unwrap_or(default.low0);
        let up = bound("up", self.up, self.up_head)?.unwrap_or(default.up0);
        let y_low =
            bound("terminal_low", self.terminal_low, self.terminal_low_head)?.unwrap_or(low);
        let y_up = bound("terminal_up", self.terminal_up, self.terminal_up_head)?.unwrap_or(up);
        let mu = self.mu.unwrap_or(0.0);
        if !(mu.is_finite() && (0.0..=10.0).contains(&mu)) {
            return Err(format!("zone.mu = {mu} must lie in [0, 10]"));
        }
        let zone = ZoneSettings {
            low0: low,
            up0: up,
            y_low,
            y_up,
            mu,
        };
        match zone.problem() {
            Some(p) => Err(format!("zone: {p}")),
            None => Ok(zone),
        }
    }

    /// Both forms of the zone in force on `soil` (the default zone if the
    /// spec is not valid there).
    pub fn effective(&self, soil: &VanGenuchten) -> EffectiveZone {
        let z = self
            .resolve(soil)
            .unwrap_or_else(|_| ZoneSettings::default_for(soil));
        let head = |theta: f64| soil.pressure_head_at(theta).max(ZONE_HEAD_RANGE.0);
        EffectiveZone {
            low: z.low0,
            up: z.up0,
            terminal_low: z.y_low,
            terminal_up: z.y_up,
            mu: z.mu,
            low_head: head(z.low0),
            up_head: head(z.up0),
            terminal_low_head: head(z.y_low),
            terminal_up_head: head(z.y_up),
        }
    }
}

/// A soil-moisture sensor: where it is, how noisy, and how its raw
/// reading becomes θ.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SensorSpec {
    /// 1 to 64 characters: letters, digits and `-._/`.
    pub id: String,
    /// Depth below the surface [m], in (0, 0.5] (the column's depth).
    pub depth: f64,
    /// Standard deviation of its θ error [m³/m³], in [0, 0.2].
    #[serde(default = "default_sensor_noise")]
    pub noise: f64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub calibration: Option<Calibration>,
}

fn default_sensor_noise() -> f64 {
    0.02
}

/// Range of a raw sensor reading (counts, millivolts, …).
pub const RAW_RANGE: (f64, f64) = (-1e9, 1e9);

/// How a sensor's raw reading becomes θ. Factory calibrations of capacitive
/// probes are off by about 5 vol %, soil-specific ones by about 1 %.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "kebab-case", deny_unknown_fields)]
pub enum Calibration {
    /// θ = slope·raw + offset.
    Linear { slope: f64, offset: f64 },
    /// Piecewise linear through (raw, θ) points, raw strictly increasing and
    /// θ strictly monotone; a raw reading outside the table is refused.
    Table { points: Vec<[f64; 2]> },
}

impl Calibration {
    /// What is wrong with it (`name` is its key), if anything.
    pub fn validate(&self, name: &str) -> Result<(), String> {
        match self {
            Calibration::Linear { slope, offset } => {
                if !(slope.is_finite() && *slope != 0.0 && slope.abs() <= 1e6) {
                    return Err(format!(
                        "{name}.slope = {slope} must be finite, non-zero (monotone) and at most 1e6 in size"
                    ));
                }
                check_range(&format!("{name}.offset"), *offset, (-1e6, 1e6))
            }
            Calibration::Table { points } => {
                if !(2..=100).contains(&points.len()) {
                    return Err(format!(
                        "{name}.points needs 2 to 100 (raw, θ) points, got {}",
                        points.len()
                    ));
                }
                for (i, [raw, theta]) in points.iter().enumerate() {
                    check_range(&format!("{name}.points[{i}] raw"), *raw, RAW_RANGE)?;
                    check_range(&format!("{name}.points[{i}] θ"), *theta, (0.0, 1.0))?;
                }
                let rising = points.windows(2).all(|w| w[1][0] > w[0][0]);
                if !rising {
                    return Err(format!(
                        "{name}.points: raw values must be strictly increasing"
                    ));
                }
                let up = points.windows(2).all(|w| w[1][1] > w[0][1]);
                let down = points.windows(2).all(|w| w[1][1] < w[0][1]);
                if !(up || down) {
                    return Err(format!(
                        "{name}.points: θ must be strictly monotone in raw (a calibration that \
                         is not monotone cannot be inverted)"
                    ));
                }
                Ok(())
            }
        }
    }

    /// θ of a raw reading, or why there is none.
    pub fn theta(&self, raw: f64) -> Result<f64, String> {
        let theta = match self {
            Calibration::Linear { slope, offset } => slope * raw + offset,
            Calibration::Table { points } => {
                let (first, last) = (points[0][0], points[points.len() - 1][0]);
                if !(first..=last).contains(&raw) {
                    return Err(format!(
                        "raw = {raw} lies outside the calibration table [{first}, {last}]"
                    ));
                }
                let i = points
                    .windows(2)
                    .position(|w| raw <= w[1][0])
                    .unwrap_or(points.len() - 2);
                let ([r0, t0], [r1, t1]) = (points[i], points[i + 1]);
                t0 + (t1 - t0) * (raw - r0) / (r1 - r0)
            }
        };
        if theta.is_finite() && (0.0..=1.0).contains(&theta) {
            Ok(theta)
        } else {
            Err(format!(
                "raw = {raw} calibrates to θ = {theta}, outside [0, 1]"
            ))
        }
    }
}

impl SensorSpec {
    /// The default sensor of a field: at the rooting depth.
    pub fn default_at(depth: f64) -> SensorSpec {
        SensorSpec {
            id: "default".into(),
            depth,
            noise: default_sensor_noise(),
            calibration: None,
        }
    }

    fn validate(&self, i: usize) -> Result<(), String> {
        let name = format!("sensors[{i}]");
        let id_ok = (1..=64).contains(&self.id.chars().count())
            && self
                .id
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || "-._/".contains(c));
        if !id_ok {
            return Err(format!(
                "{name}.id = '{}' must have 1 to 64 letters, digits or -._/",
                self.id
            ));
        }
        if !(self.depth.is_finite() && self.depth > 0.0 && self.depth <= COLUMN_DEPTH) {
            return Err(format!(
                "{name}.depth = {} m must lie in (0, {COLUMN_DEPTH}] (sensor '{}' would lie \
                 below the column)",
                self.depth, self.id
            ));
        }
        check_range(&format!("{name}.noise"), self.noise, (0.0, 0.2))?;
        if let Some(c) = &self.calibration {
            c.validate(&format!("{name}.calibration"))?;
        }
        Ok(())
    }
}

/// Depth of the simulated column [m] (MODEL.md §1).
pub const COLUMN_DEPTH: f64 = 0.5;

/// Most sensors per field (the estimator's bound, which `closed-loop`
/// keeps too).
pub use crate::estimate::MAX_SENSORS;

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
    /// Each new setpoint is POSTed to `url` (with bounded retries), signed
    /// with HMAC-SHA256 under `secret` (given, or generated at creation and
    /// returned once in the 201 body; never by a GET).
    Webhook {
        url: String,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        secret: Option<String>,
    },
}

/// The simulated plant of a field with a simulated actuator.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SimulationSpec {
    pub scenario: Scenario,
    /// The plant's true soil, when it is not the field's declared one (a
    /// texture or parameters; needed when the field's soil is `unknown`).
    /// No controller reads it: the estimator has to find it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub soil: Option<SoilSpec>,
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

impl SimulationSpec {
    /// What is wrong with the simulation section, naming the key.
    pub fn validate(&self, control_period_s: f64) -> Result<(), String> {
        for (name, v) in [
            ("process_noise", self.process_noise),
            ("measurement_noise", self.measurement_noise),
            ("forecast_error", self.forecast_error),
        ] {
            if !(v.is_finite() && (0.0..0.5).contains(&v)) {
                return Err(format!("simulation.{name} = {v} must lie in [0, 0.5)"));
            }
        }
        check_range(
            "simulation.measurement_interval_s",
            self.measurement_interval_s,
            (60.0, control_period_s.max(60.0)),
        )
        .map_err(|e| e + " (at most control_period_s)")?;
        check_range("simulation.initial_head", self.initial_head, INITIAL_HEAD)?;
        if let Some(soil) = &self.soil {
            soil.parameters()
                .map_err(|e| format!("simulation.soil: {e}"))?;
        }
        if let Some(start) = self.start {
            check_time("simulation.start", start)?;
        }
        Ok(())
    }
}

impl Default for SimulationSpec {
    fn default() -> Self {
        SimulationSpec {
            scenario: Scenario::Dry,
            soil: None,
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
            sensors: Vec::new(),
            simulation: Some(SimulationSpec::default()),
            irrigation_system: None,
            forecast_source: None,
        }
    }

    /// What is wrong with the field, if anything (the message names the key
    /// and its range).
    pub fn validate(&self) -> Result<(), String> {
        self.validate_for(false)
    }

    /// [`validate`](Self::validate) for a field that has (`own_surrogate`)
    /// a validated two-layer surrogate of its own: then model two-layer is
    /// allowed on any soil.
    pub fn validate_for(&self, own_surrogate: bool) -> Result<(), String> {
        let chars = self.name.chars().count();
        if self.name.trim().is_empty() || chars > MAX_NAME_CHARS {
            return Err(format!(
                "name must have 1 to {MAX_NAME_CHARS} characters (not only spaces), got {chars}"
            ));
        }
        if self.name.chars().any(char::is_control) {
            return Err("name must not contain control characters".into());
        }
        let soil = self.soil.nominal()?;
        if self.model != ModelKind::Richards
            && !self.soil.is_sandy_loam()
            && !(own_surrogate && self.model == ModelKind::TwoLayer)
        {
            return Err(format!(
                "model '{}' is trained for sandy-loam only; use model 'richards' for another soil",
                self.model.name()
            ));
        }
        let c = self.crop;
        check_range(
            "crop.crop_coefficient",
            c.crop_coefficient,
            CROP_COEFFICIENT,
        )?;
        if !(c.rooting_depth.is_finite() && c.rooting_depth > 0.0 && c.rooting_depth <= 0.5) {
            return Err(format!(
                "crop.rooting_depth = {} must lie in (0, 0.5] m",
                c.rooting_depth
            ));
        }
        self.zone.resolve(&soil)?;
        if !(self.irrigation_max.is_finite()
            && self.irrigation_max > 0.0
            && self.irrigation_max <= IRRIGATION_MAX.1)
        {
            return Err(format!(
                "irrigation_max = {} must lie in (0, {}] m/s",
                self.irrigation_max, IRRIGATION_MAX.1
            ));
        }
        check_range("control_period_s", self.control_period_s, CONTROL_PERIOD_S)?;
        check_range(
            "measurement_wait_s",
            self.measurement_wait_s,
            MEASUREMENT_WAIT_S,
        )?;
        if let Actuator::Webhook { url, secret } = &self.actuator {
            validate_webhook_url(url)?;
            if let Some(secret) = secret
                && !(16..=200).contains(&secret.chars().count())
            {
                return Err("actuator.secret must have 16 to 200 characters".into());
            }
        }
        if let Some(system) = &self.irrigation_system {
            system.validate()?;
        }
        if self.sensors.len() > MAX_SENSORS {
            return Err(format!(
                "sensors: at most {MAX_SENSORS}, got {}",
                self.sensors.len()
            ));
        }
        let mut ids = std::collections::HashSet::new();
        for (i, sensor) in self.sensors.iter().enumerate() {
            sensor.validate(i)?;
            if !ids.insert(sensor.id.as_str()) {
                return Err(format!("sensors[{i}].id '{}' is used twice", sensor.id));
            }
        }
        if let Some(source) = &self.forecast_source {
            source.validate()?;
        }
        match (&self.actuator, &self.simulation) {
            (Actuator::Simulated, Some(sim)) => {
                sim.validate(self.control_period_s)?;
                if self.soil.is_unknown() && sim.soil.is_none() {
                    return Err(
                        "a simulated field of soil 'unknown' needs simulation.soil, the plant's true soil"
                            .into(),
                    );
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

    /// The zone-MPC settings of this field, on its declared soil.
    pub fn mpc_settings(&self) -> MpcSettings {
        self.mpc_settings_with(None)
    }

    /// The zone-MPC settings with the estimated soil, when there is one: its
    /// [θr, θs] bound the prediction, and for a field of soil `unknown` the
    /// zone is resolved on it too (a zone in heads follows the estimate).
    pub fn mpc_settings_with(&self, estimated: Option<&VanGenuchten>) -> MpcSettings {
        let declared = self.soil.nominal().unwrap_or(VanGenuchten::SANDY_LOAM);
        let zone_soil = match estimated {
            Some(e) if self.soil.is_unknown() && self.zone.resolve(e).is_ok() => *e,
            _ => declared,
        };
        let bounds = estimated.copied().unwrap_or(declared);
        MpcSettings {
            u_max: self.irrigation_max,
            zone: self
                .zone
                .resolve(&zone_soil)
                .unwrap_or_else(|_| ZoneSettings::default_for(&zone_soil)),
            theta_r: bounds.residual_water_content,
            theta_s: bounds.saturated_water_content,
            ..MpcSettings::default()
        }
    }

    /// The sensors in force: those given, or the default one at the rooting
    /// depth. The first is the primary sensor.
    pub fn effective_sensors(&self) -> Vec<SensorSpec> {
        if self.sensors.is_empty() {
            vec![SensorSpec::default_at(self.crop.rooting_depth)]
        } else {
            self.sensors.clone()
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

impl Field {
    /// The field as the API shows it: the spec as given, with the webhook
    /// secret removed (and the webhook URL too unless `reveal_url`, for
    /// requests that carry the token), and the zone in force in both forms.
    pub fn public(&self, reveal_url: bool) -> serde_json::Value {
        let mut doc = serde_json::to_value(self).unwrap_or_default();
        if let Some(actuator) = doc.get_mut("actuator").and_then(|a| a.as_object_mut()) {
            actuator.remove("secret");
            if !reveal_url && actuator.remove("url").is_some() {
                actuator.insert("url_hidden".into(), serde_json::Value::Bool(true));
            }
        }
        let soil = self.spec.soil.nominal().unwrap_or(VanGenuchten::SANDY_LOAM);
        if let Some(obj) = doc.as_object_mut() {
            obj.insert(
                "effective_zone".into(),
                serde_json::to_value(self.spec.zone.effective(&soil)).unwrap_or_default(),
            );
        }
        doc
    }
}

/// One soil-moisture reading.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Measurement {
    pub time: DateTime<Utc>,
    /// Volumetric water content [m³/m³].
    pub theta: f64,
    /// The sensor; none for the field's primary (first) sensor.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sensor: Option<String>,
    /// The raw reading the θ was calibrated from, if the sensor sent one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub raw: Option<f64>,
    /// The noise-free θ, for the built-in simulated fields only.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub true_theta: Option<f64>,
}

/// A reading as it arrives (HTTP body or MQTT payload), its time already
/// parsed: θ or a raw value, from the named sensor or the primary one.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ReadingIn<'a> {
    pub time: DateTime<Utc>,
    pub theta: Option<f64>,
    pub raw: Option<f64>,
    pub sensor: Option<&'a str>,
}

/// Why a reading was refused: a short reason (a metrics label) and the
/// message naming the key and its range.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ReadingError {
    /// time, unknown-sensor, value, range, calibration.
    pub reason: &'static str,
    pub message: String,
}

/// The one check of an incoming reading, shared by `POST
/// …/measurements` and MQTT: the time in the years 2000 … 2199 and at most
/// `max_future_skew_s` after `now`; the sensor declared by `field` (none:
/// the primary one); exactly one of θ and raw; raw in [`RAW_RANGE`] and
/// calibrated by the sensor's calibration; θ in [0, 1]. `key` names the
/// reading in messages (`measurements[3]`, an MQTT topic). The primary
/// sensor's readings are stored without a sensor id.
pub fn check_reading(
    key: &str,
    r: ReadingIn<'_>,
    field: &Field,
    now: DateTime<Utc>,
    max_future_skew_s: f64,
) -> Result<Measurement, ReadingError> {
    let err = |reason, message| ReadingError { reason, message };
    let skew = chrono::TimeDelta::milliseconds((max_future_skew_s * 1000.0) as i64);
    if r.time > now + skew {
        return Err(err(
            "time",
            format!(
                "{key}.time = {} lies more than {max_future_skew_s} s in the future (now {})",
                r.time.to_rfc3339(),
                now.to_rfc3339()
            ),
        ));
    }
    check_time(&format!("{key}.time"), r.time).map_err(|m| err("time", m))?;
    let sensors = field.spec.effective_sensors();
    let (index, sensor) = match r.sensor {
        None => (0, &sensors[0]),
        Some(name) => match sensors.iter().enumerate().find(|(_, s)| s.id == name) {
            Some(found) => found,
            None => {
                let known: Vec<&str> = sensors.iter().map(|s| s.id.as_str()).collect();
                return Err(err(
                    "unknown-sensor",
                    format!(
                        "{key}.sensor '{name}' is not a sensor of field {}; its sensors: {}",
                        field.id,
                        known.join(", ")
                    ),
                ));
            }
        },
    };
    let theta = match (r.theta, r.raw) {
        (Some(_), Some(_)) => {
            return Err(err(
                "value",
                format!("{key} gives theta and raw: give one (raw is calibrated to θ)"),
            ));
        }
        (None, None) => return Err(err("value", format!("{key} needs theta or raw"))),
        (Some(theta), None) => theta,
        (None, Some(raw)) => {
            check_range(&format!("{key}.raw"), raw, RAW_RANGE).map_err(|m| err("range", m))?;
            let Some(calibration) = &sensor.calibration else {
                return Err(err(
                    "calibration",
                    format!(
                        "{key}.raw: sensor '{}' has no calibration; send theta",
                        sensor.id
                    ),
                ));
            };
            calibration
                .theta(raw)
                .map_err(|e| err("range", format!("{key}: sensor '{}': {e}", sensor.id)))?
        }
    };
    if !(theta.is_finite() && (0.0..=1.0).contains(&theta)) {
        return Err(err(
            "range",
            format!("{key}.theta = {theta} must lie in [0, 1]"),
        ));
    }
    Ok(Measurement {
        time: r.time,
        theta,
        sensor: (index > 0).then(|| sensor.id.clone()),
        raw: r.raw,
        true_theta: None,
    })
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
    /// What is wrong with the forecast, naming the value and its range.
    pub fn validate(&self) -> Result<(), String> {
        check_time("issued_at", self.issued_at)?;
        check_time("start", self.start)?;
        check_range("step_s", self.step_s, FORECAST_STEP_S)?;
        if self.et0_mm.len() != self.precip_mm.len() {
            return Err(format!(
                "et0_mm has {} entries but precip_mm has {}: they must be equal",
                self.et0_mm.len(),
                self.precip_mm.len()
            ));
        }
        let most = (FORECAST_SPAN_S / self.step_s).floor() as usize;
        if self.et0_mm.is_empty() || self.et0_mm.len() > most {
            return Err(format!(
                "a forecast needs 1 to {most} steps of {} s (30 days), got {}",
                self.step_s,
                self.et0_mm.len()
            ));
        }
        let hours = self.step_s / 3600.0;
        for (name, values, rate) in [
            ("et0_mm", &self.et0_mm, MAX_ET0_MM_PER_H),
            ("precip_mm", &self.precip_mm, MAX_PRECIP_MM_PER_H),
        ] {
            let most = rate * hours;
            if let Some((i, v)) = values
                .iter()
                .enumerate()
                .find(|(_, v)| !(v.is_finite() && (0.0..=most).contains(*v)))
            {
                return Err(format!(
                    "{name}[{i}] = {v} must lie in [0, {most}] mm ({rate} mm/h over a step of {} s)",
                    self.step_s
                ));
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
    /// converged | iteration-cap | work-budget | time-budget | fallback.
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
    /// Valve time, volume and pulses (fields with an `irrigation_system`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub valve: Option<super::valve::ValveSchedule>,
    /// The field's own surrogate the cycle used (its model id), when it
    /// used one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub surrogate: Option<String>,
    /// The forecast the cycle used (absent in setpoints stored before).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub forecast: Option<ForecastUsed>,
    /// Predicted θ at the end of each horizon step without any irrigation
    /// (the same model and weather as `predicted_theta`); empty when the
    /// cycle made no prediction.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub predicted_theta_dry: Vec<f64>,
    /// The rain the cycle planned with, per horizon step [mm].
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub rain_mm: Vec<f64>,
    /// The reference evapotranspiration the cycle planned with, per horizon
    /// step [mm].
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub et0_mm: Vec<f64>,
    /// Why the setpoint is what it is, in words (`service::explain`).
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub explanation: String,
}

/// Which forecast a cycle used: `source` is open-meteo or met-norway (a
/// polled provider), posted (sent to the API), simulated (a simulated
/// field's scenario) or climatology (none fresh); when it was issued and,
/// for a provider, fetched. Steps a forecast did not cover were filled from
/// the climatology (flag `default-forecast`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ForecastUsed {
    pub source: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub issued_at: Option<DateTime<Utc>>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fetched_at: Option<DateTime<Utc>>,
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

    #[test]
    fn a_field_of_unknown_soil_is_planned_on_the_mean_texture_until_estimated() {
        let unknown = FieldSpec {
            soil: SoilSpec::Preset(UNKNOWN_SOIL.into()),
            model: ModelKind::Richards,
            actuator: Actuator::None,
            simulation: None,
            ..FieldSpec::demo()
        };
        assert_eq!(unknown.validate(), Ok(()));
        // the nominal soil: the mean of the Carsel & Parrish table (θr 0.0723,
        // θs 0.4117 in arithmetic mean; Ks, α, n − 1 geometric)
        let nominal = unknown.soil.nominal().unwrap();
        assert!((nominal.residual_water_content - 0.868 / 12.0).abs() < 1e-9);
        assert!((nominal.saturated_water_content - 4.94 / 12.0).abs() < 1e-9);
        let ks: f64 = Texture::ALL
            .iter()
            .map(|t| t.parameters().saturated_conductivity.ln())
            .sum::<f64>()
            / 12.0;
        assert!((nominal.saturated_conductivity.ln() - ks).abs() < 1e-9);
        assert!(unknown.soil.parameters().is_err());
        // the default zone is the head band, on the estimated soil once there is one
        let loam = Texture::Loam.parameters();
        let z = unknown.mpc_settings_with(Some(&loam)).zone;
        assert!((z.low0 - loam.water_content(-0.43)).abs() < 1e-12, "{z:?}");
        assert!((z.up0 - loam.water_content(-0.27)).abs() < 1e-12);
        let z = unknown.mpc_settings().zone;
        assert!((z.low0 - nominal.water_content(-0.43)).abs() < 1e-12);
        // a declared soil keeps its own zone whatever the estimate
        let declared = FieldSpec {
            soil: SoilSpec::Preset("sandy-loam".into()),
            ..unknown.clone()
        };
        let z = declared.mpc_settings_with(Some(&loam)).zone;
        assert_eq!((z.low0, z.up0), (0.18, 0.23));
        // surrogates are refused; a simulated unknown field needs the plant's soil
        let two_layer = FieldSpec {
            model: ModelKind::TwoLayer,
            ..unknown.clone()
        };
        assert!(two_layer.validate().unwrap_err().contains("richards"));
        let simulated = FieldSpec {
            actuator: Actuator::Simulated,
            simulation: Some(SimulationSpec::default()),
            ..unknown.clone()
        };
        assert!(
            simulated
                .validate()
                .unwrap_err()
                .contains("simulation.soil")
        );
        let with_plant = FieldSpec {
            simulation: Some(SimulationSpec {
                soil: Some(SoilSpec::Preset("loam".into())),
                ..SimulationSpec::default()
            }),
            ..simulated.clone()
        };
        assert_eq!(with_plant.validate(), Ok(()));
        let unknown_plant = FieldSpec {
            simulation: Some(SimulationSpec {
                soil: Some(SoilSpec::Preset(UNKNOWN_SOIL.into())),
                ..SimulationSpec::default()
            }),
            ..simulated
        };
        assert!(
            unknown_plant
                .validate()
                .unwrap_err()
                .contains("simulation.soil")
        );
    }
}
