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
    if !(s.sample_rate_hz.is_finite() && s.sample_rate_hz > 0.0) {
        return Err(StageError::new(format!(
            "{what}: sample rate must be a positive number of Hz, got {}",
            s.sample_rate_hz
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
        if let Some(i) = xs.iter().position(|x| !x.is_finite()) {
            return Err(StageError::new(format!(
                "{what}: taxel {taxel}, sample {i} (t = {:.3} ms) is {} (not finite)",
                i as f64 * 1000.0 / s.sample_rate_hz,
                xs[i]
            )));
        }
    }
    Ok(())
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
        s.data[5].pop();
        assert!(check_signals("t", &s).unwrap_err().message.contains("taxel 5"));
    }
}
