//! The geometry convention shared by scenes and estimators.
//!
//! Array coordinates: mm, origin at the array's centre, `x` along the sliding
//! direction (the array's horizontal axis), `y` up (towards row 0).
//!
//! An edge at angle `θ` (degrees, `0 < θ < 180`, measured counter-clockwise from
//! `+x`) is the line with direction `u = (cos θ, sin θ)`. Its unit normal
//! `n = (sin θ, -cos θ)` points towards `+x` (its x-component `sin θ` is positive).
//! The edge's position is its offset `s`: the line is `{p : n·p = s}`, and the
//! object lies on the side `n·p < s`.
//!
//! The array slides `+x` at speed `v` (mm/s) off the object, so in array
//! coordinates the edge moves the other way and its offset falls at
//! `ds/dt = -v sin θ`: taxels with the largest `n·p` leave the object first.
//! Hence the time to cross the array grows like `1 / sin θ` at fixed extent, and
//! the extent of a square array along `n` grows like `sin θ + |cos θ|`, giving
//! the paper's `1 + |cot θ|` growth of crossing time.

use crate::payload::TaxelLayout;

/// An edge's direction and normal, from its angle in degrees.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Edge {
    /// Angle from `+x`, degrees.
    pub theta_deg: f64,
    /// Unit normal `(sin θ, -cos θ)`, pointing towards `+x`.
    pub normal: [f64; 2],
}

impl Edge {
    /// The edge at `theta_deg`.
    pub fn new(theta_deg: f64) -> Self {
        let t = theta_deg.to_radians();
        Edge {
            theta_deg,
            normal: [t.sin(), -t.cos()],
        }
    }

    /// Signed offset `n·p` of point `p` (mm).
    pub fn offset(&self, p: [f64; 2]) -> f64 {
        self.normal[0] * p[0] + self.normal[1] * p[1]
    }

    /// Speed at which the edge's offset falls when the array slides at `speed_mm_s`
    /// (mm/s): `v sin θ`.
    pub fn normal_speed(&self, speed_mm_s: f64) -> f64 {
        speed_mm_s * self.normal[0]
    }

    /// `(min, max)` of `n·p` over the whole area of every taxel of `layout`
    /// (square taxels of side `taxel_mm`): the offsets between which the edge
    /// touches some taxel.
    pub fn footprint(&self, layout: &TaxelLayout) -> (f64, f64) {
        let h = layout.taxel_mm() / 2.0 * (self.normal[0].abs() + self.normal[1].abs());
        let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
        for p in layout.positions() {
            let o = self.offset(p);
            lo = lo.min(o - h);
            hi = hi.max(o + h);
        }
        (lo, hi)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crossing_extent_of_the_paper_array() {
        let l = TaxelLayout::paper();
        // At 90 degrees the normal is +x: the footprint spans the 11 mm of taxels.
        let (lo, hi) = Edge::new(90.0).footprint(&l);
        assert!((hi - lo - 11.0).abs() < 1e-12);
        // At 45 degrees: 11 mm * (sin + cos).
        let (lo, hi) = Edge::new(45.0).footprint(&l);
        assert!((hi - lo - 11.0 * 2f64.sqrt()).abs() < 1e-9);
        // The normal points to +x for every angle in (0, 180).
        for a in [1.0, 45.0, 90.0, 135.0, 179.0] {
            assert!(Edge::new(a).normal[0] > 0.0);
        }
    }
}
