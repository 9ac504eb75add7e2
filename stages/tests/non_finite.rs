//! Every signal stage that notes non-finite input in its own pass (the
//! filter's and encoders' transposes, the normalizer's range, the drive's
//! slopes) refuses NaN and ±inf wherever they sit, naming the stage, taxel
//! and sample, as the full scan it replaced did: first and last samples,
//! the tail the vector kernels leave to scalar code (lengths not a multiple
//! of 4, taxel counts not a multiple of 4) and the middle.

mod common;

use palpate_core::{Payload, Signals, StageConfig, TaxelLayout};
use palpate_stages::encode::izhikevich::IzhikevichConfig;
use palpate_stages::encode::lif::LifConfig;
use palpate_stages::signal::drive::{DriveConfig, DriveKind};
use palpate_stages::signal::lowpass::{FilterMode, LowpassConfig};
use palpate_stages::signal::normalize::NormalizeConfig;

fn signals(taxels: usize, n: usize) -> Signals {
    Signals {
        sample_rate_hz: 1000.0,
        layout: TaxelLayout::Positions {
            positions_mm: (0..taxels).map(|i| [i as f64 * 3.0, 0.0]).collect(),
            taxel_mm: 2.0,
        },
        unit: "V".into(),
        data: (0..taxels)
            .map(|t| (0..n).map(|k| ((k + 7 * t) as f64 * 0.05).sin()).collect())
            .collect(),
    }
}

fn stages() -> Vec<(&'static str, Box<dyn StageConfig>)> {
    vec![
        (
            "lowpass",
            Box::new(LowpassConfig {
                order: 2,
                cutoff_hz: 10.0,
                mode: FilterMode::ZeroPhase,
            }),
        ),
        (
            "lowpass",
            Box::new(LowpassConfig {
                order: 3,
                cutoff_hz: 10.0,
                mode: FilterMode::Causal,
            }),
        ),
        ("normalize", Box::new(NormalizeConfig::default())),
        ("drive", Box::new(DriveConfig::default())),
        (
            "drive",
            Box::new(DriveConfig {
                gain: Some(30.0),
                ..Default::default()
            }),
        ),
        (
            "drive",
            Box::new(DriveConfig {
                kind: DriveKind::Direct,
                ..Default::default()
            }),
        ),
        ("izhikevich", Box::new(IzhikevichConfig::default())),
        ("lif", Box::new(LifConfig::default())),
    ]
}

fn run(cfg: &dyn StageConfig, s: &Signals) -> Result<Payload, String> {
    common::process_one(cfg, s.clone().into())
}

#[test]
fn non_finite_samples_are_named_wherever_they_sit() {
    for (name, cfg) in stages() {
        for (taxels, n) in [(16, 203), (6, 64), (1, 5), (17, 2)] {
            let clean = signals(taxels, n);
            assert!(run(cfg.as_ref(), &clean).is_ok(), "{name}: clean input refused");
            for t in [0, taxels / 2, taxels - 1] {
                for i in [0, 1, n / 2, n.saturating_sub(2), n - 1] {
                    for bad in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
                        let mut s = clean.clone();
                        s.data[t][i] = bad;
                        let e = run(cfg.as_ref(), &s).expect_err("non-finite input must be refused");
                        assert!(
                            e.starts_with(name) && e.contains(&format!("taxel {t}, sample {i} ")),
                            "{name} ({taxels} x {n}, taxel {t}, sample {i}, {bad}): {e}"
                        );
                    }
                }
            }
        }
    }
}

/// The vector checks do not mistake the extreme finite values for NaN or
/// infinity.
#[test]
fn the_largest_finite_values_pass() {
    for (name, cfg) in stages() {
        let mut s = signals(16, 101);
        s.data[3][50] = f64::MAX;
        s.data[15][100] = f64::MIN;
        s.data[0][0] = f64::MIN_POSITIVE / 4.0;
        match run(cfg.as_ref(), &s) {
            Ok(p) => {
                // (A filter of f64::MAX may overflow; the next stage then
                // refuses its output by name. The others stay finite.)
                if let (Ok(out), false) = (p.signals(), name == "lowpass") {
                    assert!(
                        out.data.iter().flatten().all(|x| x.is_finite()),
                        "{name}: non-finite output"
                    );
                }
            }
            Err(e) => panic!("{name}: finite extremes refused: {e}"),
        }
    }
}
