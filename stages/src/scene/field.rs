//! Exact area averages of the contact pressure field over a square taxel.
//!
//! For an edge at angle `θ` with unit normal `n = (sin θ, -cos θ)` the contact
//! field depends on a point `p` only through its signed depth `d = s - n·p`
//! (positive on the object), so a taxel centred at `c` (offset `n·c`) with side
//! `a` sees the field through the distribution of `n·p` over its square. Writing
//! `p = c + (a/2)(ξ₁, ξ₂)` with `ξ` uniform on `[-1, 1]²`,
//! `n·p = n·c + X + Y`, `X ~ U(±h₁)`, `Y ~ U(±h₂)`, with half-widths
//! `h₁ = (a/2)|sin θ|`, `h₂ = (a/2)|cos θ|` (swapped so that `h₁ >= h₂`). The
//! taxel's average of a profile `g(d)` at `u = s - n·c` is
//!
//! ```text
//! ḡ(u) = E[g(u - X - Y)] = 1/(4 h₁ h₂) ∫∫ g(u - x - y) dx dy
//!      = [G(u+h₁+h₂) - G(u-h₁+h₂) - G(u+h₁-h₂) + G(u-h₁-h₂)] / (4 h₁ h₂)
//! ```
//!
//! where `G'' = g`. Two profiles, both closed form:
//!
//! * a **step** (contact on the object side), exact when unblurred: the
//!   fraction of the square on the object side is the CDF of the trapezoidal
//!   law of `X + Y`, piecewise quadratic ([`TaxelShape::step_fraction`]). This
//!   is the same number as clipping the square by the half-plane and taking the
//!   polygon's area, with no division by a vanishing width at θ = 90°.
//! * a step or a Gaussian bump **blurred by a Gaussian** of scale `σ` (the skin):
//!   `g(d) = J_k(d / σ)` for the chain `J_k` of [`super::special::chain`], whose
//!   second antiderivative is `σ² J_{k+2}(d / σ)`. When a half-width is below
//!   `1e-6 σ` the double difference degrades to a single one (or to `g(u)`),
//!   whose error `O((h/σ)²)` is below `1e-12`; this avoids `0/0` at θ = 90°.
//!   Cancellation in the double difference leaves an absolute error below
//!   about `1e-9` (tested against a fine brute-force quadrature).
//!
//! [`Profile`] sums such terms: the contact field of an edge or a ridge, with
//! the stress concentration and the skin's blur when the scene lists them, and
//! can tabulate itself for fast evaluation along a trial ([`Table`]: cubic
//! Hermite on exact values and slopes, error bound tested).

use super::special::chain;
use palpate_core::geometry::Edge;

/// How a square taxel of side `a` spreads over the edge's normal direction.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TaxelShape {
    /// The larger half-width, mm (> 0).
    pub h1: f64,
    /// The smaller half-width, mm (>= 0).
    pub h2: f64,
}

impl TaxelShape {
    /// The shape of a square taxel of side `taxel_mm` seen along `edge`'s normal.
    pub fn new(edge: &Edge, taxel_mm: f64) -> Self {
        let a = taxel_mm / 2.0 * edge.normal[0].abs();
        let b = taxel_mm / 2.0 * edge.normal[1].abs();
        TaxelShape {
            h1: a.max(b),
            h2: a.min(b),
        }
    }

    /// Half-extent of the taxel along the normal: `h₁ + h₂`.
    pub fn reach(&self) -> f64 {
        self.h1 + self.h2
    }

    /// Exact fraction of the taxel's area with `n·p < n·c + u`: the CDF of
    /// `X + Y` at `u` (trapezoidal law). Monotone, in `[0, 1]`, continuous.
    pub fn step_fraction(&self, u: f64) -> f64 {
        let (h1, h2) = (self.h1, self.h2);
        // Symmetry F(-u) = 1 - F(u) keeps the two tails bit-for-bit mirrored.
        let (v, flip) = if u > 0.0 { (-u, true) } else { (u, false) };
        let f = if v <= -(h1 + h2) {
            0.0
        } else if v < h2 - h1 {
            // Quadratic corner: only reachable when h2 > 0 (strict inequalities).
            let w = v + h1 + h2;
            w * w / (8.0 * h1 * h2)
        } else {
            0.5 + v / (2.0 * h1)
        };
        if flip {
            1.0 - f
        } else {
            f
        }
    }

    /// `E[J_k((u - X - Y) / σ)]`, the area average of level `k` of the chain
    /// (`k = 0`: blurred step; `k = -1`: Gaussian bump density; `k = -2`: its
    /// slope), for `σ > 0`.
    pub fn blurred(&self, u: f64, k: i32, sigma: f64) -> f64 {
        let (h1, h2) = (self.h1, self.h2);
        // Far tails: the step's plateaus and the densities' zeros (Φ(-9) ~ 1e-19).
        let far = h1 + h2 + 9.0 * sigma;
        if u <= -far {
            return 0.0;
        }
        if u >= far {
            return if k == 0 { 1.0 } else { 0.0 };
        }
        let small = 1e-6 * sigma;
        let z = |x: f64| x / sigma;
        if h1 < small {
            chain(k, z(u))
        } else if h2 < small {
            sigma * (chain(k + 1, z(u + h1)) - chain(k + 1, z(u - h1))) / (2.0 * h1)
        } else {
            let g = |x: f64| chain(k + 2, z(x));
            sigma * sigma * (g(u + h1 + h2) - g(u - h1 + h2) - g(u + h1 - h2) + g(u - h1 - h2))
                / (4.0 * h1 * h2)
        }
    }
}

/// One term of a contact profile, as a function of depth `d = s - n·p` (mm,
/// positive towards the object).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Term {
    /// `amp` where `d > at`, 0 elsewhere.
    Step {
        /// Depth of the step, mm.
        at: f64,
        /// Height, in pressure units.
        amp: f64,
    },
    /// `amp · exp(-(d - at)² / (2 width²))`.
    Bump {
        /// Depth of the peak, mm.
        at: f64,
        /// Gaussian width, mm (> 0).
        width: f64,
        /// Peak, in pressure units.
        amp: f64,
    },
}

/// A contact profile, area-averaged over one taxel: `base + Σ terms`, all
/// blurred by a Gaussian of scale `sigma` (0 = no blur).
#[derive(Clone, Debug, PartialEq)]
pub struct Profile {
    /// Constant pressure everywhere (a ridge's flat surface), pressure units.
    pub base: f64,
    /// Terms.
    pub terms: Vec<Term>,
    /// Gaussian blur scale, mm (the skin's spreading).
    pub sigma: f64,
    /// The taxel's spread along the normal.
    pub shape: TaxelShape,
}

impl Profile {
    /// Splits the profile into a part evaluated exactly (the base and, when
    /// unblurred, the steps) and a smooth part to tabulate (`None` if empty).
    pub fn split(&self) -> (Profile, Option<Profile>) {
        let (exact, smooth): (Vec<Term>, Vec<Term>) = self
            .terms
            .iter()
            .partition(|t| self.sigma == 0.0 && matches!(t, Term::Step { .. }));
        let smooth = (!smooth.is_empty()).then_some(Profile {
            base: 0.0,
            terms: smooth,
            sigma: self.sigma,
            shape: self.shape,
        });
        (
            Profile {
                base: self.base,
                terms: exact,
                sigma: self.sigma,
                shape: self.shape,
            },
            smooth,
        )
    }

    /// The taxel's average pressure when the edge's offset exceeds the taxel's
    /// by `u` mm.
    pub fn value(&self, u: f64) -> f64 {
        let mut v = self.base;
        for t in &self.terms {
            v += match *t {
                Term::Step { at, amp } => {
                    if self.sigma == 0.0 {
                        amp * self.shape.step_fraction(u - at)
                    } else {
                        amp * self.shape.blurred(u - at, 0, self.sigma)
                    }
                }
                Term::Bump { at, width, amp } => {
                    // Blurring a Gaussian of width w by one of scale σ gives one of
                    // width ω = sqrt(w² + σ²) and peak scaled by w/ω; as a density
                    // in units of ω: amp (w/ω) sqrt(2π) φ((d - at)/ω).
                    let w = (width * width + self.sigma * self.sigma).sqrt();
                    amp * width / w * SQRT_2PI * self.shape.blurred(u - at, -1, w)
                }
            };
        }
        v
    }

    /// `d value / du` for a profile with no unblurred step (every level has a
    /// smooth derivative).
    pub fn slope(&self, u: f64) -> f64 {
        let mut v = 0.0;
        for t in &self.terms {
            v += match *t {
                Term::Step { at, amp } => amp * self.shape.blurred(u - at, -1, self.sigma) / self.sigma,
                Term::Bump { at, width, amp } => {
                    let w = (width * width + self.sigma * self.sigma).sqrt();
                    amp * width / w * SQRT_2PI * self.shape.blurred(u - at, -2, w) / w
                }
            };
        }
        v
    }

    /// The interval of `u` outside which the profile is constant (to 1e-19).
    pub fn support(&self) -> (f64, f64) {
        let r = self.shape.reach();
        let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
        for t in &self.terms {
            let (at, scale) = match *t {
                Term::Step { at, .. } => (at, self.sigma),
                Term::Bump { at, width, .. } => (at, (width * width + self.sigma * self.sigma).sqrt()),
            };
            lo = lo.min(at - r - 9.0 * scale);
            hi = hi.max(at + r + 9.0 * scale);
        }
        if lo > hi {
            (0.0, 0.0)
        } else {
            (lo, hi)
        }
    }

    /// The smallest length scale of the profile's smooth parts, mm.
    fn finest_scale(&self) -> f64 {
        self.terms
            .iter()
            .map(|t| match *t {
                Term::Step { .. } => self.sigma,
                Term::Bump { width, .. } => (width * width + self.sigma * self.sigma).sqrt(),
            })
            .fold(f64::INFINITY, f64::min)
    }
}

const SQRT_2PI: f64 = 2.506_628_274_631_000_7;

/// Points per finest length scale in a [`Table`]. With cubic Hermite
/// interpolation on exact values and slopes the error is at most
/// `Δ⁴/384 · max|f''''|`; for these Gaussian-smoothed profiles that is below
/// `1e-7` of the term's amplitude at 24 points per scale (tested).
pub const TABLE_POINTS_PER_SCALE: f64 = 24.0;

/// A profile tabulated for fast evaluation: cubic Hermite interpolation on a
/// uniform grid of exact values and slopes; constant outside its support.
#[derive(Clone, Debug)]
pub struct Table {
    u0: f64,
    inv_du: f64,
    du: f64,
    values: Vec<f64>,
    slopes: Vec<f64>,
    left: f64,
    right: f64,
    /// Index of the last grid point, as f64.
    last: f64,
    /// Per interval, the cubic's coefficients `[p0, m0, b, a]` of
    /// `p0 + t (m0 + t (b + t a))`, so a batch evaluation does no more than
    /// one load and three multiply-adds per sample.
    coef: Vec<[f64; 4]>,
}

impl Table {
    /// Tabulates a smooth profile: every step blurred (`sigma > 0`) or only
    /// bumps (see [`Profile::split`]). Internal invariant: no unblurred step.
    pub fn new(profile: &Profile) -> Table {
        let (lo, hi) = profile.support();
        let du = profile.finest_scale() / TABLE_POINTS_PER_SCALE;
        let n = (((hi - lo) / du).ceil() as usize).max(1) + 1;
        let values: Vec<f64> = (0..n).map(|i| profile.value(lo + i as f64 * du)).collect();
        let slopes: Vec<f64> = (0..n).map(|i| profile.slope(lo + i as f64 * du) * du).collect();
        let coef = if n < 2 {
            vec![[values[0], 0.0, 0.0, 0.0]]
        } else {
            (0..n - 1)
                .map(|i| {
                    let (p0, p1, m0, m1) = (values[i], values[i + 1], slopes[i], slopes[i + 1]);
                    let d = p1 - p0;
                    [p0, m0, 3.0 * d - 2.0 * m0 - m1, m0 + m1 - 2.0 * d]
                })
                .collect()
        };
        Table {
            u0: lo,
            inv_du: 1.0 / du,
            du,
            left: profile.value(lo - 1.0),
            right: profile.value(hi + 1.0),
            last: (n - 1) as f64,
            values,
            slopes,
            coef,
        }
    }

    /// Grid spacing, mm.
    pub fn spacing(&self) -> f64 {
        self.du
    }

    /// The interpolated profile at `u`.
    #[inline]
    pub fn eval(&self, u: f64) -> f64 {
        let x = (u - self.u0) * self.inv_du;
        if x.is_nan() || x < 0.0 {
            return self.left;
        }
        if x >= self.last {
            return self.right;
        }
        let i = x as usize;
        let t = x - i as f64;
        let (p0, p1, m0, m1) = (
            self.values[i],
            self.values[i + 1],
            self.slopes[i],
            self.slopes[i + 1],
        );
        // Cubic Hermite basis in Horner form.
        let d = p1 - p0;
        let a = m0 + m1 - 2.0 * d;
        let b = 3.0 * d - 2.0 * m0 - m1;
        p0 + t * (m0 + t * (b + t * a))
    }

    /// Batch evaluation inside the support: `out[k] = scale * (base +
    /// f(s[k] - shift))` for the simulator's active samples, whose offsets `s`
    /// never increase (the array slides one way). An argument a rounding error
    /// outside the span is clamped to its end, where the interpolant equals the
    /// exact value. Agrees with [`Table::eval`] to rounding (tested).
    ///
    /// Why runs: `s` moves by well under a grid step per sample, so samples come
    /// in runs sharing one interval. The grid coordinates of all samples are
    /// computed first (vectorized, into `out`), runs found by a linear scan,
    /// and each run's cubic evaluated with constant coefficients: no per-sample
    /// index conversion or table lookup.
    pub fn eval_active(&self, shift: f64, s: &[f64], out: &mut [f64], scale: f64, base: f64) {
        debug_assert!(s.windows(2).all(|w| w[1] <= w[0]), "offsets must not increase");
        let top = self.coef.len() - 1;
        let last = self.last.max(0.0);
        let n = s.len().min(out.len());
        let (out, s) = (&mut out[..n], &s[..n]);
        crate::wide::with_avx2(
            #[inline(always)]
            || {
                for (o, &v) in out.iter_mut().zip(s) {
                    *o = ((v - shift - self.u0) * self.inv_du).max(0.0).min(last);
                }
                let mut k = 0;
                while k < n {
                    let i = (out[k] as usize).min(top);
                    let fi = i as f64;
                    // The run: samples at or above the interval's lower node
                    // (the lowest interval takes everything below).
                    let mut e = k + 1;
                    if i == 0 {
                        e = n;
                    } else {
                        while e < n && out[e] >= fi {
                            e += 1;
                        }
                    }
                    let [p0, m0, b, a] = self.coef[i];
                    for o in &mut out[k..e] {
                        let t = (*o - fi).clamp(0.0, 1.0);
                        *o = scale * (base + (p0 + t * (m0 + t * (b + t * a))));
                    }
                    k = e;
                }
            },
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Brute-force midpoint quadrature of the area average over an `n x n` grid
    /// of the square (error O(1/n²) for smooth integrands, O(1/n) at a kink).
    fn brute(theta: f64, a: f64, u: f64, g: impl Fn(f64) -> f64, n: usize) -> f64 {
        let e = Edge::new(theta);
        let mut sum = 0.0;
        for i in 0..n {
            for j in 0..n {
                let x = -a / 2.0 + (i as f64 + 0.5) * a / n as f64;
                let y = -a / 2.0 + (j as f64 + 0.5) * a / n as f64;
                sum += g(u - e.offset([x, y]));
            }
        }
        sum / (n * n) as f64
    }

    /// The exact fraction of a square on one side of a line, by clipping the
    /// square (Sutherland-Hodgman) and taking the polygon's area (shoelace).
    fn clipped_area_fraction(theta: f64, a: f64, u: f64) -> f64 {
        let e = Edge::new(theta);
        let h = a / 2.0;
        let square = [[-h, -h], [h, -h], [h, h], [-h, h]];
        let inside = |p: [f64; 2]| e.offset(p) < u;
        let mut out = Vec::new();
        for k in 0..4 {
            let (p, q) = (square[k], square[(k + 1) % 4]);
            let (ip, iq) = (inside(p), inside(q));
            if ip {
                out.push(p);
            }
            if ip != iq {
                let (op, oq) = (e.offset(p), e.offset(q));
                let t = (u - op) / (oq - op);
                out.push([p[0] + t * (q[0] - p[0]), p[1] + t * (q[1] - p[1])]);
            }
        }
        let mut area = 0.0;
        for k in 0..out.len() {
            let (p, q) = (out[k], out[(k + 1) % out.len()]);
            area += p[0] * q[1] - q[0] * p[1];
        }
        area.abs() / 2.0 / (a * a)
    }

    #[test]
    fn step_fraction_equals_clipped_polygon_area() {
        for theta in [1.0, 10.0, 33.0, 45.0, 60.0, 89.9, 90.0, 120.0, 179.0] {
            let shape = TaxelShape::new(&Edge::new(theta), 2.0);
            for k in -30..=30 {
                let u = k as f64 * 0.05;
                let want = clipped_area_fraction(theta, 2.0, u);
                let got = shape.step_fraction(u);
                assert!((got - want).abs() < 1e-12, "θ={theta} u={u}: {got} vs {want}");
            }
        }
    }

    #[test]
    fn blurred_averages_match_brute_force_quadrature() {
        for theta in [10.0, 45.0, 72.0, 90.0, 135.0] {
            let e = Edge::new(theta);
            let shape = TaxelShape::new(&e, 2.0);
            for sigma in [0.1, 0.5, 1.5] {
                for k in -12..=12 {
                    let u = k as f64 * 0.25;
                    let step = shape.blurred(u, 0, sigma);
                    let want = brute(theta, 2.0, u, |d| super::super::special::cdf(d / sigma), 400);
                    assert!(
                        (step - want).abs() < 2e-5,
                        "θ={theta} σ={sigma} u={u}: {step} vs {want}"
                    );
                    let bump = shape.blurred(u, -1, sigma);
                    let want = brute(theta, 2.0, u, |d| super::super::special::pdf(d / sigma), 400);
                    assert!(
                        (bump - want).abs() < 2e-5,
                        "bump θ={theta} σ={sigma} u={u}: {bump} vs {want}"
                    );
                }
            }
        }
    }

    #[test]
    fn blurred_step_tends_to_the_exact_step_as_sigma_shrinks() {
        let shape = TaxelShape::new(&Edge::new(37.0), 2.0);
        for k in -20..=20 {
            let u = k as f64 * 0.07;
            let d = (shape.blurred(u, 0, 1e-4) - shape.step_fraction(u)).abs();
            assert!(d < 1e-4, "u={u}: {d}");
        }
    }

    #[test]
    fn table_interpolation_error_is_bounded() {
        for theta in [10.0, 45.0, 90.0] {
            let shape = TaxelShape::new(&Edge::new(theta), 2.0);
            let p = Profile {
                base: 0.0,
                terms: vec![
                    Term::Step { at: 0.0, amp: 1.0 },
                    Term::Bump {
                        at: 0.3,
                        width: 0.2,
                        amp: 0.5,
                    },
                ],
                sigma: 0.3,
                shape,
            };
            let t = Table::new(&p);
            let (lo, hi) = p.support();
            let mut worst: f64 = 0.0;
            for i in 0..5000 {
                let u = lo - 1.0 + (hi - lo + 2.0) * (i as f64 + 0.37) / 5000.0;
                worst = worst.max((t.eval(u) - p.value(u)).abs());
            }
            assert!(worst < 1e-7, "θ={theta}: worst table error {worst}");
            // The batch path agrees with the scalar one inside the span, and
            // clamps (to the exact end values) a hair outside it. Offsets fall
            // (as while sliding), with steps from much less than a grid step
            // to several, and a hold (repeated values).
            let mut s: Vec<f64> = (0..=4000)
                .map(|i| hi + 1e-12 - (hi - lo + 2e-12) * (i as f64 / 4000.0).powi(3))
                .collect();
            s.splice(100..100, [s[100]; 7]);
            let mut out = vec![0.0; s.len()];
            t.eval_active(
                0.25,
                &s.iter().map(|v| v + 0.25).collect::<Vec<_>>(),
                &mut out,
                2.0,
                0.5,
            );
            for (&u, &o) in s.iter().zip(&out) {
                let want = 2.0 * (0.5 + t.eval(u.clamp(lo, hi)));
                assert!((o - want).abs() < 1e-12, "θ={theta} u={u}: {o} vs {want}");
                assert!((o - 2.0 * (0.5 + p.value(u))).abs() < 3e-7);
            }
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]
        #[test]
        fn averages_are_finite_monotone_and_bounded(theta in 0.01f64..179.99, sigma in 0.0f64..3.0, u in -20.0f64..20.0) {
            let shape = TaxelShape::new(&Edge::new(theta), 2.0);
            let f = shape.step_fraction(u);
            prop_assert!((0.0..=1.0).contains(&f));
            prop_assert!(shape.step_fraction(u + 0.01) >= f);
            if sigma > 1e-3 {
                let b = shape.blurred(u, 0, sigma);
                prop_assert!(b.is_finite() && (-1e-9..=1.0 + 1e-9).contains(&b), "{}", b);
                prop_assert!(shape.blurred(u + 0.01, 0, sigma) >= b - 1e-9);
                let d = shape.blurred(u, -1, sigma);
                prop_assert!(d.is_finite() && d >= -1e-9);
            }
        }
    }
}
