//! The accuracy-time frontier: the Pareto function on hand-made points, the
//! decision-time metric on cropped trials, the frontier report of a small
//! series sweep, and the timing files every run writes.

use palpate::core::{self, LoadOptions, RunOptions};
use palpate::frontier::{self, pareto, FrontierRow};
use proptest::prelude::*;
use std::path::PathBuf;

fn out_dir(name: &str) -> PathBuf {
    std::env::temp_dir().join(format!("palpate-frontier-test-{}-{name}", std::process::id()))
}

#[test]
fn pareto_on_hand_made_points() {
    // (time, error): lower is better in both.
    let pts = [
        (1.0, 5.0),           // fastest: on
        (2.0, 3.0),           // on
        (2.0, 4.0),           // same time, worse error than (2, 3): off
        (3.0, 3.0),           // same error as (2, 3), slower: off
        (4.0, 1.0),           // on
        (4.0, 1.0),           // exact duplicate: neither dominates the other, both on
        (5.0, 2.0),           // dominated by (4, 1): off
        (0.5, f64::NAN),      // no error: never on, dominates nothing
        (f64::INFINITY, 0.0), // no time: never on
    ];
    assert_eq!(
        pareto(&pts),
        [true, true, false, false, true, true, false, false, false]
    );
    assert_eq!(
        pareto(&[(3.0, 7.0)]),
        [true],
        "a single point is its own frontier"
    );
    assert_eq!(pareto(&[]), Vec::<bool>::new());
    assert_eq!(pareto(&[(f64::NAN, f64::NAN)]), [false]);
    // A point better in both removes every other.
    assert_eq!(
        pareto(&[(2.0, 2.0), (1.0, 1.0), (3.0, 1.0)]),
        [false, true, false]
    );
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]
    /// Every point off the frontier is dominated by one on it, and no point on
    /// it is dominated by any point.
    #[test]
    fn pareto_properties(pts in prop::collection::vec((0u8..6, 0u8..6), 1..20)) {
        let pts: Vec<(f64, f64)> = pts.into_iter().map(|(a, b)| (a as f64, b as f64)).collect();
        let on = pareto(&pts);
        let dominates = |q: (f64, f64), p: (f64, f64)| q.0 <= p.0 && q.1 <= p.1 && (q.0 < p.0 || q.1 < p.1);
        prop_assert!(on.iter().any(|&b| b));
        for (i, &p) in pts.iter().enumerate() {
            if on[i] {
                prop_assert!(!pts.iter().any(|&q| dominates(q, p)));
            } else {
                prop_assert!(pts.iter().zip(&on).any(|(&q, &o)| o && dominates(q, p)));
            }
        }
    }
}

/// A small, fast graph: the ideal scene with short holds, 3 angles x 2 trials.
const SMALL: &str = r#"
[run]
seed = 3

[stages.scene]
type = "scene"
angles = [30.0, 60.0, 90.0]
trials_per_angle = 2

[stages.scene.motion]
hold_before_s = 0.5
hold_after_s = 0.5

[stages.norm]
type = "normalize"
inputs = ["scene"]

[stages.drive]
type = "drive"
inputs = ["norm"]
kind = "fa_i"

[stages.enc]
type = "izhikevich"
inputs = ["drive"]

[stages.crop]
type = "crop"
inputs = ["enc"]
share = 0.5
truncate = true

[stages.bins]
type = "bin"
inputs = ["crop"]

[stages.wss]
type = "wss"
inputs = ["bins"]

[stages.wss_stop]
type = "wss"
inputs = ["bins"]
stop_margin = 0.05

[stages.ann]
type = "ann"
inputs = ["bins"]
hidden = 8
max_epochs = 5

[stages.mae]
type = "mae"
inputs = ["wss", "wss_stop", "ann"]
per_class = false
"#;

#[test]
fn decision_time_of_a_cropped_run_stays_within_the_crop() {
    palpate::link();
    let out = out_dir("crop");
    let g = core::load_str(
        SMALL,
        "small.toml",
        "small",
        &LoadOptions {
            out: Some(out.clone()),
            ..Default::default()
        },
    )
    .unwrap_or_else(|e| panic!("{e}"));
    let r = core::run(
        &g,
        &RunOptions {
            keep_outputs: true,
            ..Default::default()
        },
    )
    .unwrap();
    let metrics: Vec<(String, f64)> = r
        .reports
        .iter()
        .flat_map(|(_, rep)| rep.metrics.clone())
        .collect();
    let metric = |n: &str| metrics.iter().find(|m| m.0 == n).map(|m| m.1);
    let mut caps = Vec::new();
    for est in ["wss", "wss_stop", "ann"] {
        let mut from_contact = Vec::new();
        for item in r.outputs[est].iter() {
            let [t0, t1] = item.meta.crossing_ms.expect("the scene knows its crossing");
            let cut = t0 + 0.5 * (t1 - t0);
            let t = item
                .payload
                .estimate()
                .unwrap()
                .decision_time_ms
                .unwrap_or_else(|| panic!("{est}: no decision time"));
            assert!(
                t <= cut,
                "{est} trial {}: decision {t} ms after the cut {cut} ms",
                item.meta.trial_id
            );
            from_contact.push(t - t0);
            caps.push(0.5 * (t1 - t0));
        }
        let d = metric(&format!("{est}.decision_ms")).unwrap_or_else(|| panic!("no {est}.decision_ms"));
        from_contact.sort_by(f64::total_cmp);
        let n = from_contact.len();
        let median = (from_contact[(n - 1) / 2] + from_contact[n / 2]) / 2.0;
        assert!((d - median).abs() < 1e-9, "{est}: metric {d} vs median {median}");
    }
    // The per-trial bound carries to the medians.
    caps.sort_by(f64::total_cmp);
    let cap = caps[caps.len() / 2];
    assert!(metric("wss.decision_ms").unwrap() <= cap);
    // Early stop never needs more palpation than the whole (cropped) trial.
    assert!(metric("wss_stop.decision_ms").unwrap() <= metric("wss.decision_ms").unwrap());
    let text: String = r.reports.iter().map(|(_, rep)| rep.text.clone()).collect();
    assert!(text.contains("decision time: median"), "{text}");
    let _ = std::fs::remove_dir_all(out);
}

const SWEEP: &str = r#"
[sweep]
frontier = ["wss", "wss_stop"]

[[sweep.series]]
name = "grid"
key = "stages.wss.angles"
values = [{ from = 30.0, to = 90.0, step = 30.0 }, { from = 30.0, to = 90.0, step = 10.0 }]

[[sweep.series]]
name = "hop"
key = "stages.bins.hop_ms"
values = [10.0, 25.0]
"#;

fn sweep_text() -> String {
    // Without the ANN (training in every point would only slow the test) and
    // without the crop (whole trials).
    let base = SMALL
        .replace(
            "inputs = [\"wss\", \"wss_stop\", \"ann\"]",
            "inputs = [\"wss\", \"wss_stop\"]",
        )
        .replace(
            "[stages.ann]\ntype = \"ann\"\ninputs = [\"bins\"]\nhidden = 8\nmax_epochs = 5\n",
            "",
        )
        .replace(
            "[stages.crop]\ntype = \"crop\"\ninputs = [\"enc\"]\nshare = 0.5\ntruncate = true\n",
            "",
        )
        .replace("inputs = [\"crop\"]", "inputs = [\"enc\"]");
    assert!(!base.contains("crop") && !base.contains("ann"), "{base}");
    format!("{base}\n{SWEEP}")
}

#[test]
fn the_frontier_of_a_small_series_sweep() {
    palpate::link();
    let out = out_dir("sweep");
    let text = sweep_text();
    let opts = LoadOptions {
        out: Some(out.clone()),
        ..Default::default()
    };
    let g = core::load_str(&text, "s.toml", "s", &opts).unwrap_or_else(|e| panic!("{e}"));
    let runs = core::sweep::run_text(&text, "s.toml", "s", &opts, &g, &RunOptions::default())
        .unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(runs.len(), 4);
    let rows: Vec<FrontierRow> =
        frontier::rows(&runs, &g.sweep.as_ref().unwrap().frontier, Some(&g)).unwrap();
    assert_eq!(rows.len(), 8, "4 points x 2 estimators");
    let summary: Vec<(&str, &str, bool, Option<&str>)> = rows
        .iter()
        .map(|r| {
            (
                r.point.as_str(),
                r.estimator.as_str(),
                r.is_base,
                r.same_as.as_deref(),
            )
        })
        .collect();
    let p0 = "grid/from=30.0,to=90.0,step=30.0";
    assert_eq!(
        summary,
        [
            (p0, "wss", false, None),
            // The grid series changes `wss` only: `wss_stop` keeps the base configuration.
            (p0, "wss_stop", true, None),
            ("grid/from=30.0,to=90.0,step=10.0", "wss", false, None),
            ("grid/from=30.0,to=90.0,step=10.0", "wss_stop", true, Some(p0)),
            // hop 10 is the base value: base for both, first time for `wss`.
            ("hop/10.0", "wss", true, None),
            ("hop/10.0", "wss_stop", true, Some(p0)),
            ("hop/25.0", "wss", false, None),
            ("hop/25.0", "wss_stop", false, None),
        ]
    );
    assert_eq!(rows[0].series, "grid");
    assert_eq!(rows[7].value, "25.0");
    for r in &rows {
        assert!(r.compute_ms > 0.0 && r.compute_ms.is_finite(), "{r:?}");
        assert!(r.estimator_ms > 0.0 && r.estimator_ms < r.compute_ms, "{r:?}");
        assert!(r.source_ms > 0.0, "the scene's time is kept apart: {r:?}");
        assert!(r.decision_ms.is_some() && r.mae_deg.is_some(), "{r:?}");
        assert_eq!(r.train_s_per_fold, None, "WSS trains nothing");
        assert_eq!(r.runs, 1);
    }
    // A point served from the cache reports the times of the run that
    // computed its stages: the repeated base configuration costs the same.
    assert!(rows[5].cached_stages >= 5, "{:?}", rows[5]);
    assert_eq!(rows[5].compute_ms, rows[1].compute_ms);
    assert_eq!(rows[5].mae_deg, rows[1].mae_deg);
    // The marks are the Pareto sets of the unique rows' own numbers.
    for decision in [false, true] {
        let unique: Vec<&FrontierRow> = rows.iter().filter(|r| r.same_as.is_none()).collect();
        let t = |r: &FrontierRow| {
            if decision {
                r.decision_ms.unwrap()
            } else {
                r.compute_ms
            }
        };
        let pts: Vec<(f64, f64)> = unique.iter().map(|r| (t(r), r.mae_deg.unwrap())).collect();
        let marks: Vec<bool> = unique
            .iter()
            .map(|r| {
                if decision {
                    r.on_frontier_decision
                } else {
                    r.on_frontier_compute
                }
            })
            .collect();
        assert_eq!(marks, pareto(&pts), "decision {decision}");
        for est in ["wss", "wss_stop"] {
            let own: Vec<&&FrontierRow> = unique.iter().filter(|r| r.estimator == est).collect();
            let pts: Vec<(f64, f64)> = own.iter().map(|r| (t(r), r.mae_deg.unwrap())).collect();
            let marks: Vec<bool> = own
                .iter()
                .map(|r| {
                    if decision {
                        r.on_own_frontier_decision
                    } else {
                        r.on_own_frontier_compute
                    }
                })
                .collect();
            assert_eq!(marks, pareto(&pts), "{est}, decision {decision}");
        }
        // Overall implies own.
        assert!(rows
            .iter()
            .all(|r| !r.on_frontier_compute || r.on_own_frontier_compute));
    }
    assert!(rows
        .iter()
        .filter(|r| r.same_as.is_some())
        .all(|r| !r.on_frontier_compute
            && !r.on_frontier_decision
            && !r.on_own_frontier_compute
            && !r.on_own_frontier_decision));

    let series = vec!["grid".to_string(), "hop".to_string()];
    let files = frontier::write(&out, &rows, &series, &g.sweep.as_ref().unwrap().frontier).unwrap();
    let names: Vec<String> = files
        .iter()
        .map(|f| f.file_name().unwrap().to_string_lossy().into())
        .collect();
    assert_eq!(
        names,
        [
            "frontier.md",
            "frontier.csv",
            "frontier.json",
            "frontier_compute.svg",
            "frontier_decision.svg"
        ]
    );
    let md = std::fs::read_to_string(out.join("frontier.md")).unwrap();
    assert!(
        md.contains("| grid | from=30.0,to=90.0,step=10.0 | wss |"),
        "{md}"
    );
    assert!(md.contains(&format!("| base, as {p0} |")), "{md}");
    assert!(
        md.contains("Overall frontier against compute time per trial"),
        "{md}"
    );
    assert!(
        md.contains("Each estimator's own frontier against decision time"),
        "{md}"
    );
    let csv = std::fs::read_to_string(out.join("frontier.csv")).unwrap();
    assert_eq!(csv.lines().count(), 9);
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("frontier.json")).unwrap()).unwrap();
    assert_eq!(json.as_array().unwrap().len(), 8);
    let svg = std::fs::read_to_string(out.join("frontier_compute.svg")).unwrap();
    assert!(
        svg.contains("overall frontier") && svg.contains("wss_stop"),
        "legend"
    );
    let table = frontier::render(&rows);
    assert_eq!(table.lines().count(), 1 + 6, "repeats left out:\n{table}");
    let _ = std::fs::remove_dir_all(out);
}

#[test]
fn the_frontier_list_is_checked() {
    palpate::link();
    let opts = LoadOptions {
        out: Some(out_dir("check")),
        ..Default::default()
    };
    let text = sweep_text().replace("frontier = [\"wss\", \"wss_stop\"]", "frontier = [\"bins\"]");
    // The loader checks the list, so a library caller gets the same errors.
    let e = core::load_str(&text, "s.toml", "s", &opts)
        .unwrap_err()
        .to_string();
    assert!(e.contains("`bins`, a map stage (bin), not an estimator"), "{e}");
    let text = sweep_text()
        .replace(
            "inputs = [\"wss\", \"wss_stop\"]\nper_class",
            "inputs = [\"wss\"]\nper_class",
        )
        .replace(
            "[stages.wss_stop]",
            "[stages.raster]\ntype = \"raster_plot\"\ninputs = [\"enc\"]\n\n[stages.wss_stop]",
        );
    let e = core::load_str(&text, "s.toml", "s", &opts)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("estimator `wss_stop`, which feeds no sink that scores estimates"),
        "{e}"
    );
}

#[test]
fn the_cli_writes_timing_files_and_the_frontier() {
    let dir = out_dir("cli");
    std::fs::create_dir_all(&dir).unwrap();
    let single = dir.join("single.toml");
    let base = sweep_text();
    let cut = base.find("[sweep]").unwrap();
    std::fs::write(&single, &base[..cut]).unwrap();
    let swept = dir.join("swept.toml");
    std::fs::write(&swept, &base).unwrap();
    let run = |graph: &PathBuf, out: &PathBuf| {
        let o = std::process::Command::new(env!("CARGO_BIN_EXE_palpate"))
            .arg("run")
            .arg(graph)
            .arg("--out")
            .arg(out)
            .output()
            .unwrap();
        let stdout = String::from_utf8_lossy(&o.stdout).to_string();
        assert!(
            o.status.success(),
            "{stdout}\n{}",
            String::from_utf8_lossy(&o.stderr)
        );
        stdout
    };
    let out1 = dir.join("o1");
    let stdout = run(&single, &out1);
    assert!(stdout.contains("fit p95 ms"), "{stdout}");
    for f in ["run.json", "timing.md", "timing.csv"] {
        assert!(out1.join(f).exists(), "{f}");
    }
    let csv = std::fs::read_to_string(out1.join("timing.csv")).unwrap();
    assert!(csv.starts_with("stage,type,role,trials,median_ms,p95_ms,fits,fit_median_ms,fit_p95_ms"));
    assert!(
        csv.lines().any(|l| l.starts_with("wss,wss,estimator,6,")),
        "{csv}"
    );
    let out2 = dir.join("o2");
    let stdout = run(&swept, &out2);
    assert!(
        stdout.contains("accuracy-time frontier") && stdout.contains("hop/25.0"),
        "{stdout}"
    );
    for f in [
        "frontier.md",
        "frontier.csv",
        "frontier.json",
        "frontier_compute.svg",
        "frontier_decision.svg",
    ] {
        assert!(out2.join(f).exists(), "{f}");
    }
    for p in ["grid/from=30.0,to=90.0,step=30.0", "hop/25.0"] {
        for f in ["timing.md", "timing.csv", "run.json", "mae.json"] {
            assert!(out2.join(p).join(f).exists(), "{p}/{f}");
        }
    }
    // A point served from the cache marks its cached stages.
    let md = std::fs::read_to_string(out2.join("hop/10.0/timing.md")).unwrap();
    assert!(
        md.contains("| scene* |") && md.contains("served from the sweep cache"),
        "{md}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}
