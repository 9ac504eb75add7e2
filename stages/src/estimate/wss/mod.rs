//! WSS: weighted spatiotemporal similarity against simulated edge templates
//! (Kumar et al. 2020, section 2.5).
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
//! `constant` (1), `one_minus_sr` (`1 − SR`, the paper's best) or
//! `one_plus_sr` (`1 + SR`); the default is `constant` (see below). The estimate is `argmax_θ max_k WSS_θ(k)` (eq. 7);
//! [`Estimate::scores`] holds every class's `max_k WSS_θ(k)`.
//!
//! # Decisions where the paper is silent
//!
//! * `R` of an image (or template) with no spatial variance is 0, never NaN
//!   (variance below 1e-20 of the image's energy counts as none: rounding).
//! * A window whose weights are all 0 falls back to constant weights.
//! * Frames before the trial's start (`k − i < 0`) are, by default, counted as
//!   spike-free frames (`before_start = "silent"`: correlation 0, weight 1), so a
//!   window holding only `m` real frames scores at most `m / k(θ)` of a full
//!   one and a few busy frames at a trial's very start cannot win on their own.
//!   `"exclude"` leaves them out of both sums (a window of one frame is then a
//!   plain correlation, up to 1): on simulated lab trials a start-of-trial
//!   burst then won 1 trial in 510 at 2 mm/s and 15 in 510 on a 3x3 array,
//!   with errors of 40 to 165 degrees.
//! * `distance = "area"` averages `exp(−d²/σ²)` over each taxel's square (the
//!   default `"centre"` reads eq. 6 literally; see [`Distance`]).
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
//!   per probed angle; an end class of the grid searches out to half-way to 0
//!   or 180 degrees) or `"parabola"` (vertex through the best class and its
//!   neighbours: free, but the score falls faster towards smaller angles than
//!   larger ones, so it is biased by up to about 2 degrees on the 5-degree
//!   grid); `angle_deg` then carries the refined value and `class_deg` the
//!   grid class. The default `"none"` answers the class, as the paper does.
//!   Measured bias of the search on the ideal scene (constant weights, one
//!   trial per angle, `palpate run graphs/quickstart.toml` with
//!   `scenes/ideal.toml`, `refine=search`): `+1.9·sin 2θ` degrees, towards 90
//!   (45 -> 46.83, 136.4 -> 134.5, 23.4 -> 23.99), the same with `sigma_mm`
//!   0.5, 0.7, 1 or 1.5 and with `distance = "area"`: a property of the
//!   spike images' timing, not of the template's shape. It acts like a
//!   declared speed ~3 % too low (`speed_mm_s = 2.13` flips its sign); the
//!   joint speed search does not remove it (it trades angle for speed along
//!   `v·sin θ`). On the lab scene it gives 0.73 ± 0.19 degrees MAE over 13
//!   off-grid angles and 5 seeds, one seed at 1.11 (`palpate run
//!   graphs/continuous.toml`, the `search` point; `timing`: 0.43 ± 0.07).
//!   Its cause is the ends of the crossing, not the middle: the score of an
//!   ideal 45-degree trial over classes 43 to 49 by 0.1 (`refine = "none"`,
//!   `angles = { from = 43, to = 49, step = 0.1 }`, a `write_estimates`
//!   sink) rises smoothly to 46.8 (0.9668) and then falls along another
//!   curve (46.9: 0.9664, 47: 0.9650): a kink, not a smooth peak. At 45 the
//!   best alignment pairs the template's first ~27 frames (the line over
//!   the last corner taxel) with spike-free frames, whose correlation is 0:
//!   the encoder needs the edge well onto a corner taxel before it fires, so
//!   the observed activity is shorter than the template's span. Eq. 5
//!   divides by the template's length `k(θ) + 1`, so a faster template (an
//!   angle nearer 90) that drops those frames scores higher, up to where its
//!   length equals the activity's: the kink. Near 90 degrees the length
//!   barely changes with `θ`, and the opposite end effect (activity that
//!   outlasts the template: the low-pass tail and the 100 ms bins) is what
//!   is left. Dividing by a fixed length instead (the sum of eq. 5's
//!   numerator) or comparing every probed angle on the same interior
//!   frames of the best class's match removes most of the bias at 20 to 70
//!   degrees but moves 84.1 by about −1.2 degrees; neither is the default.
//! * The same end effect on smaller arrays reaches the class itself: the
//!   activity is a larger share shorter than the template's span when there
//!   are fewer taxels to cross. On the ideal scene with constant weighting,
//!   one trial per class 10 to 90 by 5 (`palpate run graphs/quickstart.toml`
//!   with `file` set to `scenes/ideal.toml`, `--set
//!   stages.scene.trials_per_angle=1 --set 'stages.wss.weighting="constant"'
//!   --set stages.scene.array.rows=R --set stages.scene.array.cols=C`), every
//!   class is exact on 4 x 4, 5 x 5 and 6 x 6 arrays, but 5 of 17 go one
//!   class (5 degrees) towards 90 on 3 x 3 (45 to 75), 2 on 3 x 5, 8 on
//!   2 x 6 and 11 on 2 x 2 (20 to 70); a 4 x 4 array at 2.5 mm pitch
//!   (`stages.scene.array.pitch_mm=2.5`) sends 50 to 55. `refine = "timing"` has no such bias: MAE 0.00 and 0.03 degrees
//!   on the same 3 x 3 and 2 x 6 trials. On arrays of three rows or fewer,
//!   prefer it (or a finer grid with `refine = "search"`, whose bias is the
//!   `+1.9·sin 2θ` above).
//! * `refine = "timing"` leaves the score curve alone: the continuous angle
//!   is that of the plane fitted through the taxels' arrival times
//!   ([`timing`]: `t = a + b·x + c·y`, `θ = atan2(−b, c)`). A response that
//!   has the same shape at every taxel (encoder delay, skin spread, bins)
//!   only shifts `a`, so on the ideal scene it is unbiased, and it needs no
//!   declared speed (it measures one, `−1/b`). WSS keeps deciding edge or no
//!   edge and the class; a timing answer more than 1.5 grid steps from the
//!   class is flagged uncertain. Measured figures: [`timing`] and
//!   RESULTS.md's continuous-angle section.
//! * The default grid is 10 to 170 degrees by 5 (33 classes): both leanings
//!   of an edge. Edges nearer 0 or 180 than the grid are reached only by the
//!   refinement; their crossing takes `1/sin θ` long (320 s at 1 degree on
//!   the paper's array at 2 mm/s), past the templates' cap, and a whole row
//!   of taxels fires at once, so their class is not reliable: use a grid that
//!   covers them, and a longer `max_template_s`, if a task has such edges.
//! * Weighting on the ideal scene: `one_minus_sr` misses classes there (50,
//!   55 and 75 degrees go 5 degrees high; constant and `one_plus_sr` are
//!   exact). On that scene a taxel fires only while the edge is over its own
//!   area, so a template's span holds spike-free frames (correlation 0 by
//!   the zero-variance rule), and `1 − SR` gives exactly those frames its
//!   largest weight, 1: the score of a longer template (a smaller angle) is
//!   diluted more, pulling answers towards 90 degrees. The equations leave no
//!   room to fix it (R of an empty frame is 0 by palpate's rule, its weight `1 − 0`
//!   by eq. 5; no template width or shape tried, `sigma_mm` 0.3 to 1 with
//!   either `distance`, helps). Adding only the lab's skin spread (0.5 mm) to
//!   the ideal scene makes `one_minus_sr` exact: spread fills those frames.
//!   Hence the default is `constant`; the paper graphs set `one_minus_sr`.
//! * "No edge" (`angle_deg = None`): no frame has a spike, or the best score is
//!   under `threshold`.
//! * Uncertain answers ([`Estimate::uncertain`]): when a class that is not the
//!   best class's grid neighbour scores within `uncertain_margin` (default
//!   0.05) of the best, the answer is kept but flagged. Edges nearer 0 or 180
//!   than a few degrees cross the array with a whole row of taxels at once
//!   and score low and flat over the grid: on the ideal scene 3 degrees is
//!   answered 157.6 (best 0.246, a rival 0.246) and 177 degrees 22.4; on the
//!   lab scene (seeds 1 and 2, 5 trials each of 5 and 175 degrees next to
//!   the 13 angles of graphs/continuous.toml, `write_estimates`) every such
//!   trial off by more than 5 degrees (10 of 20, 11.7 to 27.4 degrees off
//!   as orientations) had a rival within 0.031, while no trial at 7.7 to
//!   172.3 degrees (130) had one closer than 0.069. So a wrong answer near 0 or 180 is flagged, not
//!   silent; some right ones near 0 or 180 are flagged too.
//!
//! # Unknown crossing speed
//!
//! The speed is "known beforehand" (the robot's command): unless the config
//! sets `speed_mm_s`, each trial's templates are built for the speed the
//! trial declares ([`palpate_core::TrialMeta::speed_mm_s`]: a scene's
//! `motion.speed_mm_s`, a recording's label), else 2 mm/s (warned on
//! stderr, once per stage). So a scene run
//! at another speed needs no second key, and trials of several speeds mix.
//! Templates for the wrong speed cost much: the quickstart at 4 mm/s scores
//! 0.15 degrees MAE, and 25.7 with `--set stages.wss.speed_mm_s=2`
//! (`palpate run graphs/quickstart.toml --set
//! stages.scene.motion.speed_mm_s=4`).
//!
//! The templates' timing is the edge's normal speed `v·sin θ`, so a declared
//! speed 10 % off is matched best by an angle whose `sin θ` is 10 % off. With
//! `speed_tolerance = e > 0`, templates are built at `speed_steps` speeds over
//! `v·(1 ± e)`, each class scores its best speed, and with `refine = "search"`
//! the best class's speed is refined by golden-section search before the
//! angle is. Cost: `speed_steps` times the classes, plus about 20
//! single-class evaluations per trial. Batch only.
//!
//! # Speed
//!
//! [`batch`] computes eq. 5 as FFT convolutions (one inverse FFT per class and
//! block, the taxel sum done in the frequency domain, template spectra cached;
//! a one-block convolution spans only the trial's active frames, from the
//! first frame with spatial variance to the last, since an inactive frame is
//! zero in eq. 5's sums);
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
pub mod timing;

pub use batch::{pearson, wss_batch, wss_batch_speeds, wss_reference, wss_reference_series, wss_series};
pub use params::{AngleGrid, BeforeStart, Distance, Refine, Weighting, WssConfig, WssParams, WssSettings};
pub use stream::WssStream;
pub use templates::{raw_template, ClassTemplates, Templates};

use palpate_core::{
    register_stage, BuildContext, ConfigError, Estimate, Estimator, FitContext, InputSpec, Inspection, Item,
    Model, OutputFacts, PayloadKind, Stage, StageConfig, StageError, TrialContext,
};
use std::sync::{Arc, Mutex};

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
        Ok(Stage::Estimator(Box::new(WssEstimator { params })))
    }
    /// Warnings for keys set to a value of their own that the other keys
    /// make unused: a typo'd experiment (`speed_steps` without a
    /// `speed_tolerance`) would otherwise run as if they were not set.
    fn inspect(&self, _ctx: &BuildContext, _inputs: &[OutputFacts]) -> Inspection {
        let mut out = Inspection::default();
        let d = WssConfig::default();
        let mut unused = |key: &str, set: bool, needs: &str| {
            if set {
                out.warnings
                    .push(ConfigError::key(key, format!("has no effect without {needs}")));
            }
        };
        unused(
            "speed_steps",
            self.speed_steps != d.speed_steps && self.speed_tolerance == 0.0,
            "`speed_tolerance` > 0 (the speed grid is searched only then)",
        );
        unused(
            "refine_tol_deg",
            self.refine_tol_deg != d.refine_tol_deg && self.refine != Refine::Search,
            "`refine = \"search\"`",
        );
        unused(
            "timing_window_ms",
            self.timing_window_ms != d.timing_window_ms && self.refine != Refine::Timing,
            "`refine = \"timing\"`",
        );
        out
    }
}
register_stage!("wss", WssConfig);

struct WssEstimator {
    params: WssParams,
}

impl Estimator for WssEstimator {
    fn trained(&self) -> bool {
        false
    }
    fn fit(&self, _train: &[&Item], _ctx: &FitContext<'_>) -> Result<Box<dyn Model>, StageError> {
        Ok(Box::new(WssModel {
            params: self.params.clone(),
            cache: Mutex::new(Vec::new()),
        }))
    }
}

/// Templates of every speed of the grid (the declared speed alone when it is known).
type SpeedSets = Arc<Vec<(f64, Arc<Templates>)>>;

/// Template sets [`WssModel`] keeps, most recently used first. Each set may
/// hold up to 64 MiB of cached spectra per grid speed, and a recording whose
/// trials declare many distinct speeds would otherwise keep one set per
/// speed, growing with the number of trials. Four covers a few speeds mixed
/// in one run; more only rebuild templates (the same results, more time).
const MAX_TEMPLATE_SETS: usize = 4;

/// What the template sets are cached by: layout (its JSON), hop and speed bits.
type SetKey = (String, u64, u64);

/// The fitted (model-based) WSS: parameters and templates cached per
/// (layout, hop, speed), at most [`MAX_TEMPLATE_SETS`] of them: a trial's
/// speed is its own declared one unless the config sets one
/// ([`WssParams::for_trial`]).
struct WssModel {
    params: WssParams,
    cache: Mutex<Vec<(SetKey, SpeedSets)>>,
}

impl WssModel {
    /// The template sets for `images` under `params` (a speed set).
    fn templates(
        &self,
        images: &palpate_core::SpikeImages,
        params: &WssParams,
    ) -> Result<SpeedSets, StageError> {
        let key = (
            serde_json::to_string(&images.layout).unwrap_or_default(),
            images.hop_ms.to_bits(),
            params.speed().to_bits(),
        );
        {
            let mut c = self.cache.lock().unwrap_or_else(|e| e.into_inner());
            if let Some(i) = c.iter().position(|(k, _)| *k == key) {
                let hit = c.remove(i);
                let t = hit.1.clone();
                c.insert(0, hit);
                return Ok(t);
            }
        }
        // Built outside the lock: two threads may both build the same templates
        // on first use, which costs time but never changes a result.
        let mut sets = Vec::new();
        for f in params.speed_factors() {
            let t = Templates::new(&images.layout, images.hop_ms, &params.at_speed(f))
                .map_err(|e| StageError::new(format!("wss: images' {e}")))?;
            sets.push((f, Arc::new(t)));
        }
        let t: SpeedSets = Arc::new(sets);
        let mut c = self.cache.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(i) = c.iter().position(|(k, _)| *k == key) {
            // Another thread built them first: share its sets.
            return Ok(c[i].1.clone());
        }
        c.insert(0, (key, t.clone()));
        c.truncate(MAX_TEMPLATE_SETS);
        Ok(t)
    }
}

impl Model for WssModel {
    fn predict(&self, item: &Item, ctx: &TrialContext<'_>) -> Result<Estimate, StageError> {
        let images = item.payload.images()?;
        let params = self.params.for_trial(item.meta.speed_mm_s, ctx.stage_id);
        if let Some(why) = params::blind_layout(&images.layout) {
            params::warn_once("layout", ctx.stage_id, || {
                format!("warning: wss `{}`: {why}", ctx.stage_id)
            });
        }
        let sets = self.templates(images, &params)?;
        let e = match params.stop_margin {
            None => {
                let refs: Vec<(f64, &Templates)> = sets.iter().map(|(f, t)| (*f, t.as_ref())).collect();
                wss_batch_speeds(images, &refs, &params)?
            }
            Some(margin) => {
                // The config allows stop_margin only with a known speed: one set.
                let tpl = sets[0].1.clone();
                let mut s = WssStream::new(tpl, params.clone(), images.window_ms)?;
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
