//! Sweeps beyond one process, through the `palpate` binary: shards and
//! `--points` subsets, completion markers and resuming, `palpate merge`, and
//! shards writing one folder at the same time. The sweep is
//! tests/data/cluster_sweep.toml (8 points x 2 repeats on the ideal scene).

mod common;

use common::{palpate, text};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

const GRAPH: &str = "tests/data/cluster_sweep.toml";

/// A successful run's stdout then stderr (a failed one fails the test).
fn ok(args: &[&str]) -> String {
    let out = palpate(args);
    assert!(out.status.success(), "palpate {args:?} failed:\n{}", text(&out));
    text(&out)
}

fn s(p: &Path) -> &str {
    p.to_str().expect("utf-8 temp path")
}

/// The frontier rows without the columns that measure time (they differ
/// between any two runs) or depend on the sweep cache (which points a process
/// ran together).
fn frontier_accuracy(dir: &Path) -> Vec<serde_json::Value> {
    let text = std::fs::read_to_string(dir.join("frontier.json")).expect("frontier.json");
    let rows: Vec<serde_json::Value> = serde_json::from_str(&text).expect("frontier.json parses");
    let timing = [
        "compute_ms",
        "estimator_ms",
        "source_ms",
        "train_s_per_fold",
        "cached_stages",
        "on_frontier_compute",
        "on_own_frontier_compute",
    ];
    rows.into_iter()
        .map(|mut r| {
            if let Some(o) = r.as_object_mut() {
                for k in timing {
                    o.remove(k);
                }
            }
            r
        })
        .collect()
}

fn assert_same_report(a: &Path, b: &Path) {
    for f in ["sweep.csv", "sweep.json"] {
        let x = std::fs::read(a.join(f)).unwrap_or_else(|e| panic!("{}: {e}", a.join(f).display()));
        let y = std::fs::read(b.join(f)).unwrap_or_else(|e| panic!("{}: {e}", b.join(f).display()));
        assert!(
            x == y,
            "{f} differs:\n{}\n---\n{}",
            String::from_utf8_lossy(&x),
            String::from_utf8_lossy(&y)
        );
    }
    assert_eq!(frontier_accuracy(a), frontier_accuracy(b));
}

fn markers(dir: &Path) -> Vec<PathBuf> {
    let mut found = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        let Ok(rd) = std::fs::read_dir(&d) else { continue };
        for e in rd.flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else if p.file_name().is_some_and(|n| n == "point.json") {
                found.push(p);
            }
        }
    }
    found.sort();
    found
}

/// One single-process run of the sweep, shared by the tests (it is the
/// reference every split is compared with).
fn single() -> PathBuf {
    static ONCE: std::sync::OnceLock<PathBuf> = std::sync::OnceLock::new();
    ONCE.get_or_init(|| {
        let dir = std::env::temp_dir().join(format!("palpate-cluster-single-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        ok(&["run", GRAPH, "--out", s(&dir), "--threads", "1"]);
        assert_eq!(markers(&dir).len(), 16, "8 points x 2 repeats");
        dir
    })
    .clone()
}

#[test]
fn sweep_list_numbers_every_point() {
    let text = ok(&["sweep", "list", GRAPH]);
    assert!(text.contains("8 points x 2 repeats"), "{text}");
    for (i, label) in ["hop/10.0", "hop/50.0", "ann_hidden/4", "ann_hidden/16"]
        .iter()
        .zip([0, 3, 4, 7])
        .map(|(l, i)| (i, l))
    {
        let line = text
            .lines()
            .find(|l| l.split_whitespace().next() == Some(&i.to_string()))
            .unwrap_or_else(|| panic!("no line for point {i}:\n{text}"));
        assert!(line.contains(label), "{line}");
    }
}

#[test]
fn shards_together_equal_the_single_run_and_merge_rebuilds_it() {
    let reference = single();
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("sharded");
    // Shards 1 and 2 of 3 leave the sweep incomplete: no report yet.
    for k in ["1/3", "2/3"] {
        let text = ok(&["run", GRAPH, "--out", s(&out), "--shard", k, "--threads", "1"]);
        assert!(text.contains("palpate merge"), "{text}");
        assert!(!out.join("sweep.csv").exists());
    }
    // merge lists what is missing and writes nothing.
    let m = palpate(&["merge", s(&out)]);
    assert!(!m.status.success());
    let err = String::from_utf8_lossy(&m.stderr);
    assert!(err.contains("not complete") && err.contains("point 7"), "{err}");
    assert!(!out.join("sweep.csv").exists());
    // The last shard completes the sweep and writes the report.
    ok(&["run", GRAPH, "--out", s(&out), "--shard", "3/3", "--threads", "2"]);
    assert_same_report(&reference, &out);
    // merge rebuilds the same report from the folders alone.
    std::fs::remove_file(out.join("sweep.csv")).unwrap();
    std::fs::remove_file(out.join("sweep.json")).unwrap();
    ok(&["merge", s(&out)]);
    assert_same_report(&reference, &out);
}

#[test]
fn a_rerun_skips_complete_points_and_redoes_broken_ones() {
    let reference = single();
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("resumed");
    ok(&[
        "run",
        GRAPH,
        "--out",
        s(&out),
        "--points",
        "0,5-6",
        "--threads",
        "1",
    ]);
    let done = markers(&out);
    assert_eq!(done.len(), 6, "3 points x 2 repeats: {done:?}");
    // A kill between a point's reports and its marker leaves no marker; a kill
    // while some other tool copied the folder may leave a cut one.
    std::fs::remove_file(&done[0]).unwrap();
    let cut = std::fs::read(&done[1]).unwrap();
    std::fs::write(&done[1], &cut[..cut.len() / 2]).unwrap();
    let kept = std::fs::read(&done[2]).unwrap();
    let text = ok(&["run", GRAPH, "--out", s(&out), "--threads", "1"]);
    assert!(text.contains("skipped 4 already complete"), "{text}");
    assert_eq!(
        std::fs::read(&done[2]).unwrap(),
        kept,
        "a complete point was not redone"
    );
    assert_same_report(&reference, &out);
    // --fresh redoes everything selected.
    let text = ok(&[
        "run",
        GRAPH,
        "--out",
        s(&out),
        "--points",
        "2",
        "--fresh",
        "--threads",
        "1",
    ]);
    assert!(text.contains("ran 2 point runs, skipped 0"), "{text}");
}

#[test]
fn a_killed_shard_resumes_without_redoing_finished_points() {
    let reference = single();
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("killed");
    let mut child = Command::new(env!("CARGO_BIN_EXE_palpate"))
        .args(["run", GRAPH, "--out", s(&out), "--threads", "1"])
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let t0 = Instant::now();
    while markers(&out).len() < 3 && t0.elapsed() < Duration::from_secs(120) {
        std::thread::sleep(Duration::from_millis(20));
    }
    child.kill().unwrap();
    child.wait().unwrap();
    let survivors: Vec<(PathBuf, Vec<u8>)> = markers(&out)
        .into_iter()
        .map(|p| {
            let b = std::fs::read(&p).unwrap();
            (p, b)
        })
        .collect();
    assert!(!survivors.is_empty(), "no point finished before the kill");
    let text = ok(&["run", GRAPH, "--out", s(&out), "--threads", "1"]);
    if survivors.len() < 16 {
        assert!(text.contains(&format!("skipped {}", survivors.len())), "{text}");
    }
    for (p, b) in &survivors {
        assert_eq!(&std::fs::read(p).unwrap(), b, "{} was redone", p.display());
    }
    assert_same_report(&reference, &out);
}

#[test]
fn concurrent_shards_in_one_folder_never_corrupt_it() {
    let reference = single();
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("concurrent");
    // Two processes over the whole sweep and one over a shard, all at once: they
    // race for the same points and files.
    let spawn = |extra: &[&str]| {
        let mut args = vec!["run", GRAPH, "--out", s(&out), "--threads", "1"];
        args.extend_from_slice(extra);
        Command::new(env!("CARGO_BIN_EXE_palpate"))
            .args(&args)
            .current_dir(env!("CARGO_MANIFEST_DIR"))
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap()
    };
    let children = [spawn(&[]), spawn(&[]), spawn(&["--shard", "2/2"])];
    for c in children {
        let o = c.wait_with_output().unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    }
    assert_eq!(markers(&out).len(), 16);
    assert_same_report(&reference, &out);
    // No temporary file is left behind.
    let mut stack = vec![out.clone()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap().flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else {
                let n = p.file_name().unwrap().to_string_lossy().into_owned();
                assert!(!n.contains(".tmp-"), "left over: {}", p.display());
            }
        }
    }
}

#[test]
fn bad_selections_are_clear_errors() {
    let o = palpate(&["run", GRAPH, "--points", "0,99", "--out", "/nonexistent/never"]);
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("99") && err.contains("sweep list"), "{err}");
    let o = palpate(&["run", GRAPH, "--shard", "5/4"]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("K/N"));
    let o = palpate(&["run", "graphs/quickstart.toml", "--shard", "1/2"]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("no [sweep] table"));
    let o = palpate(&["merge", "/nonexistent/palpate-merge"]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("sweep-manifest.json"));
}

#[test]
fn slurm_writes_an_array_and_a_dependent_merge() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("slurm");
    let text = ok(&[
        "slurm",
        GRAPH,
        "--out",
        s(&out),
        "--array-size",
        "20",
        "--partition",
        "debug",
        "--cpus",
        "3",
        "--time",
        "00:10:00",
    ]);
    assert!(text.contains("submit with"), "{text}");
    let array = std::fs::read_to_string(out.join("slurm/array.sbatch")).unwrap();
    // 20 tasks asked, but the sweep has 8 points: one shard per point.
    assert!(array.contains("#SBATCH --array=1-8\n"), "{array}");
    assert!(array.contains("--shard \"${SLURM_ARRAY_TASK_ID}/8\""), "{array}");
    assert!(array.contains("#SBATCH --partition=debug\n"));
    assert!(array.contains("#SBATCH --cpus-per-task=3\n"));
    assert!(array.contains("#SBATCH --time=00:10:00\n"));
    let merge = std::fs::read_to_string(out.join("slurm/merge.sbatch")).unwrap();
    assert!(merge.contains(" merge "), "{merge}");
    let submit = std::fs::read_to_string(out.join("slurm/submit.sh")).unwrap();
    assert!(submit.contains("--dependency=afterok:"), "{submit}");
    assert!(out.join("sweep-manifest.json").is_file());
    let o = palpate(&["slurm", GRAPH, "--out", s(&out), "--partition", "a b"]);
    assert!(!o.status.success());
    // A folder with a space (or a %) cannot be an `#SBATCH --output` value:
    // refused, naming it, before any script is written.
    let spaced = dir.path().join("o sp");
    let o = palpate(&["slurm", GRAPH, "--out", s(&spaced)]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && err.contains("o sp") && err.contains("#SBATCH"),
        "{err}"
    );
    assert!(!spaced.join("slurm/array.sbatch").exists());
    // Slurm's time forms pass; a typo, or a CPU count no run would accept,
    // fails now rather than at submission or in every task.
    for t in [
        "90",
        "10:30",
        "01:00:00",
        "2-12",
        "2-12:30",
        "2-12:30:15",
        "UNLIMITED",
    ] {
        ok(&["slurm", GRAPH, "--out", s(&out), "--time", t]);
    }
    for (flag, v, says) in [
        ("--time", "1h", "Slurm's forms"),
        ("--time", "01:00:00:00", "Slurm's forms"),
        ("--time", "-5", "Slurm's forms"),
        ("--cpus", "99999999999", "cap of 4096"),
    ] {
        let o = palpate(&["slurm", GRAPH, "--out", s(&out), &format!("{flag}={v}")]);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success() && err.contains(says), "{flag} {v}: {err}");
    }
}
