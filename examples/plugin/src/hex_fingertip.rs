//! `hex_fingertip`: a sensor that is not a grid — taxels on a hexagonal lattice
//! filling a fingertip-shaped (elliptical) patch — simulated by palpate's scene
//! simulator.
//!
//! Lattice: rows `j` at `y = j * pitch * sqrt(3)/2`, taxels at
//! `x = (i + j/2) * pitch` (every other row shifted by half a pitch), kept where
//! `(x/a)^2 + (y/b)^2 <= 1` with semi-axes `a = width_mm/2` (along the sliding
//! direction) and `b = length_mm/2`. The centre taxel sits at the origin.
//!
//! The stage builds a [`palpate_stages::scene::SceneConfig`] with this explicit
//! layout and everything else (motion, angles, effects) from its keys, and
//! returns the scene's own source: the plugin adds a sensor without a line of
//! simulation code, and every scene effect works on it.

use palpate_core::{register_stage, BuildContext, ConfigError, InputSpec, PayloadKind, Stage, StageConfig};
use palpate_stages::scene::SceneConfig;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use std::path::PathBuf;

/// A fingertip skin of taxels on a hexagonal lattice (plugin example), crossed by
/// an edge as in the paper; simulated by the built-in scene simulator.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct HexFingertipConfig {
    /// Extent of the patch along the sliding direction (x), mm. Default 12.
    pub width_mm: f64,
    /// Extent of the patch across it (y), mm. Default 14.
    pub length_mm: f64,
    /// Centre-to-centre spacing of neighbouring taxels, mm. Default 3.
    pub pitch_mm: f64,
    /// Side of each (square) taxel, mm. Default 2.
    pub taxel_mm: f64,
    /// A scene file giving motion, angles and effects (e.g. the built-in
    /// "../../../graphs/scenes/lab.toml"), relative to the graph. Default: none
    /// (the ideal scene with the paper's motion and angles).
    pub scene: Option<PathBuf>,
    /// Edge orientations, degrees, each in (0, 180). Default: the scene's (the
    /// paper's 17 classes, 10 to 90 by 5).
    pub angles: Option<Vec<f64>>,
    /// Repetitions of every angle. Default: the scene's (10).
    pub trials_per_angle: Option<usize>,
}

impl Default for HexFingertipConfig {
    fn default() -> Self {
        HexFingertipConfig {
            width_mm: 12.0,
            length_mm: 14.0,
            pitch_mm: 3.0,
            taxel_mm: 2.0,
            scene: None,
            angles: None,
            trials_per_angle: None,
        }
    }
}

impl HexFingertipConfig {
    /// Taxel centres, mm, in row-major order from the top row.
    pub fn positions(&self) -> Vec<[f64; 2]> {
        let (a, b) = (self.width_mm / 2.0, self.length_mm / 2.0);
        let dy = self.pitch_mm * 3f64.sqrt() / 2.0;
        let rows = (b / dy).floor() as i64;
        let mut out = Vec::new();
        for j in (-rows..=rows).rev() {
            let y = j as f64 * dy;
            let shift = if j.rem_euclid(2) == 1 { 0.5 } else { 0.0 };
            let cols = (a / self.pitch_mm).ceil() as i64 + 1;
            for i in -cols..=cols {
                let x = (i as f64 + shift) * self.pitch_mm;
                if (x / a).powi(2) + (y / b).powi(2) <= 1.0 + 1e-12 {
                    out.push([x, y]);
                }
            }
        }
        out
    }

    fn scene_config(&self) -> Result<SceneConfig, ConfigError> {
        let positions = self.positions();
        if positions.len() < 3 {
            return Err(ConfigError::key(
                "pitch_mm",
                format!(
                    "the patch holds {} taxel(s); make it larger or the pitch smaller",
                    positions.len()
                ),
            ));
        }
        let mut keys = serde_json::json!({
            "layout": { "positions_mm": positions, "taxel_mm": self.taxel_mm },
        });
        if let Some(f) = &self.scene {
            keys["file"] = serde_json::json!(f);
        }
        if let Some(a) = &self.angles {
            keys["angles"] = serde_json::json!(a);
        }
        if let Some(t) = self.trials_per_angle {
            keys["trials_per_angle"] = serde_json::json!(t);
        }
        serde_json::from_value(keys).map_err(|e| ConfigError::general(format!("building the scene: {e}")))
    }
}

#[typetag::serde(name = "hex_fingertip")]
impl StageConfig for HexFingertipConfig {
    fn inputs(&self) -> InputSpec {
        InputSpec::none()
    }
    fn output(&self) -> Option<PayloadKind> {
        Some(PayloadKind::Signals)
    }
    fn build(&self, ctx: &BuildContext) -> Result<Stage, ConfigError> {
        for (key, v) in [
            ("width_mm", self.width_mm),
            ("length_mm", self.length_mm),
            ("pitch_mm", self.pitch_mm),
            ("taxel_mm", self.taxel_mm),
        ] {
            palpate_core::check_positive(key, v, "mm")?;
        }
        if self.taxel_mm > self.pitch_mm {
            return Err(ConfigError::key(
                "taxel_mm",
                "taxels would overlap: make it at most pitch_mm",
            ));
        }
        self.scene_config()?.build(ctx)
    }
}
register_stage!("hex_fingertip", HexFingertipConfig);

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lattice_is_hexagonal_and_inside_the_patch() {
        let c = HexFingertipConfig::default();
        let p = c.positions();
        assert!(p.len() >= 12, "{}", p.len());
        assert!(p.contains(&[0.0, 0.0]));
        // Every taxel's nearest neighbour is one pitch away (a hexagonal lattice).
        for a in &p {
            let nearest = p
                .iter()
                .filter(|b| *b != a)
                .map(|b| ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)).sqrt())
                .fold(f64::INFINITY, f64::min);
            assert!((nearest - c.pitch_mm).abs() < 1e-9, "{a:?}: {nearest}");
            assert!((a[0] / 6.0).powi(2) + (a[1] / 7.0).powi(2) <= 1.0 + 1e-9);
        }
        // Not a grid: rows alternate by half a pitch.
        let xs_row0: Vec<f64> = p.iter().filter(|q| q[1] == 0.0).map(|q| q[0]).collect();
        assert!(xs_row0.iter().all(|x| (x / 3.0).fract().abs() < 1e-9));
        assert!(p.iter().any(|q| ((q[0] / 3.0).fract().abs() - 0.5).abs() < 1e-9));
    }

    #[test]
    fn a_tiny_patch_is_an_error_naming_the_key() {
        let c = HexFingertipConfig {
            width_mm: 1.0,
            length_mm: 1.0,
            ..Default::default()
        };
        let ctx = BuildContext {
            stage_id: "hex".into(),
            seed: 0,
            out_dir: std::env::temp_dir(),
            base_dir: ".".into(),
        };
        let e = c.build(&ctx).err().unwrap();
        assert_eq!(e.key.as_deref(), Some("pitch_mm"));
    }
}
