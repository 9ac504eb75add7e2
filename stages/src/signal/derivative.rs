//! `derivative`: `dV/dt` of each taxel, in input units per second.
//!
//! With sample period `h = 1/fs`:
//!
//! * `central` (offline, default): `(x[i+1] - x[i-1]) / 2h` inside the trial,
//!   one-sided `(x[1] - x[0]) / h` and `(x[n-1] - x[n-2]) / h` at the ends.
//!   Second-order accurate and without lag (it looks half a sample ahead).
//! * `backward` (causal, for live data): `(x[i] - x[i-1]) / h`, and 0 at the
//!   first sample. First-order accurate; lags half a sample.
//!
//! A trial with a single sample has derivative 0.
//!
//! A slope larger than f64 holds (a change between samples times `fs`
//! above ~1.8e308: an absurd sample rate, or values near `f64::MAX`) is an
//! error naming the stage, taxel and sample, never an infinity passed on.

use super::{check_signals, first_non_finite};
use palpate_core::{
    fmt_num, register_stage, BuildContext, ConfigError, InputSpec, Item, Map, Payload, PayloadKind, Stage,
    StageConfig, StageError, TrialContext,
};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// Finite-difference scheme.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, JsonSchema, Default)]
#[serde(rename_all = "snake_case")]
pub enum DiffScheme {
    /// Central differences (offline, no lag).
    #[default]
    Central,
    /// Backward differences (causal).
    Backward,
}

/// Time derivative dV/dt of each taxel, per second (central or causal backward differences).
#[derive(Clone, Debug, Default, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct DerivativeConfig {
    /// `central` (offline, no lag) or `backward` (causal). Default `central`.
    pub scheme: DiffScheme,
}

#[typetag::serde(name = "derivative")]
impl StageConfig for DerivativeConfig {
    fn inputs(&self) -> InputSpec {
        InputSpec::one(PayloadKind::Signals)
    }
    fn output(&self) -> Option<PayloadKind> {
        Some(PayloadKind::Signals)
    }
    fn build(&self, _ctx: &BuildContext) -> Result<Stage, ConfigError> {
        Ok(Stage::Map(Box::new(Derivative { scheme: self.scheme })))
    }
}
register_stage!("derivative", DerivativeConfig);

/// The runtime `derivative` stage.
pub struct Derivative {
    scheme: DiffScheme,
}

/// `dx/dt` per second of samples `xs` at `fs` Hz.
pub fn differentiate(xs: &[f64], fs: f64, scheme: DiffScheme) -> Vec<f64> {
    let n = xs.len();
    let mut d = vec![0.0; n];
    if n < 2 {
        return d;
    }
    match scheme {
        DiffScheme::Central => {
            d[0] = (xs[1] - xs[0]) * fs;
            d[n - 1] = (xs[n - 1] - xs[n - 2]) * fs;
            let half = 0.5 * fs;
            for i in 1..n - 1 {
                d[i] = (xs[i + 1] - xs[i - 1]) * half;
            }
        }
        DiffScheme::Backward => {
            for i in 1..n {
                d[i] = (xs[i] - xs[i - 1]) * fs;
            }
        }
    }
    d
}

impl Map for Derivative {
    fn process(&self, inputs: &[&Item], _ctx: &TrialContext<'_>) -> Result<Payload, StageError> {
        let s = inputs[0].payload.signals()?;
        check_signals("derivative", s)?;
        let fs = s.sample_rate_hz;
        let mut data = Vec::with_capacity(s.data.len());
        for (taxel, xs) in s.data.iter().enumerate() {
            let d = differentiate(xs, fs, self.scheme);
            // Finite inputs give a non-finite slope only by overflow.
            if let Some(i) = first_non_finite(&d) {
                return Err(overflow_error("derivative", taxel, i, fs));
            }
            data.push(d);
        }
        Ok(s.with_data(format!("{}/s", s.unit), data).into())
    }
}

/// The error of a slope that overflows f64 at `taxel`, sample `i`, for
/// stage `what` at sample rate `fs`.
pub fn overflow_error(what: &str, taxel: usize, i: usize, fs: f64) -> StageError {
    StageError::new(format!(
        "{what}: taxel {taxel}, sample {i}: dV/dt is larger than f64 holds (the change between \
         samples times the sample rate, {} Hz); check the input's sample rate and values",
        fmt_num(fs)
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ramp_slope_is_exact_per_second() {
        let fs = 1000.0;
        let xs: Vec<f64> = (0..100).map(|i| 3.0 - 2.0 * i as f64 / fs).collect();
        for scheme in [DiffScheme::Central, DiffScheme::Backward] {
            let d = differentiate(&xs, fs, scheme);
            for &v in &d[1..] {
                assert!((v + 2.0).abs() < 1e-9, "{scheme:?}: {v}");
            }
        }
        assert_eq!(differentiate(&xs, fs, DiffScheme::Backward)[0], 0.0);
        assert_eq!(differentiate(&[5.0], fs, DiffScheme::Central), vec![0.0]);
    }

    /// At an absurd sample rate the slope overflows: the stage names
    /// itself, the taxel and the sample instead of passing an infinity on.
    #[test]
    fn an_overflowing_slope_is_a_named_error() {
        let meta = palpate_core::TrialMeta::default();
        let ctx = TrialContext {
            stage_id: "d",
            meta: &meta,
            seed: 0,
        };
        let mut s = crate::signal::testdata::ramps(1000.0, 0.01, 0.01, 0.0, 0.05);
        let run = |s: &palpate_core::Signals, scheme| {
            let item = Item {
                meta: std::sync::Arc::new(meta.clone()),
                payload: s.clone().into(),
            };
            Derivative { scheme }.process(&[&item], &ctx)
        };
        // A glitch of 5 in taxel 2: a change of 5 in one or two samples.
        s.data[2][20] = 5.0;
        for (scheme, at) in [(DiffScheme::Central, 19), (DiffScheme::Backward, 20)] {
            s.sample_rate_hz = 1e300;
            let ok = run(&s, scheme).unwrap();
            assert!(ok.signals().unwrap().data.iter().flatten().all(|v| v.is_finite()));
            s.sample_rate_hz = f64::MAX;
            let e = run(&s, scheme).err().unwrap().message;
            assert!(
                e.starts_with(&format!("derivative: taxel 2, sample {at}:"))
                    && e.contains("1.7976931348623157e308 Hz"),
                "{e}"
            );
        }
    }

    #[test]
    fn central_is_second_order_on_a_parabola() {
        let fs = 100.0;
        let xs: Vec<f64> = (0..50).map(|i| (i as f64 / fs).powi(2)).collect();
        let d = differentiate(&xs, fs, DiffScheme::Central);
        for (i, &v) in d.iter().enumerate().take(49).skip(1) {
            assert!((v - 2.0 * i as f64 / fs).abs() < 1e-9);
        }
    }
}
