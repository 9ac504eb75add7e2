//! Where a run writes, and how it is cut into blocks, are checked before
//! anything is computed: `run --out` naming a file (or /dev/null) used to
//! run every stage and fail only at the last sink with "File exists"; two
//! `batch` jobs with one `out` overwrote each other silently; `--block 0`
//! was taken as 1 without a word; `sweep list` printed a seed range that
//! overflows u64 as `MAX..=MAX`; a sweep (or a batch) refused at load left
//! the empty output folder it had just created.

use std::path::Path;
mod common;
use common::{palpate, text};

fn s(p: &Path) -> &str {
    p.to_str().expect("utf-8 temp path")
}

/// No stage started: off a terminal, each stage's start is a `[k/n] id:` line.
fn assert_nothing_ran(msg: &str) {
    assert!(!msg.contains("[1/"), "a stage ran first:\n{msg}");
}

#[test]
fn run_refuses_an_out_that_is_a_file_before_running() {
    let tmp = tempfile::tempdir().expect("temp dir");
    let file = tmp.path().join("afile");
    std::fs::write(&file, "x").expect("file");
    for out in [s(&file), "/dev/null"] {
        for extra in [&[][..], &["--live"][..]] {
            let mut args = vec!["run", "graphs/quickstart.toml", "--out", out];
            args.extend_from_slice(extra);
            // The live form needs a graph whose stages stream (one trial,
            // as fast as it goes, should the check ever let it run).
            if !extra.is_empty() {
                args[1] = "graphs/live.toml";
                args.extend_from_slice(&[
                    "--set",
                    "stages.daq.speed=0",
                    "--set",
                    "stages.daq.angles=[45]",
                    "--set",
                    "stages.daq.trials_per_angle=1",
                ]);
            }
            let r = palpate(&args);
            let msg = text(&r);
            assert!(!r.status.success(), "{args:?}: accepted\n{msg}");
            assert!(
                msg.contains(&format!("output directory {out}: exists and is not a directory")),
                "{args:?}: {msg}"
            );
            assert_nothing_ran(&msg);
            assert!(!msg.contains("streaming live"), "{args:?}: {msg}");
        }
    }
    // A folder under a file cannot be created: named too.
    let under = file.join("sub");
    let r = palpate(&["run", "graphs/quickstart.toml", "--out", s(&under)]);
    let msg = text(&r);
    assert!(!r.status.success());
    assert!(
        msg.contains(&format!("output directory {}: cannot create it", under.display())),
        "{msg}"
    );
    assert_nothing_ran(&msg);
}

#[test]
fn a_refused_sweep_takes_away_only_the_folder_it_created() {
    let tmp = tempfile::tempdir().expect("temp dir");
    let bad = [
        "--set",
        "sweep.series=[{name=\"a\",key=\"stages.wss.sigma_mm\",values=[-1.0]}]",
    ];
    // A folder this run created, still empty when the sweep is refused: gone.
    let fresh = tmp.path().join("new");
    let mut args = vec!["run", "graphs/quickstart.toml", "--out", s(&fresh)];
    args.extend_from_slice(&bad);
    let r = palpate(&args);
    let msg = text(&r);
    assert!(!r.status.success(), "accepted:\n{msg}");
    assert!(msg.contains("in sweep series `a`"), "{msg}");
    assert_nothing_ran(&msg);
    assert!(!fresh.exists(), "the empty folder it created was left:\n{msg}");
    // A folder that was there before, with a file in it: kept, file and all.
    let kept = tmp.path().join("kept");
    std::fs::create_dir(&kept).expect("dir");
    std::fs::write(kept.join("notes.txt"), "mine").expect("file");
    args[3] = s(&kept);
    let r = palpate(&args);
    assert!(!r.status.success());
    assert_eq!(
        std::fs::read_to_string(kept.join("notes.txt")).expect("kept file"),
        "mine"
    );
    // An empty folder that was there before: kept too (not this run's to remove).
    let empty = tmp.path().join("empty");
    std::fs::create_dir(&empty).expect("dir");
    args[3] = s(&empty);
    let r = palpate(&args);
    assert!(!r.status.success());
    assert!(empty.is_dir(), "a folder the user made was removed");
    // A batch whose second job does not load: the first job's new folder goes too.
    let first = tmp.path().join("first");
    let jobs = tmp.path().join("jobs.toml");
    std::fs::write(
        &jobs,
        format!(
            "[[job]]\ngraph = \"graphs/quickstart.toml\"\nout = {:?}\n\n[[job]]\ngraph = \"graphs/no_such.toml\"\nout = {:?}\n",
            s(&first),
            s(&tmp.path().join("second"))
        ),
    )
    .expect("jobs file");
    let r = palpate(&["batch", s(&jobs)]);
    let msg = text(&r);
    assert!(!r.status.success(), "accepted:\n{msg}");
    assert!(msg.contains("job 2"), "{msg}");
    assert!(!first.exists(), "job 1's empty folder was left:\n{msg}");
}

#[test]
fn batch_refuses_a_file_out_and_two_jobs_with_one_out() {
    let tmp = tempfile::tempdir().expect("temp dir");
    let t = tmp.path();
    let file = t.join("afile");
    std::fs::write(&file, "x").expect("file");
    let jobs = t.join("jobs.toml");
    let job = |name: &str, out: &str| {
        format!("[[job]]\ngraph = \"graphs/quickstart.toml\"\nname = \"{name}\"\nout = \"{out}\"\n")
    };
    // A job whose out is a file: refused at start, naming the job.
    std::fs::write(&jobs, job("filed", s(&file))).expect("jobs file");
    let r = palpate(&["batch", s(&jobs)]);
    let msg = text(&r);
    assert!(!r.status.success(), "{msg}");
    assert!(
        msg.contains("job 1 (filed)") && msg.contains("exists and is not a directory"),
        "{msg}"
    );
    assert_nothing_ran(&msg);
    // Two jobs with one out, spelled differently: refused, naming both.
    let out = t.join("o");
    std::fs::write(
        &jobs,
        format!(
            "{}{}{}",
            job("a", s(&out)),
            job("b", s(&t.join("other"))),
            job("c", &format!("{}/./", s(&out)))
        ),
    )
    .expect("jobs file");
    let r = palpate(&["batch", s(&jobs)]);
    let msg = text(&r);
    assert!(!r.status.success(), "{msg}");
    assert!(
        msg.contains("job 1 (a)") && msg.contains("job 3 (c)") && msg.contains("output directory"),
        "{msg}"
    );
    assert_nothing_ran(&msg);
    // Two jobs with their own outs but one log.
    let log = t.join("one.log");
    std::fs::write(
        &jobs,
        format!(
            "{}log = \"{l}\"\n{}log = \"{l}\"\n",
            job("a", s(&out)),
            job("b", s(&t.join("other"))),
            l = s(&log)
        ),
    )
    .expect("jobs file");
    let r = palpate(&["batch", s(&jobs)]);
    let msg = text(&r);
    assert!(!r.status.success(), "{msg}");
    assert!(
        msg.contains("job 1 (a) and") && msg.contains("job 2 (b)") && msg.contains("log"),
        "{msg}"
    );
    assert_nothing_ran(&msg);
}

#[test]
fn block_zero_is_refused_naming_the_flag() {
    let r = palpate(&["run", "graphs/live.toml", "--live", "--block", "0"]);
    let msg = text(&r);
    // clap's usage error (2), before anything streams.
    assert_eq!(r.status.code(), Some(2), "{msg}");
    assert!(msg.contains("--block") && msg.contains("at least 1"), "{msg}");
    assert!(!msg.contains("streaming live"), "{msg}");
}

#[test]
fn sweep_list_prints_the_real_seed_range_or_refuses_an_overflow() {
    let max = "18446744073709551615";
    let r = palpate(&[
        "sweep",
        "list",
        "graphs/quickstart.toml",
        "--set",
        &format!("run.seed=\"{max}\""),
        "--set",
        "sweep.repeats=3",
    ]);
    let msg = text(&r);
    assert!(!r.status.success(), "{msg}");
    assert!(
        msg.contains("`run.seed` = 18446744073709551615") && msg.contains("`sweep.repeats` = 3"),
        "{msg}"
    );
    assert!(!msg.contains(&format!("{max}..={max}")), "{msg}");
    // `run` and `check` refuse it too, before running.
    let tmp = tempfile::tempdir().expect("temp dir");
    for cmd in ["run", "check"] {
        let seed = format!("run.seed=\"{max}\"");
        let mut args = vec![
            cmd,
            "graphs/quickstart.toml",
            "--set",
            &seed,
            "--set",
            "sweep.repeats=3",
        ];
        if cmd == "run" {
            args.extend_from_slice(&["--out", s(tmp.path())]);
        }
        let r = palpate(&args);
        let msg = text(&r);
        assert!(!r.status.success(), "{cmd}: {msg}");
        assert!(msg.contains("`sweep.repeats` = 3"), "{cmd}: {msg}");
        assert_nothing_ran(&msg);
    }
    // A range that ends at the largest seed prints as it is.
    let r = palpate(&[
        "sweep",
        "list",
        "graphs/quickstart.toml",
        "--set",
        "run.seed=\"18446744073709551613\"",
        "--set",
        "sweep.repeats=3",
    ]);
    let msg = text(&r);
    assert!(r.status.success(), "{msg}");
    assert!(
        msg.contains("seeds 18446744073709551613..=18446744073709551615"),
        "{msg}"
    );
}
