//! One trial of a scene: the palpation's geometry over time, the area-averaged
//! contact field, then the signal effects, block by block.
//!
//! Geometry (core's convention, `palpate_core::geometry`): the edge at `θ` has
//! normal `n = (sin θ, -cos θ)`, the object lies where `n·p < s`, and while the
//! array slides `+x` by `X` the offset is `s = s₀ - X sin θ`. With `(lo, hi)` the
//! footprint of the taxels along `n` and `W` the stimulus' width along `n`
//! (0 for an edge, the bar's width for a ridge), the plan is:
//!
//! * start at `s₀ = hi + W + m` (the whole array on the object, or before the
//!   bar), with margin `m = margin_mm + reach`, where `reach` is how far the
//!   listed field effects spread a response (4 blur scales: the plateau is flat
//!   to about 1e-5 when the slide starts) plus the bound of the trial variation;
//! * hold `hold_before_s`, slide until `s = lo - m` at `speed_mm_s`, hold
//!   `hold_after_s`;
//! * the stimulus touches some taxel while `lo < s < hi + W`: `crossing_ms` =
//!   `[hold + m / (v sin θ), hold + (hi + W - lo + m) / (v sin θ)]`, so the
//!   crossing lasts `(hi - lo + W) / (v sin θ)`: 5.5 s at 90° for the paper's bare
//!   11 mm footprint at 2 mm/s, growing like `1 + |cot θ|`. The skin spreads
//!   each taxel's response by about 2σ on each side (1 mm for σ = 0.5 mm, the
//!   paper's 1 mm skin), which makes the response span 13 mm, the paper's active
//!   area: the "about 6.5 s at 90 degrees" of the paper's protocol.
//!
//! Trial variation (when listed) perturbs the *actual* trial, not the plan: the
//! object is rotated by `δθ` about the point the array's centre passes at
//! mid-crossing, the array lands `δx` off, slides at `v (1 + δv)` for the planned
//! distance and presses with force `1 + δF`. The recording runs until the
//! actual slide ends plus the hold, so trials may differ in length by a few
//! samples. `crossing_ms` stays the nominal plan: it is what the experimenter
//! commanding the robot knows.
//!
//! A `sleeve` (when listed) makes the contact pattern lag the array by its
//! stick-slip shear `u(t)` (the actual displacement becomes `X - u`; slips only
//! move the pattern forward, so `s` still never increases) and scales each
//! taxel's pressure by the friction's moment; a `tilt` scales it by the
//! trial's pressure gradient (see `sensor`). Both act on the area-averaged
//! field, before the signal effects, and only when listed.

use super::config::{Scene, StimulusKind, MAX_TRIAL_VALUES};
use super::effects::{self, Block, BuiltEffects, TrialInfo};
use super::field::{Profile, Table, TaxelShape, Term};
use palpate_core::geometry::Edge;
use palpate_core::{ConfigError, Signals, StageError};

/// Samples per block: 16 taxels x 1024 samples x 8 bytes = 128 KiB, which
/// stays in L2 while every effect passes over it.
pub const BLOCK: usize = 256;

/// The nominal plan of a trial at one angle.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Plan {
    /// Angle, degrees.
    pub theta_deg: f64,
    /// Footprint of the taxels along the normal, mm.
    pub lo: f64,
    /// Footprint of the taxels along the normal, mm.
    pub hi: f64,
    /// Stimulus width along the normal, mm.
    pub width: f64,
    /// Margin used at each end, mm.
    pub margin: f64,
    /// Offset where the centre of the crossing lies: `(lo + hi + W) / 2`, mm.
    pub s_mid: f64,
    /// Displacement of the array at mid-crossing, mm.
    pub x_mid: f64,
    /// Distance the array slides, mm.
    pub travel: f64,
    /// Nominal samples in the trial.
    pub n_samples: usize,
}

/// A scene ready to simulate trials.
pub struct Simulator {
    /// The resolved scene.
    pub scene: Scene,
    /// Its effects, built.
    pub effects: BuiltEffects,
    /// Unit of the output.
    pub unit: String,
}

impl Simulator {
    /// Builds the effects (array properties from `array_seed`) and checks that
    /// every angle's trial is simulable.
    pub fn new(scene: Scene, array_seed: u64) -> Result<Simulator, ConfigError> {
        let effects = effects::build(&scene, array_seed)?;
        let mut unit = "pressure".to_string();
        for (e, _) in &effects.signal {
            unit = e.unit_after(&unit);
        }
        let sim = Simulator { scene, effects, unit };
        for &a in &sim.scene.angles {
            sim.plan(a)?;
        }
        Ok(sim)
    }

    /// How far the field effects spread a response beyond the taxel, mm.
    fn reach(&self) -> f64 {
        let f = &self.effects.field;
        let mut r = 4.0 * f.sigma_mm;
        for &(_, depth, width) in &f.stress {
            r = r.max(depth + 4.0 * (width * width + f.sigma_mm * f.sigma_mm).sqrt());
        }
        r
    }

    /// The nominal plan at angle `theta_deg`. Errors (naming the key) when the
    /// variation is too large for the angle or the trial too long to hold.
    pub fn plan(&self, theta_deg: f64) -> Result<Plan, ConfigError> {
        let sc = &self.scene;
        let edge = Edge::new(theta_deg);
        let (lo, hi) = edge.footprint(&sc.layout);
        let width = match sc.stimulus {
            StimulusKind::Edge => 0.0,
            StimulusKind::Ridge => sc.ridge.width_mm,
        };
        let sin = edge.normal[0];
        let half = (hi - lo + width) / 2.0;
        // Trial variation bounds (3 SD, the truncation): a start offset moves the
        // edge by at most 3 sd_x sin θ <= 3 sd_x; a rotation by δ about a pivot at
        // distance <= x_mid + R from every taxel moves it by at most that times δ.
        let sd_x: f64 = self.effects.variations.iter().map(|v| v.start_sd_mm).sum();
        let sd_a: f64 = self
            .effects
            .variations
            .iter()
            .map(|v| v.angle_sd_deg.to_radians())
            .sum();
        let r_max = sc
            .layout
            .positions()
            .iter()
            .map(|p| p[0].hypot(p[1]))
            .fold(0.0, f64::max)
            + sc.layout.taxel_mm() / std::f64::consts::SQRT_2;
        let k = 3.0 * sd_a;
        // A sleeve's shear makes the pattern lag the array by up to u_max.
        let shear: f64 = self.effects.sleeves.iter().map(|(c, _)| c.u_max()).sum();
        let base = sc.motion.margin_mm + self.reach() + 3.0 * sd_x + shear;
        // margin = base + k (x_mid + R), x_mid = (half + margin) / sin θ.
        if k >= 0.5 * sin {
            // sin θ > 6 SD holds between asin(6 SD) and 180° minus it (the
            // sine is symmetric about 90°), rounded inwards.
            let lo = ((6.0 * sd_a).min(1.0).asin().to_degrees() * 1e2).ceil() / 1e2 + 0.01;
            let range = if lo < 90.0 {
                format!(", or use angles from {lo:.2} to {:.2} degrees", 180.0 - lo)
            } else {
                String::new()
            };
            return Err(ConfigError::key(
                "effects",
                format!(
                    "the placement-angle variation ({} degrees SD) is too large for the angle {theta_deg}: the edge could start under the array; \
                     keep the variations' `angle_sd_deg` (summed) at or under {:.3} degrees for this angle{range} \
                     (3 SD of rotation must stay under half the sine of the edge's angle)",
                    sd_a.to_degrees(),
                    // Rounded towards the side that works.
                    ((sin / 6.0).to_degrees() * 1e3).floor() / 1e3,
                ),
            ));
        }
        let margin = (base + k * (half / sin + r_max)) / (1.0 - k / sin);
        let s0 = hi + width + margin;
        let s_mid = (lo + hi + width) / 2.0;
        let x_mid = (s0 - s_mid) / sin;
        let travel = (hi + width - lo + 2.0 * margin) / sin;
        let m = &sc.motion;
        // Slowest actual speed (3 SD) bounds the recording's length.
        let slow: f64 = self
            .effects
            .variations
            .iter()
            .map(|v| 1.0 - 3.0 * v.speed_rel_sd)
            .product();
        let duration = m.hold_before_s + travel / (m.speed_mm_s * slow) + m.hold_after_s;
        let values = duration * m.sample_rate_hz * sc.layout.len() as f64;
        if values.is_nan() || values > MAX_TRIAL_VALUES {
            return Err(ConfigError::key(
                "angles",
                format!(
                    "at {theta_deg} degrees a trial lasts {duration:.0} s ({values:.2e} values: the edge travels {travel:.0} mm \
                     to cross taxels spread over {:.0} mm), more than the limit of {MAX_TRIAL_VALUES:.0e}; use angles further \
                     from 0 and 180, a higher speed, a lower sample rate, or check the array's size (`array`, `layout`)",
                    hi + width - lo
                ),
            ));
        }
        let n_samples = ((m.hold_before_s + travel / m.speed_mm_s + m.hold_after_s) * m.sample_rate_hz)
            .round()
            .max(1.0) as usize;
        Ok(Plan {
            theta_deg,
            lo,
            hi,
            width,
            margin,
            s_mid,
            x_mid,
            travel,
            n_samples,
        })
    }

    /// The nominal crossing `[start, end]`, ms: while the stimulus touches some
    /// taxel.
    pub fn crossing_ms(&self, plan: &Plan) -> [f64; 2] {
        let m = &self.scene.motion;
        let vs = m.speed_mm_s * Edge::new(plan.theta_deg).normal[0];
        let t0 = m.hold_before_s + plan.margin / vs;
        let t1 = m.hold_before_s + (plan.hi + plan.width - plan.lo + plan.margin) / vs;
        [t0 * 1000.0, t1 * 1000.0]
    }

    /// The contact profile of the stimulus at the actual angle, area-averaged
    /// over a taxel of `shape`, before force scaling.
    pub fn profile(&self, shape: TaxelShape) -> Profile {
        let f = &self.effects.field;
        let (base, mut terms, edges) = match self.scene.stimulus {
            StimulusKind::Edge => (0.0, vec![Term::Step { at: 0.0, amp: 1.0 }], vec![(0.0, 1.0, 1.0)]),
            StimulusKind::Ridge => {
                let h = self.scene.ridge.extra_pressure();
                let w = self.scene.ridge.width_mm;
                (
                    1.0,
                    vec![Term::Step { at: 0.0, amp: h }, Term::Step { at: w, amp: -h }],
                    // (edge depth, direction into the bar, pressure it borders)
                    vec![(0.0, 1.0, h), (w, -1.0, h)],
                )
            }
        };
        for &(peak, depth, width) in &f.stress {
            for &(at, dir, p) in &edges {
                terms.push(Term::Bump {
                    at: at + dir * depth,
                    width,
                    amp: peak * p,
                });
            }
        }
        Profile {
            base,
            terms,
            sigma: f.sigma_mm,
            shape,
        }
    }

    /// Simulates one trial at nominal angle `theta_deg` with the trial's seed.
    pub fn simulate(&self, theta_deg: f64, trial_seed: u64) -> Result<Signals, StageError> {
        let mut data = Vec::new();
        self.simulate_into(theta_deg, trial_seed, &mut data)?;
        Ok(Signals {
            sample_rate_hz: self.scene.motion.sample_rate_hz,
            layout: self.scene.layout.clone(),
            unit: self.unit.clone(),
            data,
        })
    }

    /// [`Simulator::simulate`] into caller-owned rows (`data[taxel][sample]`),
    /// reusing their allocations: for loops over many trials that do not keep
    /// them (a live emulator, a benchmark of the computation alone), which then
    /// skip the allocator and the kernel's zeroing of fresh pages.
    pub fn simulate_into(
        &self,
        theta_deg: f64,
        trial_seed: u64,
        data: &mut Vec<Vec<f64>>,
    ) -> Result<(), StageError> {
        let plan = self.plan(theta_deg)?;
        let sc = &self.scene;
        let m = &sc.motion;
        let draw = effects::draw_trial(&self.effects.variations, trial_seed);
        let theta_a = (theta_deg + draw.dtheta_deg).clamp(1e-3, 180.0 - 1e-3);
        let nominal = Edge::new(theta_deg);
        let actual = Edge::new(theta_a);
        let sin_a = actual.normal[0];
        // The pivot P = s_mid n (nominal): the actual edge passes through it at
        // the nominal mid-crossing displacement.
        let s_p = plan.s_mid * (actual.normal[0] * nominal.normal[0] + actual.normal[1] * nominal.normal[1]);
        let speed = m.speed_mm_s * draw.speed_factor;
        let slide_s = plan.travel / speed;
        let fs = m.sample_rate_hz;
        let n = ((m.hold_before_s + slide_s + m.hold_after_s) * fs)
            .round()
            .max(1.0) as usize;
        let positions = sc.layout.positions();
        let centres: Vec<f64> = positions.iter().map(|&p| actual.offset(p)).collect();
        let n_taxels = centres.len();
        let shape = TaxelShape::new(&actual, sc.layout.taxel_mm());
        let profile = self.profile(shape);
        // Unblurred steps are evaluated exactly (the ideal path); smooth terms
        // through a table of exact values and slopes (error bound in `field`).
        let (exact, smooth) = profile.split();
        let table = smooth.as_ref().map(Table::new);
        let force = draw.force * m.force_rel;
        let (sup_lo, sup_hi) = profile.support();
        let (left, right) = (profile.value(sup_lo - 1.0), profile.value(sup_hi + 1.0));
        // Sleeves: the shear u(k) (mm) by which the pattern lags the array,
        // and per sleeve the rim's relative pressure change c u / u_s.
        let k0 = (m.hold_before_s * fs).round() as usize;
        let k1 = ((m.hold_before_s + slide_s) * fs).round() as usize;
        let mut shift: Vec<f64> = Vec::new();
        let mut couplings: Vec<Vec<f64>> = Vec::new();
        for (c, occ) in &self.effects.sleeves {
            effects::log_event("run", "sleeve");
            let u = c.track(
                n,
                k0,
                k1,
                speed / fs,
                &mut effects::stream(trial_seed, "sleeve", *occ),
            );
            if shift.is_empty() {
                shift = u.clone();
            } else {
                for (a, b) in shift.iter_mut().zip(&u) {
                    *a += b;
                }
            }
            let per_u = c.pressure_coupling / c.u_static().max(f64::MIN_POSITIVE);
            couplings.push(u.iter().map(|v| v * per_u).collect());
        }
        // Tilts: a per-trial pressure factor per taxel.
        let mut tilt = vec![1.0; positions.len()];
        for (c, occ) in &self.effects.tilts {
            effects::log_event("run", "tilt");
            let g = c.gains(&sc.layout, &mut effects::stream(trial_seed, "tilt", *occ));
            for (t, g) in tilt.iter_mut().zip(g) {
                *t *= g;
            }
        }
        let rim = positions.iter().map(|p| p[0].abs()).fold(0.0, f64::max);
        let x_rel: Vec<f64> = positions
            .iter()
            .map(|p| if rim > 0.0 { p[0] / rim } else { 0.0 })
            .collect();
        let reshape = !self.effects.sleeves.is_empty() || !self.effects.tilts.is_empty();
        let travel_at = |k: usize| speed * (k as f64 / fs - m.hold_before_s).clamp(0.0, slide_s);
        // With a sleeve the pattern's displacement is the array's minus the
        // shear; while the sleeve sticks the two cancel, so a running maximum
        // keeps rounding from moving the pattern backwards.
        let lagged: Vec<f64> = if shift.is_empty() {
            Vec::new()
        } else {
            let mut hi = f64::NEG_INFINITY;
            (0..n)
                .map(|k| {
                    hi = hi.max(travel_at(k) - shift[k]);
                    hi
                })
                .collect()
        };
        let offset_at = |k: usize| {
            let x = lagged.get(k).copied().unwrap_or_else(|| travel_at(k));
            s_p - (x + draw.dx_mm - plan.x_mid) * sin_a
        };

        let info = TrialInfo {
            sample_rate_hz: fs,
            n_samples: n,
            layout: &sc.layout,
        };
        let mut states: Vec<_> = self
            .effects
            .signal
            .iter()
            .map(|(e, occ)| e.start(&info, effects::stream(trial_seed, e.kind(), *occ)))
            .collect();
        data.resize_with(n_taxels, Vec::new);
        for row in data.iter_mut() {
            row.clear();
            row.reserve(n);
        }
        let mut buf = vec![0.0; n_taxels * BLOCK.min(n)];
        let mut s_buf = vec![0.0; BLOCK.min(n)];
        let mut start = 0;
        while start < n {
            let len = BLOCK.min(n - start);
            for (j, s) in s_buf[..len].iter_mut().enumerate() {
                *s = offset_at(start + j);
            }
            let block = &mut buf[..n_taxels * len];
            let s_blk = &s_buf[..len];
            for (row, &c) in block.chunks_exact_mut(len).zip(&centres) {
                // `s` never increases: samples with the stimulus beyond the
                // profile's support come first (constant `right`), then the
                // active ones, then those past it (constant `left`). Only the
                // active ones are evaluated; the constants are the exact limits.
                let k1 = s_blk.partition_point(|&s| s - c > sup_hi);
                let k2 = k1 + s_blk[k1..].partition_point(|&s| s - c >= sup_lo);
                row[..k1].fill(force * right);
                row[k2..].fill(force * left);
                let (row, s_act) = (&mut row[k1..k2], &s_blk[k1..k2]);
                match (&table, exact.terms.is_empty()) {
                    (Some(t), true) => t.eval_active(c, s_act, row, force, exact.base),
                    (Some(t), false) => {
                        for (x, &s) in row.iter_mut().zip(s_act) {
                            *x = force * (exact.value(s - c) + t.eval(s - c));
                        }
                    }
                    (None, _) => {
                        for (x, &s) in row.iter_mut().zip(s_act) {
                            *x = force * exact.value(s - c);
                        }
                    }
                }
            }
            if reshape {
                for (i, row) in block.chunks_exact_mut(len).enumerate() {
                    for (j, x) in row.iter_mut().enumerate() {
                        let mut f = tilt[i];
                        for cu in &couplings {
                            f *= 1.0 + cu[start + j] * x_rel[i];
                        }
                        *x *= f;
                    }
                }
            }
            let mut b = Block {
                data: block,
                len,
                start,
            };
            for st in states.iter_mut() {
                st.process(&mut b);
            }
            for (out, row) in data.iter_mut().zip(b.data.chunks_exact(len)) {
                out.extend_from_slice(row);
            }
            start += len;
        }
        Ok(())
    }
}
