//! WSS: weighted spatiotemporal similarity against simulated edge templates
//! (Kumar et al. 2020, section 2.5; SPEC.md section 4).
//!
//! # The method
//!
//! For every class angle `θ` of the grid, templates `S_i(θ)`, `i = 0..k(θ)`, are
//! ideal images of a thin line (width `line_width_mm`) at `θ` crossing the array
//! at the known speed, one per frame hop, ordered back in time from the line
//! just leaving the array ([`templates`]; eq. 6: taxel value `exp(−d²/σ²)`).
//! Observed spike images `I_0..I_{K−1}` are matched at every alignment `k`:
//!
//! `WSS_θ(k) = Σ_{i=0}^{k(θ)} w_{k−i} R(I_{k−i}, S_i(θ)) / Σ_{i=0}^{k(θ)} w_{k−i}` (eq. 5)
//!
//! with `R` Pearson's correlation over the taxels and `w` the frame's weight
//! from its spike rate `SR = C_m / max_m C_m` (`C_m` the frame's total count):
//! `constant` (1), `one_minus_sr` (`1 − SR`, the paper's best and the default) or
//! `one_plus_sr` (`1 + SR`). The estimate is `argmax_θ max_k WSS_θ(k)` (eq. 7);
//! [`Estimate::scores`] holds every class's `max_k WSS_θ(k)`.
//!
//! # Decisions where the paper is silent
//!
//! * `R` of an image (or template) with no spatial variance is 0, never NaN
//!   (variance below 1e-20 of the image's energy counts as none: rounding).
//! * A window whose weights are all 0 falls back to constant weights.
//! * Frames before the trial's start (`k − i < 0`) are, by default, not part of
//!   either sum (`before_start = "exclude"`); `"silent"` counts them as
//!   spike-free frames instead (correlation 0, weight 1), which keeps a few busy
//!   frames at a trial's very start from scoring high on their own.
//! * `sigma_mm` defaults to 1 mm, half the paper's 2 mm taxel: a taxel's
//!   template value falls to `1/e` as the line reaches the taxel's border, the
//!   span over which an edge crossing the taxel's area makes it fire. On ideal
//!   trials this places the peak of `max_k WSS_θ` over `θ` at the true angle
//!   (to about 0.3 degrees), where 1.5 mm (half the pitch) biases it by about
//!   +1 degree and 2 mm by +2; a skin that spreads pressure widely may call for
//!   a larger value.
//! * `threshold` defaults to 0.1: an edge crossing gives best scores well above
//!   it (ideal trials: 0.3 to 0.9 depending on weighting and angle), while a
//!   trial without spatiotemporal structure averages correlations near 0.
//! * Templates are capped at `max_template_s` (120 s) of palpation, since the
//!   crossing time grows like `1/sin θ`: every angle from 3 to 177 degrees fits
//!   uncapped on the paper's array at 2 mm/s; a longer crossing keeps its last
//!   part (the line nearest leaving the array).
//! * Continuous angles: `refine = "search"` (golden-section search of
//!   `max_k WSS_θ` in `θ` between the best class's neighbours, templates built
//!   per probed angle; within a few tenths of a degree on ideal trials) or
//!   `"parabola"` (vertex through the best class and its neighbours: free, but
//!   the score falls faster towards smaller angles than larger ones, so it is
//!   biased by up to about 2 degrees on the paper's 5-degree grid); `angle_deg`
//!   then carries the refined value and `class_deg` the grid class. The default
//!   `"none"` answers the class, as the paper does.
//! * "No edge" (`angle_deg = None`): no frame has a spike, or the best score is
//!   under `threshold`.
//!
//! # Speed
//!
//! [`batch`] computes eq. 5 as FFT convolutions (one inverse FFT per class and
//! block, the taxel sum done in the frequency domain, template spectra cached);
//! [`stream`] is the frame-by-frame form ([`WssStream`]) by uniformly partitioned
//! convolution. [`wss_reference`] keeps the direct sums for tests. The inner
//! kernels use AVX2 + FMA when the CPU has them (checked at run time).
//!
//! Measured (`cargo bench --bench wss`, one core of a shared AMD EPYC, 17
//! classes, 4x4 array, 10 ms hop, 2 s holds, 2 mm/s): one trial's estimate
//! 0.58 ms (90 degrees, 941 frames), 1.3 ms (45, 1491 frames), 3.5 ms (10,
//! 4060 frames); streaming 5.8, 9.5 and 11.7 µs per frame; the direct
//! reference 580 ms for a 958-frame trial (the paper's MATLAB: 3.05 s).
//!
//! # Example
//!
//! ```
//! use palpate_stages::estimate::wss::{wss_batch, Templates, WssParams};
//! use palpate_core::{SpikeImages, TaxelLayout};
//! let params = WssParams::default();
//! let layout = TaxelLayout::paper();
//! let tpl = Templates::new(&layout, 10.0, &params).unwrap();
//! let images = SpikeImages { layout, window_ms: 100.0, hop_ms: 10.0, n_frames: 3, counts: vec![0.0; 48] };
//! let est = wss_batch(&images, &tpl, &params).unwrap();
//! assert_eq!(est.angle_deg, None); // no spikes: no edge
//! ```

pub mod batch;
pub mod params;
mod simd;
pub mod stream;
pub mod templates;
#[cfg(test)]
mod tests;

pub use batch::{pearson, wss_batch, wss_reference, wss_reference_series, wss_series};
pub use params::{AngleGrid, BeforeStart, Refine, Weighting, WssParams};
pub use stream::WssStream;
pub use templates::{raw_template, ClassTemplates, Templates};

use palpate_core::{
    register_stage, BuildContext, ConfigError, Estimate, Estimator, FitContext, InputSpec, Item, Model,
    PayloadKind, Stage, StageConfig, StageError, TrialContext,
};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::sync::{Arc, Mutex};

/// Weighted spatiotemporal similarity (WSS) edge-orientation estimator (model-based, no training).
///
/// Matches a trial's spike images against simulated templates of a line
/// crossing the array at each class angle (paper eqs. 5 to 7) and answers the
/// best class, optionally refined to a continuous angle, or "no edge".
/// Templates follow the images' layout and hop, and are built once per run.
#[derive(Clone, Debug, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct WssConfig {
    /// Sliding speed the templates assume, mm/s ("known beforehand"). Default 2.
    pub speed_mm_s: f64,
    /// Spread `σ` of eq. 6, mm. Default 1 (half the paper's 2 mm taxel).
    pub sigma_mm: f64,
    /// Width of the simulated line, mm. Default 0.2 (the paper's).
    pub line_width_mm: f64,
    /// Class angles, degrees in (0, 180): a list `[10, 20, 30]` or a range
    /// `{ from = 10, to = 90, step = 5 }` (inclusive). Default the paper's 17
    /// classes, 10 to 90 by 5.
    pub angles: AngleGrid,
    /// Frame weighting `w` of eq. 5: `constant`, `one_minus_sr` or
    /// `one_plus_sr`. Default `one_minus_sr` (the paper's best).
    pub weighting: Weighting,
    /// Best score (a weighted mean correlation, in [-1, 1]) under which the
    /// answer is "no edge". Default 0.1.
    pub threshold: f64,
    /// Continuous angle: `none` (the grid class), `parabola` or `search`.
    /// Default `none`.
    pub refine: Refine,
    /// Angle tolerance of `refine = "search"`, degrees. Default 0.05.
    pub refine_tol_deg: f64,
    /// Longest template, s of palpation (crossings near 0 or 180 degrees are
    /// long); a longer crossing keeps its last part. Default 120.
    pub max_template_s: f64,
    /// Frames before the trial's start: `exclude` (not part of the sums) or
    /// `silent` (spike-free frames: correlation 0, weight 1). Default `exclude`.
    pub before_start: BeforeStart,
    /// Stop early, frame by frame, once the best class's score leads the
    /// second best by this margin (and passes `threshold`); `decision_time_ms`
    /// then tells how much palpation was used (ms from the trial's start, to
    /// the end of the stopping frame). Default: none (whole trial).
    pub stop_margin: Option<f64>,
}

impl Default for WssConfig {
    fn default() -> Self {
        let p = WssParams::default();
        WssConfig {
            speed_mm_s: p.speed_mm_s,
            sigma_mm: p.sigma_mm,
            line_width_mm: p.line_width_mm,
            angles: AngleGrid::default(),
            weighting: p.weighting,
            threshold: p.threshold,
            refine: p.refine,
            refine_tol_deg: p.refine_tol_deg,
            max_template_s: p.max_template_s,
            before_start: p.before_start,
            stop_margin: None,
        }
    }
}

impl WssConfig {
    /// The checked parameters, or an error naming the key.
    pub fn params(&self) -> Result<WssParams, ConfigError> {
        let p = WssParams {
            speed_mm_s: self.speed_mm_s,
            sigma_mm: self.sigma_mm,
            line_width_mm: self.line_width_mm,
            angles: self.angles.resolve()?,
            weighting: self.weighting,
            threshold: self.threshold,
            refine: self.refine,
            refine_tol_deg: self.refine_tol_deg,
            max_template_s: self.max_template_s,
            before_start: self.before_start,
        };
        p.validate()?;
        if let Some(m) = self.stop_margin {
            palpate_core::check_range("stop_margin", m, 0.0, 2.0, "")?;
        }
        Ok(p)
    }
}

#[typetag::serde(name = "wss")]
impl StageConfig for WssConfig {
    fn inputs(&self) -> InputSpec {
        InputSpec::one(PayloadKind::Images)
    }
    fn output(&self) -> Option<PayloadKind> {
        Some(PayloadKind::Estimates)
    }
    fn build(&self, _ctx: &BuildContext) -> Result<Stage, ConfigError> {
        let params = self.params()?;
        Ok(Stage::Estimator(Box::new(WssEstimator {
            params,
            stop_margin: self.stop_margin,
        })))
    }
}
register_stage!("wss", WssConfig);

struct WssEstimator {
    params: WssParams,
    stop_margin: Option<f64>,
}

impl Estimator for WssEstimator {
    fn trained(&self) -> bool {
        false
    }
    fn fit(&self, _train: &[&Item], _ctx: &FitContext<'_>) -> Result<Box<dyn Model>, StageError> {
        Ok(Box::new(WssModel {
            params: self.params.clone(),
            stop_margin: self.stop_margin,
            cache: Mutex::new(HashMap::new()),
        }))
    }
}

/// The fitted (model-based) WSS: parameters and templates cached per (layout, hop).
struct WssModel {
    params: WssParams,
    stop_margin: Option<f64>,
    cache: Mutex<HashMap<(String, u64), Arc<Templates>>>,
}

impl WssModel {
    fn templates(&self, images: &palpate_core::SpikeImages) -> Result<Arc<Templates>, StageError> {
        let key = (
            serde_json::to_string(&images.layout).unwrap_or_default(),
            images.hop_ms.to_bits(),
        );
        if let Some(t) = self.cache.lock().unwrap_or_else(|e| e.into_inner()).get(&key) {
            return Ok(t.clone());
        }
        // Built outside the lock: two threads may both build the same templates
        // on first use, which costs time but never changes a result.
        let t = Arc::new(
            Templates::new(&images.layout, images.hop_ms, &self.params)
                .map_err(|e| StageError::new(format!("wss: images' {e}")))?,
        );
        let mut c = self.cache.lock().unwrap_or_else(|e| e.into_inner());
        Ok(c.entry(key).or_insert(t).clone())
    }
}

impl Model for WssModel {
    fn predict(&self, item: &Item, _ctx: &TrialContext<'_>) -> Result<Estimate, StageError> {
        let images = item.payload.images()?;
        let tpl = self.templates(images)?;
        let e = match self.stop_margin {
            None => wss_batch(images, &tpl, &self.params)?,
            Some(margin) => {
                let mut s = WssStream::new(tpl, self.params.clone(), images.window_ms)?;
                let mut stopped = None;
                for k in 0..images.n_frames {
                    let e = s.push(images.frame(k))?;
                    if e.angle_deg.is_some() && s.margin() >= margin {
                        stopped = Some(e);
                        break;
                    }
                }
                match stopped {
                    Some(e) => e,
                    None => s.estimate(),
                }
            }
        };
        // Frame ends run past the trial's end by up to a window (see the
        // decision-time rule in `estimate`).
        Ok(super::cap_decision_time(e, images))
    }
}
