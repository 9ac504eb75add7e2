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

use super::check_signals;
use palpate_core::{
    register_stage, BuildContext, ConfigError, InputSpec, Item, Map, Payload, PayloadKind, Stage,
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
        let data = s
            .data
            .iter()
            .map(|xs| differentiate(xs, s.sample_rate_hz, self.scheme))
            .collect();
        Ok(s.with_data(format!("{}/s", s.unit), data).into())
    }
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
