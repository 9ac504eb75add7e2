//! The user guide's "Bringing your own recording" chapter, run as written: every
//! `cargo run --release -- ...` command of its `sh` blocks runs (with the built
//! `palpate`) from a copy of the repository's example folder, in order; each
//! must succeed, and every line of the `text` block that follows a command (its
//! shown output) must appear in what it printed. Then the two graphs' per-trial
//! answers must agree: the spikes `write_spikes` wrote, read back by
//! `spike_file`, give the same estimates as the signals they came from.

use std::path::{Path, PathBuf};
use std::process::Command;

const CHAPTER: &str = "docs/guide/src/recording.md";
const PREFIX: &str = "cargo run --release -- ";

/// `(command arguments, lines its output must contain)`, in chapter order.
fn steps(chapter: &str) -> Vec<(Vec<String>, Vec<String>)> {
    let mut steps: Vec<(Vec<String>, Vec<String>)> = Vec::new();
    let mut lines = chapter.lines();
    while let Some(line) = lines.next() {
        let Some(lang) = line.trim().strip_prefix("```") else {
            continue;
        };
        let lang = lang.trim().to_string();
        let body: Vec<&str> = lines.by_ref().take_while(|l| l.trim() != "```").collect();
        match lang.as_str() {
            "sh" => {
                for cmd in body.iter().filter_map(|l| l.trim().strip_prefix(PREFIX)) {
                    let args = cmd.split_whitespace().map(String::from).collect();
                    steps.push((args, Vec::new()));
                }
            }
            "text" => {
                // Output shown after a command belongs to it (blocks before the
                // first command show files, not output).
                if let Some(last) = steps.last_mut() {
                    if last.1.is_empty() {
                        last.1 = body
                            .iter()
                            .map(|l| l.trim().to_string())
                            .filter(|l| !l.is_empty())
                            .collect();
                    }
                }
            }
            _ => {}
        }
    }
    steps
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for entry in std::fs::read_dir(from).unwrap() {
        let entry = entry.unwrap();
        std::fs::copy(entry.path(), to.join(entry.file_name())).unwrap();
    }
}

/// `trial -> estimate_deg` of a `mae` sink's per-trial table.
fn answers(csv: &Path) -> Vec<(String, String)> {
    let text = std::fs::read_to_string(csv).unwrap_or_else(|e| panic!("{}: {e}", csv.display()));
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let col = |name: &str| header.iter().position(|h| *h == name).unwrap();
    let (t, e) = (col("trial"), col("estimate_deg"));
    let mut rows: Vec<(String, String)> = lines
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            (f[t].to_string(), f[e].to_string())
        })
        .collect();
    rows.sort();
    rows
}

#[test]
fn the_bring_your_own_recording_chapter_runs_as_written() {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let chapter = std::fs::read_to_string(root.join(CHAPTER)).unwrap();
    let steps = steps(&chapter);
    assert_eq!(
        steps.len(),
        3,
        "check, run the signals, run the spikes: {steps:?}"
    );
    // A fresh copy of what a clone holds, so the run writes nothing in the repository.
    let clone = std::env::temp_dir().join(format!("palpate-guide-recording-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&clone);
    copy_dir(
        &root.join("examples/recording"),
        &clone.join("examples/recording"),
    );
    std::fs::create_dir_all(clone.join("graphs")).unwrap();
    std::fs::copy(
        root.join("graphs/palpate-graph.schema.json"),
        clone.join("graphs/palpate-graph.schema.json"),
    )
    .unwrap();
    for (args, shown) in &steps {
        let out = Command::new(env!("CARGO_BIN_EXE_palpate"))
            .args(args)
            .current_dir(&clone)
            .output()
            .unwrap();
        let stdout = String::from_utf8_lossy(&out.stdout);
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(
            out.status.success(),
            "`palpate {}` failed:\n{stdout}\n{stderr}",
            args.join(" ")
        );
        if args[0] == "check" {
            assert!(
                stdout.contains("ok (10 stages, 0 warnings)")
                    || stderr.contains("ok (10 stages, 0 warnings)"),
                "{stdout}{stderr}"
            );
        }
        for line in shown {
            assert!(
                stdout.contains(line.as_str()),
                "`palpate {}` did not print the chapter's line\n  {line}\nit printed:\n{stdout}",
                args.join(" ")
            );
        }
    }
    // The check step's answer, as the chapter quotes it.
    assert!(chapter.contains("prints `ok (10 stages, 0 warnings)`"));
    let from_signals = answers(&clone.join("out/recording/mae_trials.csv"));
    let from_spikes = answers(&clone.join("out/recording-spikes/mae_trials.csv"));
    assert_eq!(from_signals.len(), 4);
    assert_eq!(
        from_signals, from_spikes,
        "write_spikes -> spike_file changed an answer"
    );
    for file in ["confusion_wss.svg", "mae_per_class.svg", "spikes/labels.toml"] {
        assert!(clone.join("out/recording").join(file).exists(), "{file}");
    }
    let _ = std::fs::remove_dir_all(&clone);
}
