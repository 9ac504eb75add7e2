//! Physical effects a scene may list, each a separate component.
//!
//! A scene lists its effects as an ordered list of tables, each with a `kind`.
//! Only listed effects are constructed (at build time) and computed (per trial);
//! an empty list gives exactly the ideal area-averaged contact response. Every
//! effect acts in one of three phases, and the list must respect their order
//! (otherwise "applied in the listed order" would be a lie):
//!
//! 1. **trial** (`variation`, `sleeve`, `tilt`): perturbs one trial's motion,
//!    placement and the pressure the array transmits;
//! 2. **field** (`skin`, `stress`): reshapes the contact pressure field before
//!    the taxels average it (these commute: the skin blurs the whole field,
//!    stress concentration included);
//! 3. **signal** (`creep`, `hysteresis`, `dynamics`, `ghosting`, `dead`,
//!    `piezo`, `mismatch`, `crosstalk`, `hum`,
//!    `noise`, `adc`): transforms the taxel signals sample by sample, strictly
//!    in the listed order. Their amounts are in the unit of the signal at their
//!    place in the list: "pressure" (1 = full contact with a flat surface)
//!    before `piezo`, volts after it.
//!
//! Randomness: per-trial draws come from a generator seeded by the trial's seed
//! (`ctx.seed`, itself from graph seed, stage id and trial id) and the effect's
//! kind and occurrence, so adding an effect never changes another's draws.
//! Properties of the physical array (gain and offset mismatch, dead taxels) are
//! drawn once at build time from the array seed, `derive_seed(graph seed,
//! [stage id, "array"])`, so they are identical in every trial.

use super::config::Scene;
use super::gauss::GaussianSource;
use super::sensor::{Dynamics, Ghosting, Hysteresis};
pub use super::sensor::{DynamicsConfig, GhostingConfig, HysteresisConfig, SleeveConfig, TiltConfig};
use palpate_core::{derive_seed, ConfigError, TaxelLayout};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// One effect of a scene's `effects` list, selected by `kind`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum EffectConfig {
    /// Trial-to-trial variation of speed, start position, force and placement angle.
    Variation(VariationConfig),
    /// The soft sleeve: thickness and friction-driven stick-slip shear (see `sensor`).
    Sleeve(SleeveConfig),
    /// End-effector tilt: a per-trial pressure gradient across the array (see `sensor`).
    Tilt(TiltConfig),
    /// Gaussian spreading of contact pressure through the soft skin.
    Skin(SkinConfig),
    /// Stress concentration just inside the object's edge.
    Stress(StressConfig),
    /// Viscoelastic creep: part of every change arrives with a delay.
    Creep(CreepConfig),
    /// Loading/unloading hysteresis and slow recovery of the cloth (see `sensor`).
    Hysteresis(HysteresisConfig),
    /// Per-taxel first-order dynamics, time constants fixed per array (see `sensor`).
    Dynamics(DynamicsConfig),
    /// Sneak-path ghosting of a passive row/column read-out (see `sensor`).
    Ghosting(GhostingConfig),
    /// Dead taxels: constant output, fixed per array.
    Dead(DeadConfig),
    /// Piezoresistive read-out: inverse, saturating pressure-to-voltage response.
    Piezo(PiezoConfig),
    /// Per-taxel gain and offset mismatch, fixed per array.
    Mismatch(MismatchConfig),
    /// Row and column crosstalk of the matrix read-out.
    Crosstalk(CrosstalkConfig),
    /// Mains hum.
    Hum(HumConfig),
    /// White Gaussian noise.
    Noise(NoiseConfig),
    /// ADC quantization and clipping.
    Adc(AdcConfig),
}

/// Trial-to-trial variation of the palpation (phase: trial). Every draw is
/// Gaussian, truncated at 3 SD, fresh in every trial.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct VariationConfig {
    /// Relative SD of the sliding speed (robot speed error), unitless. Default 0.01.
    pub speed_rel_sd: f64,
    /// SD of the start position along x (where the robot lands), mm. Default 0.2.
    pub start_sd_mm: f64,
    /// Relative SD of the normal force, which scales the contact pressure, unitless. Default 0.05.
    pub force_rel_sd: f64,
    /// SD of the object's placement angle, degrees (the label keeps the nominal angle). Default 0.5.
    pub angle_sd_deg: f64,
}

impl Default for VariationConfig {
    fn default() -> Self {
        VariationConfig {
            speed_rel_sd: 0.01,
            start_sd_mm: 0.2,
            force_rel_sd: 0.05,
            angle_sd_deg: 0.5,
        }
    }
}

/// Gaussian spreading of pressure through the soft skin (phase: field): the
/// contact field is convolved with an isotropic Gaussian before the taxels
/// average it. An elastic layer of thickness T spreads a line load over a width
/// of about T, so sigma ~ T/2. Several skins add in quadrature.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct SkinConfig {
    /// Gaussian scale of the spreading, mm. Default 0.5 (the paper's 1 mm skin).
    pub sigma_mm: f64,
}

impl Default for SkinConfig {
    fn default() -> Self {
        SkinConfig { sigma_mm: 0.5 }
    }
}

/// Stress concentration at the object's edge (phase: field). A rigid body with
/// a sharp edge pressed into an elastic layer carries a pressure peak just
/// inside its edge (the flat-punch singularity, smoothed by the layer and the
/// edge's rounding); modelled as a Gaussian ridge of pressure along the edge on
/// the object side. For a ridge stimulus, both sides of the bar get one.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct StressConfig {
    /// Peak extra pressure, relative to the contact pressure of the surface it
    /// borders, unitless. Default 0.3.
    pub peak: f64,
    /// Distance of the peak inside the edge, mm. Default 0.3.
    pub depth_mm: f64,
    /// Gaussian width of the peak, mm (> 0). Default 0.2.
    pub width_mm: f64,
}

impl Default for StressConfig {
    fn default() -> Self {
        StressConfig {
            peak: 0.3,
            depth_mm: 0.3,
            width_mm: 0.2,
        }
    }
}

/// Viscoelastic creep (phase: signal): a change of load reaches the sensor
/// partly at once and partly with first-order delay, `y = (1 - f) x + f z`,
/// `dz/dt = (x - z) / tau` (a standard-linear-solid creep response), starting
/// settled (`z = x` at the trial's start: the array was already resting).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct CreepConfig {
    /// Delayed fraction of every change, in [0, 1]. Default 0.1.
    pub fraction: f64,
    /// Relaxation time constant, s. Default 0.5.
    pub tau_s: f64,
}

impl Default for CreepConfig {
    fn default() -> Self {
        CreepConfig {
            fraction: 0.1,
            tau_s: 0.5,
        }
    }
}

/// Dead taxels (phase: signal): broken traces read a constant, fixed per array
/// (drawn from the array seed, the same in every trial).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct DeadConfig {
    /// Chance that each taxel is dead, in [0, 1]. Default 0.
    pub probability: f64,
    /// Taxels that are dead in any case (indices, row-major). Default none.
    pub taxels: Vec<usize>,
    /// What a dead taxel reads, in the signal's unit at this place in the list
    /// (before `piezo`: pressure 0 = an open circuit, read as no contact). Default 0.
    pub value: f64,
}

/// Piezoresistive read-out (phase: signal; pressure in, volts out). The
/// cloth's conductance grows with pressure as `p^exponent`; read through a
/// voltage divider the output falls from `v_open` (no contact: the divider
/// saturates) towards 0: `V = v_open / (1 + K p^exponent)` with
/// `K = v_open / v_contact - 1`, so that full contact (p = 1) reads
/// `v_contact`, as in the paper's Fig. 3(a). Negative pressure is read as 0.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct PiezoConfig {
    /// Output with no contact (saturation), V. Default 3.3.
    pub v_open: f64,
    /// Output at full contact with a flat surface (p = 1), V. Default 1.75.
    pub v_contact: f64,
    /// Exponent of the conductance's power law in pressure. Default 1.
    pub exponent: f64,
}

impl Default for PiezoConfig {
    fn default() -> Self {
        PiezoConfig {
            v_open: 3.3,
            v_contact: 1.75,
            exponent: 1.0,
        }
    }
}

/// Per-taxel gain and offset mismatch (phase: signal): `y = g_i x + o_i` with
/// `g_i ~ N(1, gain_sd)` and `o_i ~ N(0, offset_sd)`, truncated at 3 SD, drawn
/// once per array from the array seed (fixed across trials).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct MismatchConfig {
    /// Relative SD of the taxels' gains, in [0, 0.3]. Default 0.05.
    pub gain_sd: f64,
    /// SD of the taxels' offsets, in the signal's unit here. Default 0.02.
    pub offset_sd: f64,
}

impl Default for MismatchConfig {
    fn default() -> Self {
        MismatchConfig {
            gain_sd: 0.05,
            offset_sd: 0.02,
        }
    }
}

/// Row and column crosstalk of a matrix read-out (phase: signal; grid arrays
/// only). Rows and columns share conductors, so current leaks through the other
/// taxels on the same row and column: each reading blends in their mean,
/// `y_i = (1 - r - c) x_i + r mean(row others) + c mean(column others)`. A
/// uniform signal is left unchanged.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct CrosstalkConfig {
    /// Weight of the other taxels of the same row, unitless. Default 0.02.
    pub row: f64,
    /// Weight of the other taxels of the same column, unitless. Default 0.02.
    pub col: f64,
}

impl Default for CrosstalkConfig {
    fn default() -> Self {
        CrosstalkConfig { row: 0.02, col: 0.02 }
    }
}

/// Mains hum (phase: signal): `A sin(2π f t + φ)` added to every taxel, with
/// a phase drawn uniformly in each trial (the mains is not synchronized to the
/// robot).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct HumConfig {
    /// Mains frequency, Hz (50 or 60). Default 50.
    pub frequency_hz: f64,
    /// Amplitude, in the signal's unit here. Default 0.003.
    pub amplitude: f64,
}

impl Default for HumConfig {
    fn default() -> Self {
        HumConfig {
            frequency_hz: 50.0,
            amplitude: 0.003,
        }
    }
}

/// White Gaussian noise (phase: signal), independent per taxel and sample.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct NoiseConfig {
    /// Standard deviation, in the signal's unit here. Default 0.005.
    pub sigma: f64,
}

impl Default for NoiseConfig {
    fn default() -> Self {
        NoiseConfig { sigma: 0.005 }
    }
}

/// ADC quantization (phase: signal): values are clipped to `[min, max]` and
/// rounded to the nearest of the `2^bits` levels `min + k (max - min) / (2^bits - 1)`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct AdcConfig {
    /// Resolution, bits (1 to 32). Default 12 (the Cortex-M3's ADC).
    pub bits: u32,
    /// Lowest level, in the signal's unit here. Default 0.
    pub min: f64,
    /// Highest level (the reference voltage). Default 3.3.
    pub max: f64,
}

impl Default for AdcConfig {
    fn default() -> Self {
        AdcConfig {
            bits: 12,
            min: 0.0,
            max: 3.3,
        }
    }
}

/// The phase an effect acts in; a list must be ordered by phase.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum Phase {
    /// Perturbs a trial's motion and placement.
    Trial,
    /// Reshapes the contact field.
    Field,
    /// Transforms signals.
    Signal,
}

impl EffectConfig {
    /// The `kind` name.
    pub fn kind(&self) -> &'static str {
        match self {
            EffectConfig::Variation(_) => "variation",
            EffectConfig::Sleeve(_) => "sleeve",
            EffectConfig::Tilt(_) => "tilt",
            EffectConfig::Hysteresis(_) => "hysteresis",
            EffectConfig::Dynamics(_) => "dynamics",
            EffectConfig::Ghosting(_) => "ghosting",
            EffectConfig::Skin(_) => "skin",
            EffectConfig::Stress(_) => "stress",
            EffectConfig::Creep(_) => "creep",
            EffectConfig::Dead(_) => "dead",
            EffectConfig::Piezo(_) => "piezo",
            EffectConfig::Mismatch(_) => "mismatch",
            EffectConfig::Crosstalk(_) => "crosstalk",
            EffectConfig::Hum(_) => "hum",
            EffectConfig::Noise(_) => "noise",
            EffectConfig::Adc(_) => "adc",
        }
    }

    /// The phase it acts in.
    pub fn phase(&self) -> Phase {
        match self {
            EffectConfig::Variation(_) | EffectConfig::Sleeve(_) | EffectConfig::Tilt(_) => Phase::Trial,
            EffectConfig::Skin(_) | EffectConfig::Stress(_) => Phase::Field,
            _ => Phase::Signal,
        }
    }
}

/// A per-trial perturbation of the palpation, accumulated over `variation` effects.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TrialDraw {
    /// Added to the edge's angle, degrees.
    pub dtheta_deg: f64,
    /// Multiplies the speed.
    pub speed_factor: f64,
    /// Added to the start position along x, mm.
    pub dx_mm: f64,
    /// Multiplies the contact pressure.
    pub force: f64,
}

impl Default for TrialDraw {
    fn default() -> Self {
        TrialDraw {
            dtheta_deg: 0.0,
            speed_factor: 1.0,
            dx_mm: 0.0,
            force: 1.0,
        }
    }
}

/// The contact field's shape, accumulated over field effects.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct FieldSpec {
    /// Gaussian blur scale, mm (skins add in quadrature).
    pub sigma_mm: f64,
    /// Stress concentrations: (peak, depth mm, width mm).
    pub stress: Vec<(f64, f64, f64)>,
}

/// What a signal effect knows about the trial it processes.
#[derive(Clone, Debug)]
pub struct TrialInfo<'a> {
    /// Samples per second.
    pub sample_rate_hz: f64,
    /// Samples in the trial.
    pub n_samples: usize,
    /// The array.
    pub layout: &'a TaxelLayout,
}

/// A block of samples of every taxel: `data[taxel * len + k]` is sample
/// `start + k` of `taxel`.
pub struct Block<'a> {
    /// Taxel-major samples.
    pub data: &'a mut [f64],
    /// Samples per taxel in this block.
    pub len: usize,
    /// Index of the block's first sample in the trial.
    pub start: usize,
}

impl Block<'_> {
    /// Number of taxels.
    pub fn n_taxels(&self) -> usize {
        self.data.len().checked_div(self.len).unwrap_or(0)
    }
}

/// A signal effect's state over one trial; `process` is called on consecutive
/// blocks.
pub trait SignalState {
    /// Transforms one block in place.
    fn process(&mut self, block: &mut Block<'_>);
}

/// A signal-phase effect, built once per stage.
pub trait SignalEffect: Send + Sync {
    /// The effect's kind.
    fn kind(&self) -> &'static str;
    /// The unit of the signal after this effect.
    fn unit_after(&self, unit: &str) -> String {
        unit.to_string()
    }
    /// Starts processing one trial, with the effect's own generator.
    fn start<'a>(&'a self, info: &TrialInfo<'_>, rng: ChaCha8Rng) -> Box<dyn SignalState + 'a>;
}

/// The effects of a scene, built.
pub struct BuiltEffects {
    /// Variation effects.
    pub variations: Vec<VariationConfig>,
    /// Sleeve effects, each with its occurrence number.
    pub sleeves: Vec<(SleeveConfig, usize)>,
    /// Tilt effects, each with its occurrence number.
    pub tilts: Vec<(TiltConfig, usize)>,
    /// The field's shape.
    pub field: FieldSpec,
    /// Signal effects, in order, each with its kind's occurrence number (its
    /// random stream's label).
    pub signal: Vec<(Box<dyn SignalEffect>, usize)>,
}

#[cfg(test)]
thread_local! {
    /// Every effect constructed or run on this thread, for the test proving that
    /// unlisted effects are never constructed nor computed.
    pub(crate) static LOG: std::cell::RefCell<Vec<String>> = const { std::cell::RefCell::new(Vec::new()) };
}

/// Records an event for the unlisted-effects test (no-op outside tests).
#[inline]
pub(crate) fn log_event(_event: &str, _kind: &str) {
    #[cfg(test)]
    LOG.with(|l| l.borrow_mut().push(format!("{_event}:{_kind}")));
}

fn key(i: usize, k: &str) -> String {
    format!("effects[{i}].{k}")
}

fn check(i: usize, k: &str, v: f64, lo: f64, hi: f64, unit: &str) -> Result<f64, ConfigError> {
    palpate_core::check_range(&key(i, k), v, lo, hi, unit)
}

/// A Gaussian draw truncated at 3 SD (clamped, so extreme draws stay bounded
/// and the margins computed from 3 SD hold).
pub fn normal3(rng: &mut ChaCha8Rng, sd: f64) -> f64 {
    let z: f64 = StandardNormal.sample(rng);
    sd * z.clamp(-3.0, 3.0)
}

/// The generator of the `occurrence`-th effect of `kind` for a trial or array seed.
pub fn stream(seed: u64, kind: &str, occurrence: usize) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(derive_seed(seed, &[kind, &occurrence.to_string()]))
}

/// Builds the listed effects: checks every value (errors name
/// `effects[i].key`), checks the phase order, and draws the array's fixed
/// properties from `array_seed`.
pub fn build(scene: &Scene, array_seed: u64) -> Result<BuiltEffects, ConfigError> {
    let mut built = BuiltEffects {
        variations: Vec::new(),
        sleeves: Vec::new(),
        tilts: Vec::new(),
        field: FieldSpec::default(),
        signal: Vec::new(),
    };
    let mut counts: std::collections::BTreeMap<&str, usize> = Default::default();
    let mut last = (Phase::Trial, 0usize, "");
    let n_taxels = scene.layout.len();
    let mut sigma2 = 0.0;
    // Where `piezo` turned pressure into volts: effects about pressure and
    // conductance must come before it.
    let mut piezo_at: Option<usize> = None;
    for (i, e) in scene.effects.iter().enumerate() {
        let kind = e.kind();
        if e.phase() < last.0 {
            return Err(ConfigError::key(
                format!("effects[{i}]"),
                format!(
                    "`{kind}` acts on the {} and must be listed before `{}` (effects[{}]), which acts on the {}",
                    phase_name(e.phase()),
                    last.2,
                    last.1,
                    phase_name(last.0)
                ),
            ));
        }
        last = (e.phase(), i, kind);
        let occ = counts.entry(kind).or_insert(0);
        let occurrence = *occ;
        *occ += 1;
        log_event("build", kind);
        let rng = || stream(array_seed, kind, occurrence);
        match e {
            EffectConfig::Variation(c) => {
                check(i, "speed_rel_sd", c.speed_rel_sd, 0.0, 0.3, "")?;
                check(i, "start_sd_mm", c.start_sd_mm, 0.0, 100.0, "mm")?;
                check(i, "force_rel_sd", c.force_rel_sd, 0.0, 0.3, "")?;
                check(i, "angle_sd_deg", c.angle_sd_deg, 0.0, 10.0, "degrees")?;
                built.variations.push(c.clone());
            }
            EffectConfig::Sleeve(c) => {
                check(i, "thickness_mm", c.thickness_mm, 0.0, 100.0, "mm")?;
                check(i, "shear_modulus_kpa", c.shear_modulus_kpa, 1e-3, 1e7, "kPa")?;
                check(i, "pressure_kpa", c.pressure_kpa, 0.0, 1e5, "kPa")?;
                check(i, "friction_static", c.friction_static, 0.0, 10.0, "")?;
                check(
                    i,
                    "friction_kinetic",
                    c.friction_kinetic,
                    0.0,
                    c.friction_static,
                    "",
                )?;
                check(i, "threshold_sd", c.threshold_sd, 0.0, 0.3, "")?;
                check(i, "pressure_coupling", c.pressure_coupling, 0.0, 1.0, "")?;
                // The shear moves the pattern; beyond 10 mm the model is meaningless.
                check(
                    i,
                    "friction_static",
                    c.u_max(),
                    0.0,
                    10.0,
                    "mm of shear (mu_s p T / G at 3 SD)",
                )?;
                sigma2 += (c.thickness_mm / 2.0).powi(2);
                built.sleeves.push((c.clone(), occurrence));
            }
            EffectConfig::Tilt(c) => {
                check(i, "mean_x_per_mm", c.mean_x_per_mm, -1.0, 1.0, "per mm")?;
                check(i, "mean_y_per_mm", c.mean_y_per_mm, -1.0, 1.0, "per mm")?;
                check(i, "sd_per_mm", c.sd_per_mm, 0.0, 1.0, "per mm")?;
                built.tilts.push((c.clone(), occurrence));
            }
            EffectConfig::Hysteresis(c) => {
                before_piezo(i, kind, piezo_at)?;
                check(i, "fraction", c.fraction, 0.0, 1.0, "")?;
                palpate_core::check_positive(&key(i, "tau_s"), c.tau_s, "s")?;
                built.signal.push((Box::new(Hysteresis(c.clone())), occurrence));
            }
            EffectConfig::Dynamics(c) => {
                palpate_core::check_positive(&key(i, "tau_s"), c.tau_s, "s")?;
                check(i, "tau_s", c.tau_s, 0.0, 1e4, "s")?;
                check(i, "log_sd", c.log_sd, 0.0, 2.0, "")?;
                let mut r = rng();
                built
                    .signal
                    .push((Box::new(Dynamics::draw(c, n_taxels, &mut r)), occurrence));
            }
            EffectConfig::Ghosting(c) => {
                before_piezo(i, kind, piezo_at)?;
                check(i, "sneak", c.sneak, 0.0, 1.0, "")?;
                let Some((rows, cols)) = scene.layout.grid() else {
                    return Err(ConfigError::key(
                        key(i, "kind"),
                        "ghosting needs a grid array (`array`): it follows rows and columns",
                    ));
                };
                built.signal.push((
                    Box::new(Ghosting {
                        sneak: c.sneak,
                        rows,
                        cols,
                    }),
                    occurrence,
                ));
            }
            EffectConfig::Skin(c) => {
                check(i, "sigma_mm", c.sigma_mm, 0.0, 100.0, "mm")?;
                sigma2 += c.sigma_mm * c.sigma_mm;
            }
            EffectConfig::Stress(c) => {
                check(i, "peak", c.peak, 0.0, 100.0, "")?;
                check(i, "depth_mm", c.depth_mm, 0.0, 100.0, "mm")?;
                check(i, "width_mm", c.width_mm, 1e-6, 100.0, "mm")?;
                built.field.stress.push((c.peak, c.depth_mm, c.width_mm));
            }
            EffectConfig::Creep(c) => {
                check(i, "fraction", c.fraction, 0.0, 1.0, "")?;
                palpate_core::check_positive(&key(i, "tau_s"), c.tau_s, "s")?;
                built.signal.push((Box::new(Creep(c.clone())), occurrence));
            }
            EffectConfig::Dead(c) => {
                check(i, "probability", c.probability, 0.0, 1.0, "")?;
                check(i, "value", c.value, -1e12, 1e12, "")?;
                let mut dead = vec![false; n_taxels];
                for &t in &c.taxels {
                    if t >= n_taxels {
                        return Err(ConfigError::key(
                            key(i, "taxels"),
                            format!(
                                "taxel {t} does not exist: the array has {n_taxels} taxels (0 to {})",
                                n_taxels - 1
                            ),
                        ));
                    }
                    dead[t] = true;
                }
                let mut r = rng();
                for d in dead.iter_mut() {
                    // Draw for every taxel, so the draws do not depend on `taxels`.
                    let hit = r.random::<f64>() < c.probability;
                    *d |= hit;
                }
                built
                    .signal
                    .push((Box::new(Dead { dead, value: c.value }), occurrence));
            }
            EffectConfig::Piezo(c) => {
                piezo_at.get_or_insert(i);
                palpate_core::check_positive(&key(i, "v_open"), c.v_open, "V")?;
                check(i, "v_contact", c.v_contact, f64::MIN_POSITIVE, c.v_open, "V")?;
                if c.v_contact >= c.v_open {
                    return Err(ConfigError::key(
                        key(i, "v_contact"),
                        format!(
                            "must be below v_open ({} V): the output falls with pressure",
                            c.v_open
                        ),
                    ));
                }
                check(i, "exponent", c.exponent, 0.05, 20.0, "")?;
                built.signal.push((
                    Box::new(Piezo {
                        v_open: c.v_open,
                        k: c.v_open / c.v_contact - 1.0,
                        exponent: c.exponent,
                    }),
                    occurrence,
                ));
            }
            EffectConfig::Mismatch(c) => {
                check(i, "gain_sd", c.gain_sd, 0.0, 0.3, "")?;
                check(i, "offset_sd", c.offset_sd, 0.0, 1e9, "")?;
                let mut r = rng();
                let gain: Vec<f64> = (0..n_taxels).map(|_| 1.0 + normal3(&mut r, c.gain_sd)).collect();
                let offset: Vec<f64> = (0..n_taxels).map(|_| normal3(&mut r, c.offset_sd)).collect();
                built
                    .signal
                    .push((Box::new(Mismatch { gain, offset }), occurrence));
            }
            EffectConfig::Crosstalk(c) => {
                check(i, "row", c.row, 0.0, 0.5, "")?;
                check(i, "col", c.col, 0.0, 0.5, "")?;
                let Some((rows, cols)) = scene.layout.grid() else {
                    return Err(ConfigError::key(
                        key(i, "kind"),
                        "row/column crosstalk needs a grid array (`array`), not an explicit `layout`",
                    ));
                };
                built.signal.push((
                    Box::new(Crosstalk {
                        row: c.row,
                        col: c.col,
                        rows,
                        cols,
                    }),
                    occurrence,
                ));
            }
            EffectConfig::Hum(c) => {
                check(i, "frequency_hz", c.frequency_hz, 0.0, 1e6, "Hz")?;
                check(i, "amplitude", c.amplitude, 0.0, 1e9, "")?;
                built.signal.push((Box::new(Hum(c.clone())), occurrence));
            }
            EffectConfig::Noise(c) => {
                check(i, "sigma", c.sigma, 0.0, 1e9, "")?;
                built.signal.push((Box::new(Noise(c.sigma)), occurrence));
            }
            EffectConfig::Adc(c) => {
                if !(1..=32).contains(&c.bits) {
                    return Err(ConfigError::key(
                        key(i, "bits"),
                        format!("must lie in 1 to 32, got {}", c.bits),
                    ));
                }
                check(i, "min", c.min, -1e12, 1e12, "")?;
                check(i, "max", c.max, -1e12, 1e12, "")?;
                if c.max <= c.min {
                    return Err(ConfigError::key(
                        key(i, "max"),
                        format!("must exceed min ({})", c.min),
                    ));
                }
                let levels = ((1u64 << c.bits) - 1) as f64;
                built.signal.push((
                    Box::new(Adc {
                        min: c.min,
                        step: (c.max - c.min) / levels,
                        levels,
                    }),
                    occurrence,
                ));
            }
        }
    }
    built.field.sigma_mm = sigma2.sqrt();
    Ok(built)
}

fn before_piezo(i: usize, kind: &str, piezo_at: Option<usize>) -> Result<(), ConfigError> {
    match piezo_at {
        Some(j) => Err(ConfigError::key(
            format!("effects[{i}]"),
            format!("`{kind}` acts on pressure and must be listed before `piezo` (effects[{j}]), which turns it into volts"),
        )),
        None => Ok(()),
    }
}

fn phase_name(p: Phase) -> &'static str {
    match p {
        Phase::Trial => "trial's motion",
        Phase::Field => "contact field",
        Phase::Signal => "taxel signals",
    }
}

/// Draws one trial's perturbation from the `variation` effects.
pub fn draw_trial(variations: &[VariationConfig], trial_seed: u64) -> TrialDraw {
    let mut d = TrialDraw::default();
    for (j, v) in variations.iter().enumerate() {
        log_event("run", "variation");
        let mut r = stream(trial_seed, "variation", j);
        // Fixed draw order, each draw made even at SD 0, so changing one SD never
        // changes the others' values.
        let speed = normal3(&mut r, v.speed_rel_sd);
        let dx = normal3(&mut r, v.start_sd_mm);
        let force = normal3(&mut r, v.force_rel_sd);
        let angle = normal3(&mut r, v.angle_sd_deg);
        d.speed_factor *= 1.0 + speed;
        d.dx_mm += dx;
        d.force *= 1.0 + force;
        d.dtheta_deg += angle;
    }
    d
}

struct Creep(CreepConfig);

struct CreepState {
    keep: f64,
    alpha: f64,
    fraction: f64,
    z: Vec<f64>,
    started: bool,
}

impl SignalEffect for Creep {
    fn kind(&self) -> &'static str {
        "creep"
    }
    fn start<'a>(&'a self, info: &TrialInfo<'_>, _rng: ChaCha8Rng) -> Box<dyn SignalState + 'a> {
        log_event("run", "creep");
        // Exact discretization of dz/dt = (x - z)/tau for x held over a sample.
        let alpha = 1.0 - (-1.0 / (self.0.tau_s * info.sample_rate_hz)).exp();
        Box::new(CreepState {
            keep: 1.0 - self.0.fraction,
            alpha,
            fraction: self.0.fraction,
            z: vec![0.0; info.layout.len()],
            started: false,
        })
    }
}

impl SignalState for CreepState {
    fn process(&mut self, b: &mut Block<'_>) {
        // Pure arithmetic: compiled for AVX2 where the CPU has it (same bits).
        crate::wide::with_avx2(
            #[inline(always)]
            || {
                let len = b.len;
                if !self.started {
                    for (i, row) in b.data.chunks_exact(len).enumerate() {
                        self.z[i] = row[0];
                    }
                    self.started = true;
                }
                let (keep, alpha, frac) = (self.keep, self.alpha, self.fraction);
                // Four taxels at a time: four independent recurrences hide each
                // other's latency.
                let mut rows = b.data.chunks_exact_mut(len).enumerate().peekable();
                while rows.peek().is_some() {
                    let group: Vec<(usize, &mut [f64])> = rows.by_ref().take(4).collect();
                    if group.len() == 4 {
                        let mut it = group.into_iter();
                        let (i0, r0) = it.next().expect("4 rows");
                        let (_, r1) = it.next().expect("4 rows");
                        let (_, r2) = it.next().expect("4 rows");
                        let (_, r3) = it.next().expect("4 rows");
                        let mut z = [self.z[i0], self.z[i0 + 1], self.z[i0 + 2], self.z[i0 + 3]];
                        for k in 0..len {
                            let x = [r0[k], r1[k], r2[k], r3[k]];
                            for j in 0..4 {
                                z[j] += alpha * (x[j] - z[j]);
                            }
                            r0[k] = keep * x[0] + frac * z[0];
                            r1[k] = keep * x[1] + frac * z[1];
                            r2[k] = keep * x[2] + frac * z[2];
                            r3[k] = keep * x[3] + frac * z[3];
                        }
                        self.z[i0..i0 + 4].copy_from_slice(&z);
                    } else {
                        for (i, row) in group {
                            let mut z = self.z[i];
                            for x in row.iter_mut() {
                                z += alpha * (*x - z);
                                *x = keep * *x + frac * z;
                            }
                            self.z[i] = z;
                        }
                    }
                }
            },
        )
    }
}

struct Dead {
    dead: Vec<bool>,
    value: f64,
}

impl SignalEffect for Dead {
    fn kind(&self) -> &'static str {
        "dead"
    }
    fn start<'a>(&'a self, _info: &TrialInfo<'_>, _rng: ChaCha8Rng) -> Box<dyn SignalState + 'a> {
        log_event("run", "dead");
        Box::new(DeadState(self))
    }
}

struct DeadState<'a>(&'a Dead);

impl SignalState for DeadState<'_> {
    fn process(&mut self, b: &mut Block<'_>) {
        let len = b.len;
        for (row, &dead) in b.data.chunks_exact_mut(len).zip(&self.0.dead) {
            if dead {
                row.fill(self.0.value);
            }
        }
    }
}

struct Piezo {
    v_open: f64,
    k: f64,
    exponent: f64,
}

impl SignalEffect for Piezo {
    fn kind(&self) -> &'static str {
        "piezo"
    }
    fn unit_after(&self, _unit: &str) -> String {
        "V".into()
    }
    fn start<'a>(&'a self, _info: &TrialInfo<'_>, _rng: ChaCha8Rng) -> Box<dyn SignalState + 'a> {
        log_event("run", "piezo");
        Box::new(PiezoState(self))
    }
}

struct PiezoState<'a>(&'a Piezo);

impl SignalState for PiezoState<'_> {
    fn process(&mut self, b: &mut Block<'_>) {
        // Pure arithmetic: compiled for AVX2 where the CPU has it (same bits).
        crate::wide::with_avx2(
            #[inline(always)]
            || {
                let Piezo { v_open, k, exponent } = *self.0;
                if exponent == 1.0 {
                    for x in b.data.iter_mut() {
                        *x = v_open / (1.0 + k * x.max(0.0));
                    }
                } else {
                    for x in b.data.iter_mut() {
                        *x = v_open / (1.0 + k * x.max(0.0).powf(exponent));
                    }
                }
            },
        )
    }
}

struct Mismatch {
    gain: Vec<f64>,
    offset: Vec<f64>,
}

impl SignalEffect for Mismatch {
    fn kind(&self) -> &'static str {
        "mismatch"
    }
    fn start<'a>(&'a self, _info: &TrialInfo<'_>, _rng: ChaCha8Rng) -> Box<dyn SignalState + 'a> {
        log_event("run", "mismatch");
        Box::new(MismatchState(self))
    }
}

struct MismatchState<'a>(&'a Mismatch);

impl SignalState for MismatchState<'_> {
    fn process(&mut self, b: &mut Block<'_>) {
        // Pure arithmetic: compiled for AVX2 where the CPU has it (same bits).
        crate::wide::with_avx2(
            #[inline(always)]
            || {
                let len = b.len;
                for (i, row) in b.data.chunks_exact_mut(len).enumerate() {
                    let (g, o) = (self.0.gain[i], self.0.offset[i]);
                    for x in row.iter_mut() {
                        *x = g * *x + o;
                    }
                }
            },
        )
    }
}

struct Crosstalk {
    row: f64,
    col: f64,
    rows: usize,
    cols: usize,
}

impl SignalEffect for Crosstalk {
    fn kind(&self) -> &'static str {
        "crosstalk"
    }
    fn start<'a>(&'a self, _info: &TrialInfo<'_>, _rng: ChaCha8Rng) -> Box<dyn SignalState + 'a> {
        log_event("run", "crosstalk");
        Box::new(CrosstalkState {
            fx: self,
            row_sum: Vec::new(),
            col_sum: Vec::new(),
        })
    }
}

struct CrosstalkState<'a> {
    fx: &'a Crosstalk,
    row_sum: Vec<f64>,
    col_sum: Vec<f64>,
}

impl SignalState for CrosstalkState<'_> {
    fn process(&mut self, b: &mut Block<'_>) {
        // Pure arithmetic: compiled for AVX2 where the CPU has it (same bits).
        crate::wide::with_avx2(
            #[inline(always)]
            || {
                let Crosstalk { row, col, rows, cols } = *self.fx;
                let len = b.len;
                self.row_sum.clear();
                self.row_sum.resize(rows * len, 0.0);
                self.col_sum.clear();
                self.col_sum.resize(cols * len, 0.0);
                for (i, x) in b.data.chunks_exact(len).enumerate() {
                    let (r, c) = (i / cols, i % cols);
                    for (s, v) in self.row_sum[r * len..(r + 1) * len].iter_mut().zip(x) {
                        *s += v;
                    }
                    for (s, v) in self.col_sum[c * len..(c + 1) * len].iter_mut().zip(x) {
                        *s += v;
                    }
                }
                // With a single taxel in a row (or column) there are no others to leak
                // from: that weight stays on the taxel itself.
                let (wr, wc) = (if cols > 1 { row } else { 0.0 }, if rows > 1 { col } else { 0.0 });
                let (nr, nc) = ((cols.max(2) - 1) as f64, (rows.max(2) - 1) as f64);
                // x' = (1 - wr - wc) v + wr (rs - v) / nr + wc (cs - v) / nc, with the
                // divisions hoisted: three multiply-adds per sample.
                let (br, bc) = (wr / nr, wc / nc);
                let a = 1.0 - wr - wc - br - bc;
                for (i, x) in b.data.chunks_exact_mut(len).enumerate() {
                    let (r, c) = (i / cols, i % cols);
                    let rs = &self.row_sum[r * len..(r + 1) * len];
                    let cs = &self.col_sum[c * len..(c + 1) * len];
                    for ((v, &rk), &ck) in x.iter_mut().zip(rs).zip(cs) {
                        *v = a * *v + br * rk + bc * ck;
                    }
                }
            },
        )
    }
}

struct Hum(HumConfig);

struct HumState {
    amplitude: f64,
    omega: f64,
    phase: f64,
    wave: Vec<f64>,
}

impl SignalEffect for Hum {
    fn kind(&self) -> &'static str {
        "hum"
    }
    fn start<'a>(&'a self, info: &TrialInfo<'_>, mut rng: ChaCha8Rng) -> Box<dyn SignalState + 'a> {
        log_event("run", "hum");
        Box::new(HumState {
            amplitude: self.0.amplitude,
            omega: std::f64::consts::TAU * self.0.frequency_hz / info.sample_rate_hz,
            phase: rng.random::<f64>() * std::f64::consts::TAU,
            wave: Vec::new(),
        })
    }
}

impl SignalState for HumState {
    fn process(&mut self, b: &mut Block<'_>) {
        // Pure arithmetic: compiled for AVX2 where the CPU has it (same bits).
        crate::wide::with_avx2(
            #[inline(always)]
            || {
                let len = b.len;
                // One sine per sample, shared by every taxel: the exact phase at the
                // block's start, then a rotation recurrence (error ~1e-13 over a block).
                let phi0 = (self.phase + self.omega * b.start as f64) % std::f64::consts::TAU;
                let (mut s, mut c) = phi0.sin_cos();
                let (sd, cd) = self.omega.sin_cos();
                self.wave.clear();
                for _ in 0..len {
                    self.wave.push(self.amplitude * s);
                    let s2 = s * cd + c * sd;
                    c = c * cd - s * sd;
                    s = s2;
                }
                for row in b.data.chunks_exact_mut(len) {
                    for (x, w) in row.iter_mut().zip(&self.wave) {
                        *x += w;
                    }
                }
            },
        )
    }
}

struct Noise(f64);

struct NoiseState {
    sigma: f64,
    source: GaussianSource,
}

impl SignalEffect for Noise {
    fn kind(&self) -> &'static str {
        "noise"
    }
    fn start<'a>(&'a self, _info: &TrialInfo<'_>, mut rng: ChaCha8Rng) -> Box<dyn SignalState + 'a> {
        log_event("run", "noise");
        Box::new(NoiseState {
            sigma: self.0,
            source: GaussianSource::new(&mut rng),
        })
    }
}

impl SignalState for NoiseState {
    fn process(&mut self, b: &mut Block<'_>) {
        self.source.add_scaled(b.data, self.sigma);
    }
}

struct Adc {
    min: f64,
    step: f64,
    levels: f64,
}

impl SignalEffect for Adc {
    fn kind(&self) -> &'static str {
        "adc"
    }
    fn start<'a>(&'a self, _info: &TrialInfo<'_>, _rng: ChaCha8Rng) -> Box<dyn SignalState + 'a> {
        log_event("run", "adc");
        Box::new(AdcState(self))
    }
}

struct AdcState<'a>(&'a Adc);

impl SignalState for AdcState<'_> {
    fn process(&mut self, b: &mut Block<'_>) {
        // Pure arithmetic: compiled for AVX2 where the CPU has it (same bits).
        crate::wide::with_avx2(
            #[inline(always)]
            || {
                let Adc { min, step, levels } = *self.0;
                let inv = 1.0 / step;
                // Adding and subtracting 1.5 * 2^52 rounds a double below 2^51 to the
                // nearest integer (ties to even) with two vectorizable additions.
                const ROUND: f64 = 6_755_399_441_055_744.0;
                for x in b.data.iter_mut() {
                    // `max` ignores NaN: a NaN sample reads as the lowest level.
                    let code = ((*x - min) * inv).max(0.0).min(levels);
                    *x = min + ((code + ROUND) - ROUND) * step;
                }
            },
        )
    }
}

/// The quantization grid of an ADC config: `(min, step, levels)`.
pub fn adc_grid(c: &AdcConfig) -> (f64, f64, u64) {
    let levels = (1u64 << c.bits) - 1;
    (c.min, (c.max - c.min) / levels as f64, levels)
}
