//! `palpate batch`: several graphs in one process sharing one cache give
//! each graph the same report as running it alone, share what they have in
//! common, never share across a different folder or protocol, and name the
//! jobs file, job and key on bad input.

use std::path::Path;
mod common;
use common::{palpate, text};

const GRAPH: &str = "tests/data/cluster_sweep.toml";

fn ok(args: &[&str]) -> String {
    let out = palpate(args);
    assert!(out.status.success(), "palpate {args:?} failed:\n{}", text(&out));
    text(&out)
}

fn s(p: &Path) -> &str {
    p.to_str().expect("utf-8 temp path")
}

/// A sweep's results (not its times): sweep.csv and sweep.json carry every
/// point's metrics as mean and SD over the repeats; the points' own metric
/// bits are in each run's point.json.
fn results(dir: &Path) -> Vec<(String, String)> {
    let mut out = Vec::new();
    for f in ["sweep.csv", "sweep.json"] {
        let t =
            std::fs::read_to_string(dir.join(f)).unwrap_or_else(|e| panic!("{}: {e}", dir.join(f).display()));
        out.push((f.to_string(), t));
    }
    let points = points(dir);
    assert!(!points.is_empty(), "{}: no point.json", dir.display());
    for (path, _, metrics) in points {
        out.push((path, metrics.join("\n")));
    }
    out
}

/// Every point run under `dir` (sorted by path): its path relative to
/// `dir`, its label and its metrics' names and bits, from its point.json.
fn points(dir: &Path) -> Vec<(String, String, Vec<String>)> {
    let mut paths: Vec<_> = walk(dir)
        .into_iter()
        .filter(|p| p.file_name().is_some_and(|n| n == "point.json"))
        .collect();
    paths.sort();
    paths
        .into_iter()
        .map(|p| {
            let v: serde_json::Value =
                serde_json::from_str(&std::fs::read_to_string(&p).expect("point.json"))
                    .expect("point.json parses");
            let metrics = v["reports"]
                .as_array()
                .expect("reports")
                .iter()
                .flat_map(|r| r["metrics"].as_array().cloned().unwrap_or_default())
                .map(|m| format!("{} {}", m["name"], m["bits"]))
                .collect();
            let label = v["label"].as_str().unwrap_or_default().to_string();
            (
                p.strip_prefix(dir).expect("under dir").display().to_string(),
                label,
                metrics,
            )
        })
        .collect()
}

/// Asserts two sweeps' results are the same, naming the first file that
/// differs.
fn same(a: &Path, b: &Path) {
    let (x, y) = (results(a), results(b));
    assert_eq!(
        x.len(),
        y.len(),
        "{} and {}: other files",
        a.display(),
        b.display()
    );
    for ((f, u), (_, v)) in x.iter().zip(&y) {
        assert!(
            u == v,
            "{} and {}: {f} differs:\n{u}\n---\n{v}",
            a.display(),
            b.display()
        );
    }
}

fn walk(dir: &Path) -> Vec<std::path::PathBuf> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir).expect("readable dir").flatten() {
        let p = e.path();
        if p.is_dir() {
            out.extend(walk(&p));
        } else {
            out.push(p);
        }
    }
    out
}

/// The number the batch prints after "cache: ".
fn reused(log: &str) -> usize {
    let tail = log.split("cache: ").nth(1).expect("the batch reports its cache");
    tail.split_whitespace()
        .next()
        .and_then(|n| n.parse().ok())
        .expect("a count")
}

#[test]
fn a_batch_gives_each_graph_its_own_results_and_shares_the_rest() {
    let tmp = tempfile::tempdir().expect("temp dir");
    let t = tmp.path();
    let base = format!("{}/{GRAPH}", env!("CARGO_MANIFEST_DIR"));
    // Job b changes only WSS's threshold: the scene, drive, encoder and bins
    // are job a's. Job c changes the protocol: the ANN's folds differ, so
    // its scores must not be job a's even though its stage settings are.
    let jobs = format!(
        r#"
[[job]]
graph = "{base}"
out = "{a}"
name = "a"

[[job]]
graph = "{base}"
out = "{b}"
set = ["stages.wss.threshold=0.2"]
name = "b"

[[job]]
graph = "{base}"
out = "{c}"
set = ["run.protocol={{ hold_out = {{ test_share = 0.5, seed = 3 }} }}"]
name = "c"
"#,
        a = s(&t.join("batch/a")),
        b = s(&t.join("batch/b")),
        c = s(&t.join("batch/c")),
    );
    let jobs_file = t.join("jobs.toml");
    std::fs::write(&jobs_file, jobs).expect("jobs file");
    let times = t.join("times.json");
    // One job at a time: each later job finds what the earlier ones computed.
    let log = ok(&["batch", s(&jobs_file), "--jobs", "1", "--times", s(&times)]);
    assert!(reused(&log) > 0, "nothing shared:\n{log}");
    let times: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&times).expect("times")).expect("times parse");
    for name in ["a", "b", "c"] {
        assert!(times[name].as_f64().is_some_and(|x| x >= 0.0), "{times}");
        assert!(t.join(format!("batch/{name}.log")).exists());
    }
    // Each alone, by `palpate run`.
    ok(&["run", GRAPH, "--out", s(&t.join("alone/a"))]);
    ok(&[
        "run",
        GRAPH,
        "--out",
        s(&t.join("alone/b")),
        "--set",
        "stages.wss.threshold=0.2",
    ]);
    ok(&[
        "run",
        GRAPH,
        "--out",
        s(&t.join("alone/c")),
        "--set",
        "run.protocol={ hold_out = { test_share = 0.5, seed = 3 } }",
    ]);
    for name in ["a", "b", "c"] {
        same(&t.join(format!("batch/{name}")), &t.join(format!("alone/{name}")));
    }
    // The protocol changed the ANN's answers (so the check above could fail).
    assert_ne!(
        results(&t.join("alone/a")),
        results(&t.join("alone/c")),
        "protocols agree"
    );
}

#[test]
fn graphs_in_other_folders_do_not_share_a_relative_file() {
    // The same graph text in two folders, each with its own `scene.toml`
    // (the second palpates faster): same stage settings, other scenes. Each
    // must get its own scene's results.
    let tmp = tempfile::tempdir().expect("temp dir");
    let t = tmp.path();
    let scene = std::fs::read_to_string(format!("{}/graphs/scenes/ideal.toml", env!("CARGO_MANIFEST_DIR")))
        .expect("ideal scene");
    let faster = scene.replacen("speed_mm_s = 2.0", "speed_mm_s = 2.5", 1);
    assert_ne!(scene, faster);
    let graph = std::fs::read_to_string(format!("{}/{GRAPH}", env!("CARGO_MANIFEST_DIR")))
        .expect("graph")
        .replace("../../graphs/scenes/ideal.toml", "scene.toml");
    assert!(graph.contains("\"scene.toml\""));
    for (dir, scene) in [("one", &scene), ("two", &faster)] {
        let d = t.join(dir);
        std::fs::create_dir_all(&d).expect("dir");
        std::fs::write(d.join("graph.toml"), &graph).expect("graph");
        std::fs::write(d.join("scene.toml"), scene).expect("scene");
    }
    let jobs = format!(
        "[[job]]\ngraph = \"{}\"\nout = \"{}\"\n\n[[job]]\ngraph = \"{}\"\nout = \"{}\"\n",
        s(&t.join("one/graph.toml")),
        s(&t.join("out/one")),
        s(&t.join("two/graph.toml")),
        s(&t.join("out/two")),
    );
    std::fs::write(t.join("jobs.toml"), jobs).expect("jobs");
    ok(&["batch", s(&t.join("jobs.toml")), "--jobs", "1"]);
    ok(&[
        "run",
        s(&t.join("one/graph.toml")),
        "--out",
        s(&t.join("alone/one")),
    ]);
    ok(&[
        "run",
        s(&t.join("two/graph.toml")),
        "--out",
        s(&t.join("alone/two")),
    ]);
    same(&t.join("out/one"), &t.join("alone/one"));
    same(&t.join("out/two"), &t.join("alone/two"));
    // The scenes' results differ (so the checks above could fail).
    assert_ne!(
        results(&t.join("alone/one")),
        results(&t.join("alone/two")),
        "scenes agree"
    );
}

#[test]
fn bad_jobs_files_are_named_with_the_job_and_key() {
    let tmp = tempfile::tempdir().expect("temp dir");
    let t = tmp.path();
    let cases: [(&str, &[&str]); 5] = [
        ("[[job]]\ngraph = \"tests/data/cluster_sweep.toml\"\nspeed = 2\n", &["jobs.toml", "speed"]),
        ("[[job]]\ngraph = \"no/such/graph.toml\"\n", &["jobs.toml", "job 1", "no/such/graph.toml"]),
        (
            "[[job]]\ngraph = \"tests/data/cluster_sweep.toml\"\nset = [\"stages.wss.threshold\"]\n",
            &["jobs.toml", "job 1", "set"],
        ),
        (
            "[[job]]\ngraph = \"tests/data/cluster_sweep.toml\"\nname = \"x\"\nset = [\"stages.wss.nonsense=1\"]\n",
            &["jobs.toml", "job 1 (x)", "nonsense"],
        ),
        ("", &["jobs.toml", "no [[job]]"]),
    ];
    for (body, needles) in cases {
        let f = t.join("jobs.toml");
        std::fs::write(&f, body).expect("jobs file");
        let out = palpate(&["batch", s(&f)]);
        let msg = text(&out);
        assert!(!out.status.success(), "{body}: accepted\n{msg}");
        for n in needles {
            assert!(msg.contains(n), "{body}: `{n}` missing from:\n{msg}");
        }
    }
    // A job whose log cannot be written fails the batch, naming the job.
    let f = t.join("jobs.toml");
    std::fs::write(
        &f,
        format!(
            "[[job]]\ngraph = \"tests/data/cluster_sweep.toml\"\nout = \"{}\"\nname = \"unlogged\"\nlog = \"{}\"\n",
            s(&t.join("out")),
            s(&t.join("jobs.toml/x.log"))
        ),
    )
    .expect("jobs file");
    let out = palpate(&["batch", s(&f)]);
    let msg = text(&out);
    assert!(!out.status.success(), "{msg}");
    assert!(msg.contains("FAILED: unlogged"), "{msg}");
}

#[test]
fn a_sweep_over_the_protocol_does_not_reuse_another_protocols_answers() {
    // Before stage keys held the protocol, every point of such a sweep after
    // the first was served the first point's trained-estimator answers.
    let tmp = tempfile::tempdir().expect("temp dir");
    let t = tmp.path();
    let text = std::fs::read_to_string(format!("{}/{GRAPH}", env!("CARGO_MANIFEST_DIR"))).expect("graph");
    let base = text[..text.find("[sweep]").expect("a [sweep] table")].replace(
        "../../graphs/scenes/ideal.toml",
        &format!("{}/graphs/scenes/ideal.toml", env!("CARGO_MANIFEST_DIR")),
    );
    let hold_out = "{ hold_out = { test_share = 0.5, seed = 3 } }";
    let sweep = |values: &str| {
        format!("{base}[sweep]\nkey = \"run.protocol\"\nvalues = [{values}]\nrepeats = 2\nmetrics = [\"ann.mae_deg\"]\n")
    };
    std::fs::write(
        t.join("both.toml"),
        sweep(&format!("\"leave_one_trial_out\", {hold_out}")),
    )
    .expect("graph");
    std::fs::write(t.join("one.toml"), sweep(hold_out)).expect("graph");
    ok(&["run", s(&t.join("both.toml")), "--out", s(&t.join("both"))]);
    ok(&["run", s(&t.join("one.toml")), "--out", s(&t.join("one"))]);
    let both = points(&t.join("both"));
    let one = points(&t.join("one"));
    assert_eq!((both.len(), one.len()), (4, 2));
    let held: Vec<_> = both.iter().filter(|(_, l, _)| l.contains("hold_out")).collect();
    let loto: Vec<_> = both.iter().filter(|(_, l, _)| !l.contains("hold_out")).collect();
    assert_eq!((held.len(), loto.len()), (2, 2), "{both:?}");
    for (h, o) in held.iter().zip(&one) {
        assert!(
            h.2 == o.2,
            "the hold-out point differs from the hold-out sweep alone"
        );
    }
    assert!(
        held.iter().zip(&loto).any(|(h, l)| h.2 != l.2),
        "the protocols agree, so the check above could not fail"
    );
}

#[test]
fn each_job_gets_its_share_of_the_threads() {
    use palpate::batch::threads_per_job;
    // 0 threads = the core count, shared out among the jobs at once.
    assert_eq!(threads_per_job(0, 2, 2), 1);
    assert_eq!(threads_per_job(0, 2, 8), 4);
    assert_eq!(threads_per_job(6, 4, 2), 1);
    // Never zero: more jobs than threads still run, one thread each.
    assert_eq!(threads_per_job(2, 4, 2), 1);
    assert_eq!(threads_per_job(0, 0, 4), 4);
    assert_eq!(threads_per_job(8, 1, 2), 8);
}

#[test]
fn graphs_without_a_sweep_share_nothing_and_the_batch_says_so() {
    let tmp = tempfile::tempdir().expect("temp dir");
    let t = tmp.path();
    let root = env!("CARGO_MANIFEST_DIR");
    let text = std::fs::read_to_string(format!("{root}/{GRAPH}")).expect("graph");
    let single = text
        .split("\n[sweep]")
        .next()
        .expect("text before the sweep")
        .replace(
            "../../graphs/scenes/ideal.toml",
            &format!("{root}/graphs/scenes/ideal.toml"),
        );
    assert!(!single.contains("[sweep"));
    let graph = t.join("single.toml");
    std::fs::write(&graph, single).expect("graph file");
    let jobs = |set: &str| {
        format!(
            "[[job]]\ngraph = \"{g}\"\nout = \"{a}\"\n{set}\n[[job]]\ngraph = \"{g}\"\nout = \"{b}\"\n{set}\n",
            g = s(&graph),
            a = s(&t.join(format!("{}a", set.len()))),
            b = s(&t.join(format!("{}b", set.len()))),
        )
    };
    let file = t.join("jobs.toml");
    std::fs::write(&file, jobs("")).expect("jobs file");
    let log = ok(&["batch", s(&file), "--jobs", "1"]);
    assert_eq!(reused(&log), 0, "{log}");
    assert!(
        log.contains("2 jobs without a [sweep] ran trial by trial"),
        "{log}"
    );
    // The one-point sweep the message suggests shares the second job's front end.
    std::fs::write(&file, jobs("set = [\"sweep.repeats=1\"]")).expect("jobs file");
    let log = ok(&["batch", s(&file), "--jobs", "1"]);
    assert!(reused(&log) > 0, "{log}");
    assert!(!log.contains("without a [sweep]"), "{log}");
}
