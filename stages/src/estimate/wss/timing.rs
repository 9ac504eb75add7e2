//! Arrival-time plane: the edge's angle and normal speed from *when* each
//! taxel fires, for `refine = "timing"`.
//!
//! # The maths
//!
//! An edge at angle `θ` (normal `n = (sin θ, −cos θ)`, the array sliding `+x`
//! at speed `v`, see the guide's geometry page) sits at offset
//! `s(t) = s₀ − v·sin θ·t`, so it reaches the taxel at `p = (x, y)` when
//! `n·p = s(t)`:
//!
//! `t(p) = s₀/(v sin θ) − x/v + y·cot θ/v = a + b·x + c·y`
//!
//! a plane in `(x, y)` with `b = −1/v` and `c = cot θ / v`. Hence
//! `θ = atan2(−b, c)` (in (0°, 180°) whenever `b < 0`) and `v = −1/b`: the
//! angle needs no declared speed, and the speed comes out with it.
//!
//! Each taxel's arrival time is the centroid of its spike counts over the
//! frames within `timing_window_ms` of the centre of its burst (the mean
//! frame of the frames at half its largest count or more; the frames'
//! centres as times). Any response whose shape is the same for every taxel (the
//! encoder's delay, a skin's spread, the bins' window) shifts every centroid
//! alike and moves only `a`. The window keeps stray spikes far from the
//! crossing (noise over a minute-long crossing near 0 or 180 degrees) out of
//! the centroid. The plane is the unweighted least-squares fit over every
//! taxel that fired (weighting by spike count changed the lab scene's MAE by
//! under 0.03 degrees).
//!
//! Measured with palpate (debug build):
//! * ideal scene, one trial per angle from 20 to 160 degrees by 0.1
//!   (`palpate run graphs/refine_bias.toml`): largest error 0.066 degrees,
//!   MAE 0.009 (the `search` refinement: 2.14 and 1.13); at 3 to 19 and 161
//!   to 177 by 1 (the same graph with `--set stages.scene.angles=[...]`):
//!   largest error 0.002;
//! * lab scene, 13 off-grid angles x 5 trials, 5 seeds
//!   (`palpate run graphs/continuous.toml`): MAE 0.43 ± 0.07 degrees, every
//!   seed under 0.56 (`search`: 0.73 ± 0.19);
//! * lab scene, WSS told 1.6 to 2.4 mm/s for a 2 mm/s array
//!   (`palpate run graphs/paper/speed_error.toml`): 0.46 ± 0.05 degrees at
//!   every declared speed.
//!
//! A NumPy probe of the same maths on exported images found that centroids
//! over the whole trial fail near 0 and 180 degrees on the lab scene (errors
//! of 5 to 14 degrees: noise spikes over a minute-long crossing), and that a
//! burst centre at the median spike fails there too; the window around the
//! half-maximum centre does not. Hence the 3 s default: the lab scene's and
//! the paper's taxels fire within about 1.6 s of the edge.

use palpate_core::{SpikeImages, TaxelLayout};

/// The fitted plane, as an edge.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ArrivalFit {
    /// Edge angle, degrees in (0, 180).
    pub angle_deg: f64,
    /// Sliding speed of the array, `−1/b` (not the edge's normal speed `v·sin θ`), mm/s.
    pub speed_mm_s: f64,
    /// Taxels that fired (and entered the fit).
    pub taxels: usize,
}

/// Per-taxel arrival time, ms (frame centres), or `None` for a taxel that did
/// not fire: the count-weighted mean time of the frames within `half_ms` of
/// the centre of its burst (the count-weighted mean frame of the frames at
/// half its largest count or more).
pub fn arrival_times(images: &SpikeImages, half_ms: f64) -> Vec<Option<f64>> {
    Frames::of(images).arrival_times(half_ms)
}

/// Least-squares plane `t = a + b·x + c·y` through the taxels' arrival
/// times, as an edge; `None` when fewer than 3 taxels fired, when they lie
/// on one line (no plane), or when the plane runs against the motion
/// (`b ≥ 0`: the far side crossed first, no edge sliding `+x` does that).
pub fn arrival_plane(images: &SpikeImages, half_ms: f64) -> Option<ArrivalFit> {
    Frames::of(images).plane(half_ms)
}

/// A borrowed view of spike images: what the stream keeps is not a
/// [`SpikeImages`], but the same counts.
pub(crate) struct Frames<'a> {
    pub layout: &'a TaxelLayout,
    /// `counts[k * n + t]`, `n` the layout's taxels.
    pub counts: &'a [f64],
    pub hop_ms: f64,
    pub window_ms: f64,
}

impl<'a> Frames<'a> {
    fn of(images: &'a SpikeImages) -> Self {
        Frames {
            layout: &images.layout,
            counts: &images.counts,
            hop_ms: images.hop_ms,
            window_ms: images.window_ms,
        }
    }

    fn arrival_times(&self, half_ms: f64) -> Vec<Option<f64>> {
        let n = self.layout.len();
        let frames = self.counts.len().checked_div(n).unwrap_or(0);
        let hop = self.hop_ms;
        // Frames each side of the peak; at least the peak itself.
        let reach = if hop > 0.0 && half_ms.is_finite() {
            (half_ms / hop).floor().clamp(0.0, frames as f64) as usize
        } else {
            frames
        };
        let at = |k: usize, t: usize| self.counts[k * n + t];
        (0..n)
            .map(|t| {
                let max = (0..frames).map(|k| at(k, t)).fold(0.0, f64::max);
                if max <= 0.0 {
                    return None;
                }
                // The burst's centre: the mean frame of the counts at half the
                // maximum or more (a plateau's middle, not its first frame).
                let (mut sw, mut sk) = (0.0, 0.0);
                for k in 0..frames {
                    let c = at(k, t);
                    if c >= 0.5 * max {
                        sw += c;
                        sk += c * k as f64;
                    }
                }
                let centre = (sk / sw).round();
                let centre = if centre.is_finite() {
                    centre.clamp(0.0, (frames - 1) as f64) as usize
                } else {
                    0
                };
                let peak = (centre, max);
                let lo = peak.0.saturating_sub(reach);
                let hi = peak.0.saturating_add(reach).min(frames - 1);
                let (mut sw, mut st) = (0.0, 0.0);
                for k in lo..=hi {
                    let c = at(k, t);
                    sw += c;
                    st += c * (k as f64 * hop + self.window_ms / 2.0);
                }
                let mean = st / sw;
                (sw > 0.0 && mean.is_finite()).then_some(mean)
            })
            .collect()
    }

    pub(crate) fn plane(&self, half_ms: f64) -> Option<ArrivalFit> {
        let times = self.arrival_times(half_ms);
        let pts: Vec<([f64; 2], f64)> = times
            .iter()
            .enumerate()
            .filter_map(|(i, t)| t.map(|t| (self.layout.position(i), t)))
            .filter(|(p, _)| p[0].is_finite() && p[1].is_finite())
            .collect();
        if pts.len() < 3 {
            return None;
        }
        let m = pts.len() as f64;
        let (mx, my, mt) = pts.iter().fold((0.0, 0.0, 0.0), |(a, b, c), (p, t)| {
            (a + p[0] / m, b + p[1] / m, c + t / m)
        });
        let (mut sxx, mut syy, mut sxy, mut sxt, mut syt) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for (p, t) in &pts {
            let (dx, dy, dt) = (p[0] - mx, p[1] - my, t - mt);
            sxx += dx * dx;
            syy += dy * dy;
            sxy += dx * dy;
            sxt += dx * dt;
            syt += dy * dt;
        }
        let det = sxx * syy - sxy * sxy;
        // Collinear taxels (one row or column, or a line of them) fix no plane.
        if !(sxx > 0.0 && syy > 0.0 && det > 1e-9 * sxx * syy) {
            return None;
        }
        let b = (syy * sxt - sxy * syt) / det;
        let c = (sxx * syt - sxy * sxt) / det;
        if !(b < 0.0 && b.is_finite() && c.is_finite()) {
            return None;
        }
        let angle_deg = (-b).atan2(c).to_degrees();
        // b is in ms/mm, so −1/b is mm/ms.
        let speed_mm_s = -1000.0 / b;
        (angle_deg > 0.0 && angle_deg < 180.0 && speed_mm_s.is_finite()).then_some(ArrivalFit {
            angle_deg,
            speed_mm_s,
            taxels: pts.len(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Images of an ideal edge at `theta` crossing at `v` mm/s: each taxel
    /// fires `spikes` counts in the one frame holding its arrival time, plus
    /// `offset_ms` (the same for all), with 10 ms frames.
    fn ideal(theta: f64, v: f64, offset_ms: f64) -> SpikeImages {
        let layout = TaxelLayout::paper();
        let n = layout.len();
        let (s, c) = theta.to_radians().sin_cos();
        let times: Vec<f64> = (0..n)
            .map(|i| {
                let [x, y] = layout.position(i);
                // t = (s0 − n·p)/(v sin θ), s0 chosen so every time is positive.
                let np = x * s - y * c;
                1000.0 * (20.0 - np) / (v * s) + offset_ms
            })
            .collect();
        let hop = 10.0;
        let frames = (times.iter().cloned().fold(0.0, f64::max) / hop) as usize + 10;
        let mut counts = vec![0.0; frames * n];
        for (i, t) in times.iter().enumerate() {
            // Split the spike between the two frames around t, so the
            // centroid is exact at frame resolution.
            let f = (t - hop / 2.0) / hop;
            let k = f.floor() as usize;
            let w = f - k as f64;
            counts[k * n + i] += 1.0 - w;
            counts[(k + 1) * n + i] += w;
        }
        SpikeImages {
            layout,
            window_ms: hop,
            hop_ms: hop,
            n_frames: frames,
            counts,
        }
    }

    #[test]
    fn recovers_angle_and_speed_over_the_half_circle() {
        for theta in [3.0, 10.0, 33.3, 47.2, 84.1, 90.0, 97.8, 152.4, 177.0] {
            for v in [1.0, 2.0, 4.0] {
                let fit = arrival_plane(&ideal(theta, v, 37.0), f64::INFINITY).expect("fit");
                assert!((fit.angle_deg - theta).abs() < 1e-6, "{theta} at {v}: {fit:?}");
                assert!((fit.speed_mm_s - v).abs() < 1e-6 * v, "{theta} at {v}: {fit:?}");
                assert_eq!(fit.taxels, 16);
            }
        }
    }

    #[test]
    fn a_stray_spike_far_away_is_outside_the_window() {
        let mut img = ideal(5.0, 2.0, 0.0);
        // One noise count in the last frame for taxel 15 (bottom right),
        // which the edge crossed first, about a minute earlier.
        let n = img.n_taxels();
        let last = img.n_frames - 1;
        img.counts[last * n + n - 1] += 0.2;
        let all = arrival_plane(&img, f64::INFINITY).expect("fit");
        let windowed = arrival_plane(&img, 3000.0).expect("fit");
        assert!((windowed.angle_deg - 5.0).abs() < 1e-6, "{windowed:?}");
        assert!(
            (all.angle_deg - 5.0).abs() > 1e-3,
            "the stray spike should move the unwindowed fit: {all:?}"
        );
    }

    #[test]
    fn no_plane_from_too_few_collinear_or_backward_taxels() {
        let mut img = ideal(45.0, 2.0, 0.0);
        let n = img.n_taxels();
        // Only row 0 fires: collinear.
        for k in 0..img.n_frames {
            for t in 4..n {
                img.counts[k * n + t] = 0.0;
            }
        }
        assert_eq!(arrival_plane(&img, 3000.0), None);
        // No spikes at all.
        img.counts.iter_mut().for_each(|c| *c = 0.0);
        assert_eq!(arrival_plane(&img, 3000.0), None);
        // Time running backwards along x: the far side first.
        let mut rev = ideal(60.0, 2.0, 0.0);
        let frames = rev.n_frames;
        let mut flipped = vec![0.0; rev.counts.len()];
        for k in 0..frames {
            for t in 0..n {
                flipped[(frames - 1 - k) * n + t] = rev.counts[k * n + t];
            }
        }
        rev.counts = flipped;
        assert_eq!(arrival_plane(&rev, 3000.0), None);
    }

    #[test]
    fn hostile_images_give_no_nan() {
        let layout = TaxelLayout::paper();
        for (hop, window, frames) in [(0.0, 0.0, 3usize), (10.0, 100.0, 0), (f64::MAX, f64::MAX, 2)] {
            let img = SpikeImages {
                layout: layout.clone(),
                window_ms: window,
                hop_ms: hop,
                n_frames: frames,
                counts: (0..frames * 16).map(|i| (i % 7) as f64).collect(),
            };
            if let Some(f) = arrival_plane(&img, 3000.0) {
                assert!(f.angle_deg.is_finite() && f.speed_mm_s.is_finite());
            }
        }
    }
}
