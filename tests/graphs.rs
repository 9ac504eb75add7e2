//! Every graph under graphs/ checks, and runs end to end on a small trial count;
//! the CLI's `check` reports errors with stage and line; 1 and 2 threads agree.

use palpate::core::{self, LoadOptions, RunOptions};
use std::path::{Path, PathBuf};

/// Graph files (scene description files under graphs/scenes/ are not graphs).
fn graph_files() -> Vec<PathBuf> {
    fn walk(dir: &Path, out: &mut Vec<PathBuf>) {
        let mut entries: Vec<PathBuf> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().path())
            .collect();
        entries.sort();
        for p in entries {
            if p.is_dir() {
                if p.file_name().is_some_and(|n| n != "scenes") {
                    walk(&p, out);
                }
            } else if p.extension().is_some_and(|e| e == "toml") {
                out.push(p);
            }
        }
    }
    let mut v = Vec::new();
    walk(&Path::new(env!("CARGO_MANIFEST_DIR")).join("graphs"), &mut v);
    v
}

/// The graph's text made small: 2 trials of 3 angles per scene, the first two
/// values of a sweep (of each series of a series sweep), one repeat.
fn shrink(text: &str) -> String {
    let mut doc: toml::Table = toml::from_str(text).unwrap();
    if let Some(stages) = doc.get_mut("stages").and_then(|s| s.as_table_mut()) {
        for (_, st) in stages.iter_mut() {
            let Some(st) = st.as_table_mut() else { continue };
            if st.get("type").and_then(|t| t.as_str()) == Some("scene") {
                st.insert("trials_per_angle".into(), toml::Value::Integer(2));
                st.insert(
                    "angles".into(),
                    toml::Value::Array(vec![20.0.into(), 45.0.into(), 90.0.into()]),
                );
            }
        }
    }
    if let Some(sweep) = doc.get_mut("sweep").and_then(|s| s.as_table_mut()) {
        if let Some(v) = sweep.get_mut("values").and_then(|v| v.as_array_mut()) {
            v.truncate(2);
        }
        for series in sweep
            .get_mut("series")
            .and_then(|s| s.as_array_mut())
            .into_iter()
            .flatten()
        {
            if let Some(v) = series.get_mut("values").and_then(|v| v.as_array_mut()) {
                v.truncate(2);
            }
        }
        sweep.insert("repeats".into(), toml::Value::Integer(1));
    }
    toml::to_string(&doc).unwrap()
}

fn out_dir(name: &str) -> PathBuf {
    std::env::temp_dir().join(format!("palpate-graphs-test-{}-{name}", std::process::id()))
}

#[test]
fn every_graph_checks_and_runs_small() {
    palpate::link();
    let files = graph_files();
    assert!(files.iter().any(|f| f.ends_with("quickstart.toml")), "{files:?}");
    for f in &files {
        let g =
            core::load_file(f, &LoadOptions::default()).unwrap_or_else(|e| panic!("{}:\n{e}", f.display()));
        let name = f.file_stem().unwrap().to_string_lossy().to_string();
        let text = shrink(&std::fs::read_to_string(f).unwrap());
        let opts = LoadOptions {
            out: Some(out_dir(&name)),
            base_dir: f.parent().map(Path::to_path_buf),
            ..LoadOptions::default()
        };
        let small = core::load_str(&text, &f.display().to_string(), &name, &opts)
            .unwrap_or_else(|e| panic!("{} (small):\n{e}", f.display()));
        if g.sweep.is_some() {
            let runs = core::sweep::run_text(&text, &name, &name, &opts, &small, &RunOptions::default())
                .unwrap_or_else(|e| panic!("{}: {e}", f.display()));
            let sweep = small.sweep.as_ref().unwrap();
            // Each value list was cut to (at most) its first two values.
            let points = if sweep.series.is_empty() {
                sweep.values.len().min(2)
            } else {
                sweep.series.iter().map(|s| s.values.len().min(2)).sum()
            };
            assert_eq!(runs.len(), points, "{}", f.display());
            // A frontier sweep's report builds (one row per point and estimator).
            if !sweep.frontier.is_empty() {
                let rows = palpate::frontier::rows(&runs, &sweep.frontier, Some(&small))
                    .unwrap_or_else(|e| panic!("{}: {e}", f.display()));
                assert_eq!(rows.len(), points * sweep.frontier.len(), "{}", f.display());
            }
        } else {
            let r =
                core::run(&small, &RunOptions::default()).unwrap_or_else(|e| panic!("{}: {e}", f.display()));
            assert!(!r.reports.is_empty(), "{} has no sink", f.display());
        }
        let _ = std::fs::remove_dir_all(out_dir(&name));
    }
}

fn quickstart_estimates(threads: usize) -> Vec<(String, Option<f64>, Vec<u64>)> {
    palpate::link();
    let f = Path::new(env!("CARGO_MANIFEST_DIR")).join("graphs/quickstart.toml");
    let text = shrink(&std::fs::read_to_string(&f).unwrap());
    let opts = LoadOptions {
        out: Some(out_dir(&format!("threads{threads}"))),
        base_dir: f.parent().map(Path::to_path_buf),
        ..LoadOptions::default()
    };
    let g = core::load_str(&text, "quickstart.toml", "quickstart", &opts).unwrap();
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    let r = pool
        .install(|| {
            core::run(
                &g,
                &RunOptions {
                    keep_outputs: true,
                    ..RunOptions::default()
                },
            )
        })
        .unwrap();
    let _ = std::fs::remove_dir_all(out_dir(&format!("threads{threads}")));
    let est = g
        .nodes
        .iter()
        .find(|n| matches!(n.stage, core::Stage::Estimator(_)))
        .unwrap();
    r.outputs[&est.id]
        .iter()
        .map(|i| {
            let e = i.payload.estimate().unwrap();
            (
                i.meta.trial_id.clone(),
                e.angle_deg,
                e.scores.iter().map(|s| s.score.to_bits()).collect(),
            )
        })
        .collect()
}

#[test]
fn quickstart_gives_identical_bits_on_one_and_two_threads() {
    let a = quickstart_estimates(1);
    assert!(!a.is_empty());
    assert_eq!(a, quickstart_estimates(2));
}

#[test]
fn cli_check_prints_five_errors_with_stage_and_line() {
    let dir = out_dir("cli-check");
    std::fs::create_dir_all(&dir).unwrap();
    let bad = dir.join("bad.toml");
    std::fs::write(
        &bad,
        r#"[stages.scene]
type = "scene"
trials_per_angle = 3

[stages.norm]
type = "normalize"
inputs = ["scene"]
mode = "sideways"

[stages.enc]
type = "izhikevich"
inputs = ["scene"]
dt_ms = "fast"

[stages.bins]
type = "bin"
inputs = ["scene"]

[stages.est]
type = "wss"
inputs = ["bins"]
sigma = 1.0

[stages.report]
type = "mea"
inputs = ["est"]
"#,
    )
    .unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_palpate"))
        .arg("check")
        .arg(&bad)
        .output()
        .unwrap();
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    let errors: Vec<&str> = stderr.lines().filter(|l| l.contains(": error: ")).collect();
    assert_eq!(errors.len(), 5, "{stderr}");
    for (line, stage) in [
        (8, "norm"),
        (13, "enc"),
        (17, "bins"),
        (22, "est"),
        (25, "report"),
    ] {
        assert!(
            errors
                .iter()
                .any(|e| e.contains(&format!("bad.toml:{line}: error: stage `{stage}`"))),
            "no error for `{stage}` at line {line}:\n{stderr}"
        );
    }
    assert!(
        stderr.contains("5 errors in the graph; nothing was run"),
        "{stderr}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn every_builtin_stage_type_is_registered() {
    palpate::link();
    let names: Vec<&str> = core::registry::registrations()
        .iter()
        .map(|r| r.type_name)
        .collect();
    assert_eq!(
        names,
        core::registry::typetag_names(),
        "schema and typetag registries disagree"
    );
    for t in [
        "scene",
        "normalize",
        "lowpass",
        "derivative",
        "drive",
        "izhikevich",
        "lif",
        "jitter",
        "crop",
        "subarea",
        "dead_taxels",
        "bin",
        "raster_plot",
        "image_strip",
        "wss",
        "mae",
        "confusion",
    ] {
        assert!(
            names.contains(&t),
            "built-in stage `{t}` is not registered: {names:?}"
        );
    }
}

#[test]
fn the_committed_graph_schema_is_up_to_date() {
    palpate::link();
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("graphs/palpate-graph.schema.json");
    let committed: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    assert!(
        committed == core::registry::graph_schema(),
        "graphs/palpate-graph.schema.json is stale: regenerate it with `cargo run -- schema > graphs/palpate-graph.schema.json`"
    );
}

#[test]
fn simulate_writes_signals_and_a_plot() {
    let dir = out_dir("simulate");
    let scene = dir.join("small.toml");
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(&scene, "angles = [45.0]\ntrials_per_angle = 2\n").unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_palpate"))
        .args([
            "simulate",
            scene.to_str().unwrap(),
            "--out",
            dir.join("o").to_str().unwrap(),
        ])
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let names: Vec<String> = std::fs::read_dir(dir.join("o"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into())
        .collect();
    for want in [
        "edge-45deg-r00.npy",
        "edge-45deg-r01.npy",
        "labels.toml",
        "trials.json",
    ] {
        assert!(names.iter().any(|n| n == want), "{want} not in {names:?}");
    }
    assert!(names.iter().any(|n| n.ends_with(".svg")), "{names:?}");
    std::fs::remove_dir_all(&dir).unwrap();
}
