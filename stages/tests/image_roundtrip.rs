//! `write_images` -> `image_file`: the images, labels, groups and trial order
//! come back identical, in both formats; and what `image_file` refuses.

mod common;
use common::run_graph_file as run_graph;
use palpate_core::{Item, Payload};
use std::path::Path;

/// Simulated spike images of 3 angles x 2 trials (the 4x4 lab-like array),
/// written by `write_images` in `format` into `<dir>/out/images`.
fn write(dir: &Path, format: &str) -> Vec<Item> {
    let toml = format!(
        r#"
[run]
seed = 3
out = "{out}"

[stages.scene]
type = "scene"
angles = [30, 45, 90]
trials_per_angle = 2
motion = {{ hold_before_s = 0.2, hold_after_s = 0.2, speed_mm_s = 10.0 }}
effects = [{{ kind = "noise", sigma = 0.002 }}]

[stages.filter]
type = "lowpass"
inputs = ["scene"]
cutoff_hz = 20.0

[stages.norm]
type = "normalize"
inputs = ["filter"]

[stages.drive]
type = "drive"
inputs = ["norm"]

[stages.enc]
type = "izhikevich"
inputs = ["drive"]

[stages.bins]
type = "bin"
inputs = ["enc"]
window_ms = 30.0
hop_ms = 7.5

[stages.images]
type = "write_images"
inputs = ["bins"]
format = "{format}"
"#,
        out = dir.join("out").display()
    );
    let r = run_graph(dir, "write.toml", &toml).unwrap_or_else(|e| panic!("{e}"));
    r.outputs["bins"].to_vec()
}

fn read(dir: &Path, extra: &str) -> Result<Vec<Item>, String> {
    // Reports go into the test's own folder, never the crate's working folder.
    let toml = format!(
        r#"
[run]
out = "{out}"

[stages.images]
type = "image_file"
dir = "out/images"
{extra}

[stages.wss]
type = "wss"
inputs = ["images"]
angles = [30, 45, 90]

[stages.mae]
type = "mae"
inputs = ["wss"]
"#,
        out = dir.join("out/read").display()
    );
    run_graph(dir, "read.toml", &toml).map(|r| r.outputs["images"].to_vec())
}

fn assert_same(written: &[Item], read: &[Item]) {
    assert_eq!(written.len(), 6);
    assert_eq!(read.len(), written.len());
    let mut spikes = 0.0;
    for (w, r) in written.iter().zip(read) {
        assert_eq!(r.meta.trial_id, w.meta.trial_id);
        assert_eq!(r.meta.index, w.meta.index);
        assert_eq!(r.meta.label, w.meta.label);
        assert_eq!(r.meta.group, w.meta.group);
        let (Payload::Images(a), Payload::Images(b)) = (&w.payload, &r.payload) else {
            panic!("not images");
        };
        // Same layout, window, hop, frame count and every count's bits.
        assert_eq!(**a, **b, "trial {}", w.meta.trial_id);
        spikes += a.counts.iter().sum::<f64>();
    }
    assert!(spikes > 0.0, "the test images hold spikes");
}

#[test]
fn csv_images_round_trip() {
    let d = tempfile::tempdir().unwrap();
    let written = write(d.path(), "csv");
    assert_same(&written, &read(d.path(), "").unwrap());
}

#[test]
fn npy_images_round_trip() {
    let d = tempfile::tempdir().unwrap();
    let written = write(d.path(), "npy");
    assert_same(&written, &read(d.path(), "").unwrap());
}

#[test]
fn without_info_json_the_keys_are_needed_and_suffice() {
    let d = tempfile::tempdir().unwrap();
    let written = write(d.path(), "npy");
    std::fs::remove_file(d.path().join("out/images/info.json")).unwrap();
    let e = read(d.path(), "").unwrap_err();
    for key in ["layout", "window_ms", "hop_ms", "format"] {
        assert!(e.contains(&format!("key `{key}`")), "{e}");
    }
    let keys = "format = \"npy\"\nwindow_ms = 30.0\nhop_ms = 7.5\n\
                layout = { kind = \"grid\", rows = 4, cols = 4, pitch_mm = 3.0, taxel_mm = 2.0 }";
    let back = read(d.path(), keys).unwrap();
    // Without info.json's order the files come in name order.
    let mut by_id = written.clone();
    by_id.sort_by(|a, b| a.meta.trial_id.cmp(&b.meta.trial_id));
    for (w, r) in by_id.iter().zip(&back) {
        assert_eq!(r.meta.trial_id, w.meta.trial_id);
        let (Payload::Images(a), Payload::Images(b)) = (&w.payload, &r.payload) else {
            panic!("not images");
        };
        assert_eq!(a, b);
    }
}

#[test]
fn wrong_files_are_named_errors() {
    let d = tempfile::tempdir().unwrap();
    write(d.path(), "csv");
    let f = d.path().join("out/images/edge-45deg-r01.csv");
    let text = std::fs::read_to_string(&f).unwrap();
    // A negative count.
    let mut lines: Vec<String> = text.lines().map(str::to_string).collect();
    lines[2] = lines[2].replacen(",0", ",-1", 1);
    std::fs::write(&f, lines.join("\n")).unwrap();
    let e = read(d.path(), "").unwrap_err();
    assert!(
        e.contains("edge-45deg-r01.csv") && e.contains("not a spike count"),
        "{e}"
    );
    // Another hop.
    // Another hop than info.json's: refused before any file is read.
    let e = read(d.path(), "hop_ms = 5.0").unwrap_err();
    assert!(
        e.contains("key `hop_ms`") && e.contains("info.json records 7.5 ms"),
        "{e}"
    );
    // No folder.
    let e = read(d.path(), "").map(|_| ());
    assert!(e.is_err());
    std::fs::remove_dir_all(d.path().join("out/images")).unwrap();
    let e = read(d.path(), "").unwrap_err();
    assert!(e.contains("key `dir`") && e.contains("not found"), "{e}");
}
