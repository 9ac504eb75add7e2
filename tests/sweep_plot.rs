//! A sweep's declared figures (`[[sweep.plot]]`): `palpate run` writes each
//! SVG with one series per `by` value (points averaged as documented), the
//! per-class MAE reaches `x = "class"` plots, and `palpate check` refuses a
//! bad declaration naming `sweep.plot[i].<key>`.

use std::process::Command;

fn palpate_in(dir: &std::path::Path) -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_palpate"));
    c.current_dir(dir);
    c
}

/// A small sweep on the ideal scene (4 angles x 2 trials, 4 points, 2 repeats):
/// seconds in a debug build.
fn graph(plots: &str) -> String {
    let scene = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("graphs/scenes/ideal.toml");
    format!(
        r#"[run]
seed = 3

[stages.scene]
type = "scene"
file = "{}"
trials_per_angle = 2
angles = {{ from = 30, to = 90, step = 20 }}

[stages.drive]
type = "drive"
inputs = ["scene"]
kind = "fa_i"

[stages.enc]
type = "izhikevich"
inputs = ["drive"]
preset = "fa_i"
dt_ms = 1.0

[stages.bins]
type = "bin"
inputs = ["enc"]
window_ms = 100.0
hop_ms = 20.0

[stages.wss]
type = "wss"
inputs = ["bins"]
angles = {{ from = 30.0, to = 90.0, step = 20.0 }}

[stages.mae]
type = "mae"
inputs = ["wss"]
per_class = false

[sweep]
key = "stages.bins"
values = [
  {{ hop_ms = 20.0, window_ms = 100.0 }}, {{ hop_ms = 40.0, window_ms = 100.0 }},
  {{ hop_ms = 20.0, window_ms = 200.0 }}, {{ hop_ms = 40.0, window_ms = 200.0 }},
]
repeats = 2
metrics = ["wss.mae_deg", "wss.no_edge"]
{plots}"#,
        scene.display().to_string().replace('\\', "/")
    )
}

/// Every element whose class is exactly `class`.
fn count(svg: &str, class: &str) -> usize {
    svg.matches(&format!("class=\"{class}\"")).count()
}

#[test]
fn a_declared_plot_is_written_with_one_series_per_by_value() {
    let d = tempfile::tempdir().unwrap();
    let plots = r#"
[[sweep.plot]]
file = "by_window.svg"
metric = "wss.mae_deg"
x = "hop_ms"
by = "window_ms"
legend = { "window_ms = 100" = "100 ms window" }

[[sweep.plot.reference]]
name = "published"
points = [[20, 1.0], [40, 2.0]]

[[sweep.plot]]
file = "per_class.svg"
metric = "wss.mae_deg"
x = "class"
by = "window_ms"
kind = "bars"
value_labels = true

[[sweep.plot]]
file = "by_hop.svg"
metric = "wss.no_edge"
x = "hop_ms"
kind = "bars"
"#;
    std::fs::write(d.path().join("g.toml"), graph(plots)).unwrap();
    let out = palpate_in(d.path())
        .args(["run", "g.toml", "--out", "o"])
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stdout}\n{stderr}");
    let read = |f: &str| {
        std::fs::read_to_string(d.path().join("o").join(f)).unwrap_or_else(|e| panic!("{f}: {e}\n{stdout}"))
    };

    // Two windows: two lines of two hops each, the reference dashed beside them.
    let svg = read("by_window.svg");
    assert_eq!(count(&svg, "line"), 2, "{svg}");
    assert_eq!(count(&svg, "point"), 4);
    assert_eq!(count(&svg, "reference"), 1);
    assert_eq!(count(&svg, "legend-entry"), 3);
    assert!(svg.contains(">100 ms window</text>") && svg.contains(">window_ms = 200</text>"));
    assert!(stdout.contains("by_window.svg: 2 series, 4 points"), "{stdout}");

    // Per class: 2 series over the 4 true angles, at most one bar each (a
    // class answered only "no edge" has no MAE); averaged over hops and repeats.
    let svg = read("per_class.svg");
    assert_eq!(count(&svg, "legend-entry"), 2, "{svg}");
    assert_eq!(count(&svg, "tick-x"), 4, "one group per class");
    let bars = count(&svg, "bar");
    assert!((6..=8).contains(&bars), "{bars} bars\n{svg}");
    assert_eq!(count(&svg, "bar-value"), bars);
    for angle in ["30", "50", "70", "90"] {
        assert!(svg.contains(&format!(">{angle}</text>")), "class {angle}");
    }

    // One series without `by`: one bar per hop, no legend.
    let svg = read("by_hop.svg");
    assert_eq!(count(&svg, "bar"), 2, "{svg}");
    assert_eq!(count(&svg, "legend-entry"), 0);
    // The automatic plots are still written.
    assert!(d.path().join("o/sweep.json").exists());
}

#[test]
fn check_refuses_a_bad_plot_naming_its_key() {
    let d = tempfile::tempdir().unwrap();
    let plots = r#"
[[sweep.plot]]
file = "fine.svg"
metric = "wss.mae_deg"
x = "hop_ms"

[[sweep.plot]]
file = "../outside.svg"
metric = "wss.sd_deg"
x = "hop"
"#;
    std::fs::write(d.path().join("g.toml"), graph(plots)).unwrap();
    let out = palpate_in(d.path()).args(["check", "g.toml"]).output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{err}");
    assert!(
        err.contains("`sweep.plot[1].file`") && err.contains("../outside.svg"),
        "{err}"
    );
    assert!(
        err.contains("`sweep.plot[1].metric`") && err.contains("wss.sd_deg"),
        "not among the sweep's metrics: {err}"
    );
    assert!(
        err.contains("`sweep.plot[1].x`") && err.contains("`hop`"),
        "{err}"
    );
    assert!(!err.contains("sweep.plot[0]"), "the first plot is fine: {err}");
    assert!(err.contains("3 errors"), "{err}");

    // A line plot needs numbers on x; an unknown key is named with its plot.
    for (plots, want) in [
        (
            "[[sweep.plot]]\nfile = \"a.svg\"\nmetric = \"wss.mae_deg\"\n",
            "`sweep.plot[0].x` a line plot needs numbers",
        ),
        (
            "[[sweep.plot]]\nfile = \"a.svg\"\nmetric = \"wss.mae_deg\"\ncolour = \"red\"\n",
            "`sweep.plot[0].colour`",
        ),
        (
            "[[sweep.plot]]\nfile = \"sweep_x.svg\"\nmetric = \"wss.mae_deg\"\nx = \"hop_ms\"\n",
            "palpate's own plots",
        ),
    ] {
        std::fs::write(d.path().join("g.toml"), graph(plots)).unwrap();
        let out = palpate_in(d.path()).args(["check", "g.toml"]).output().unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success() && err.contains(want), "{want}: {err}");
    }
}

/// Without `[[sweep.plot]]` tables, a sweep over numbers charts each metric
/// against its key; a sweep of one value (repeats over seeds only) charts
/// nothing, since a line over one x value is a dot.
#[test]
fn default_charts_need_two_values_of_the_key() {
    let d = tempfile::tempdir().unwrap();
    let base = graph("");
    let sweep_at = base.find("[sweep]").unwrap();
    for (values, repeats, charts) in [("[20.0, 40.0]", 1, true), ("[20.0]", 2, false)] {
        let g = format!(
            "{}[sweep]\nkey = \"stages.bins.hop_ms\"\nvalues = {values}\nrepeats = {repeats}\n",
            &base[..sweep_at]
        );
        std::fs::write(d.path().join("g.toml"), g).unwrap();
        let out = palpate_in(d.path())
            .args(["run", "g.toml", "--out", "o", "--fresh"])
            .output()
            .unwrap();
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        let chart = d.path().join("o/sweep_wss_mae_deg.svg");
        assert_eq!(chart.exists(), charts, "values {values}");
        let _ = std::fs::remove_dir_all(d.path().join("o"));
    }
}
