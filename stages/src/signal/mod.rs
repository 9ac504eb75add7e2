//! Signal stages: normalization, filters, derivatives and drives.
//!
//! Every stage here maps [`Signals`] to [`Signals`] of the same rate and layout,
//! one taxel at a time:
//!
//! | type | what it computes |
//! |---|---|
//! | `normalize` | each taxel to `[0, 1]`, over the whole trial or causally from a baseline |
//! | `lowpass` | Butterworth low-pass, cascaded second-order sections, zero-phase or causal |
//! | `derivative` | `dV/dt` per second |
//! | `drive` | the neuron's input current: FA-I `G·|dV/dt|` (paper eq. 4), SA-I `G·V`, or the signal itself |
//!
//! Input samples must be finite: a NaN or infinite sample is a [`StageError`]
//! naming the stage, taxel and sample index (the user guide's "Numerical hard cases"), never a NaN
//! that travels on.

pub mod derivative;
pub mod drive;
pub mod lowpass;
pub mod normalize;

use palpate_core::{Signals, StageError};

/// Checks that every sample is finite and every taxel has the same length.
///
/// `what` names the stage (type name) in the message.
pub fn check_signals(what: &str, s: &Signals) -> Result<(), StageError> {
    check_shape(what, s)?;
    for (taxel, xs) in s.data.iter().enumerate() {
        if let Some(i) = first_non_finite(xs) {
            return Err(StageError::new(format!(
                "{what}: taxel {taxel}, sample {i} (t = {} ms) is {} (not finite)",
                fmt_ms(i as f64 * 1000.0 / s.sample_rate_hz),
                xs[i]
            )));
        }
    }
    Ok(())
}

/// [`check_signals`] without the scan for non-finite samples: the sample
/// rate, one row per taxel, rows of equal length.
///
/// Why apart: the scan reads the whole trial (2.8 MB for a 21 s lab trial,
/// ~0.1 ms), and a stage that reads every sample anyway (the filter's and
/// encoders' transposes, the normalizer's range) notes non-finite values in
/// that same pass and calls [`check_signals`] only to name the first one.
pub fn check_shape(what: &str, s: &Signals) -> Result<(), StageError> {
    if !(s.sample_rate_hz.is_finite() && s.sample_rate_hz > 0.0) {
        return Err(StageError::new(format!(
            "{what}: sample rate must be a positive number of Hz, got {}",
            palpate_core::fmt_num(s.sample_rate_hz)
        )));
    }
    if s.data.len() != s.layout.len() {
        return Err(StageError::new(format!(
            "{what}: the layout has {} taxels but the signals hold {}",
            s.layout.len(),
            s.data.len()
        )));
    }
    let n = s.n_samples();
    for (taxel, xs) in s.data.iter().enumerate() {
        if xs.len() != n {
            return Err(StageError::new(format!(
                "{what}: taxel {taxel} has {} samples, taxel 0 has {n}",
                xs.len()
            )));
        }
    }
    Ok(())
}

/// A time in ms for a message: three decimals, or in exponent form when
/// huge (a sample rate of 1e-297 Hz puts sample 1 at 1e300 ms, which `{:.3}`
/// writes as 301 digits).
pub fn fmt_ms(t: f64) -> String {
    if t.abs() < 1e15 {
        format!("{t:.3}")
    } else {
        palpate_core::fmt_num(t)
    }
}

/// The error of [`check_signals`] for signals a pass found a non-finite
/// sample in (an internal error if the scan finds none).
pub fn non_finite_error(what: &str, s: &Signals) -> StageError {
    match check_signals(what, s) {
        Err(e) => e,
        Ok(()) => StageError::new(format!("{what}: a non-finite value appeared (internal error)")),
    }
}

/// True when `x` is neither NaN nor infinite, as one compare that
/// vectorizes (`!(|x| <= MAX)` holds exactly for NaN and ±inf).
#[inline(always)]
pub fn finite(x: f64) -> bool {
    x.abs() <= f64::MAX
}

/// Index of the first NaN or infinite sample. Scans 64 samples at a time
/// without a branch per sample (`!(|x| <= MAX)` is true exactly for NaN and
/// ±inf), so the check every signal stage makes of its input vectorizes:
/// ~0.1 ns a sample instead of ~1.
pub fn first_non_finite(xs: &[f64]) -> Option<usize> {
    for (c, chunk) in xs.chunks(64).enumerate() {
        let bad = chunk.iter().fold(false, |b, &x| b | !finite(x));
        if bad {
            return chunk.iter().position(|x| !x.is_finite()).map(|i| c * 64 + i);
        }
    }
    None
}

#[cfg(test)]
pub(crate) mod testdata {
    //! Signals the tests of this family share.
    use palpate_core::{Signals, TaxelLayout};

    /// A 4 x 4 array at `fs` Hz: every taxel holds at 1 for `hold_s`, ramps
    /// linearly to 0 over `ramp_s` (taxel `i` starts `i * stagger_s` later), and
    /// holds at 0 until `total_s`.
    pub fn ramps(fs: f64, hold_s: f64, ramp_s: f64, stagger_s: f64, total_s: f64) -> Signals {
        let n = (total_s * fs).round() as usize;
        let data = (0..16)
            .map(|i| {
                let start = hold_s + i as f64 * stagger_s;
                (0..n)
                    .map(|k| {
                        let t = k as f64 / fs;
                        (1.0 - (t - start) / ramp_s).clamp(0.0, 1.0)
                    })
                    .collect()
            })
            .collect();
        Signals {
            sample_rate_hz: fs,
            layout: TaxelLayout::paper(),
            unit: "V".into(),
            data,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn non_finite_samples_are_named() {
        let mut s = testdata::ramps(1000.0, 0.1, 0.1, 0.0, 0.5);
        assert!(check_signals("t", &s).is_ok());
        s.data[3][42] = f64::NAN;
        let e = check_signals("normalize", &s).unwrap_err().message;
        assert!(e.contains("taxel 3") && e.contains("sample 42"), "{e}");
        s.data[3][42] = 0.0;
        for (i, bad) in [
            (0, f64::INFINITY),
            (63, f64::NEG_INFINITY),
            (64, f64::NAN),
            (199, f64::NAN),
        ] {
            let mut xs = vec![f64::MAX; 200];
            xs[i] = bad;
            assert_eq!(first_non_finite(&xs), Some(i));
        }
        assert_eq!(first_non_finite(&[f64::MAX, f64::MIN, 0.0, -0.0, 1e-320]), None);
        // A sample time at an absurdly low rate prints in exponent form.
        let mut slow = testdata::ramps(1000.0, 0.01, 0.01, 0.0, 0.05);
        slow.sample_rate_hz = 1e-297;
        slow.data[0][3] = f64::NAN;
        let e = check_signals("derivative", &slow).unwrap_err().message;
        assert!(e.contains("e300 ms") && e.len() < 120, "{e}");
        s.data[5].pop();
        assert!(check_signals("t", &s).unwrap_err().message.contains("taxel 5"));
    }
}
