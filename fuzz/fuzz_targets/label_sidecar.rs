//! Label sidecars (TOML, or CSV when the first byte is odd) on arbitrary text:
//! an error or labels whose numbers are finite (durations positive); the
//! layout a sidecar declares is an error or a valid layout.
#![no_main]
use libfuzzer_sys::fuzz_target;
use palpate_stages::io::common::{parse_sidecar, parse_sidecar_layout};

fuzz_target!(|data: &[u8]| {
    let Some((&first, rest)) = data.split_first() else {
        return;
    };
    let Ok(text) = std::str::from_utf8(rest) else {
        return;
    };
    let ext = if first % 2 == 1 { "csv" } else { "toml" };
    if let Ok(Some(l)) = parse_sidecar_layout(text, if first % 4 == 1 { "json" } else { ext }, "fuzz") {
        assert!(l.validate().is_ok() && l.len() >= 1);
    }
    if let Ok(map) = parse_sidecar(text, ext, "fuzz") {
        for l in map.values() {
            assert!(l.angle_deg.is_none_or(f64::is_finite));
            assert!(l.duration_ms.is_none_or(|d| d.is_finite() && d > 0.0));
        }
    }
});
