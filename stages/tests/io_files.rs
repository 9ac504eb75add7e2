//! File sources and sinks end to end: every fixture is generated here, into a
//! temporary folder (a MATLAB v5 file is written byte by byte by `mat_v5`).

use palpate_core::{load_str, Item, Payload, SpikeTrain, Stimulus, TaxelLayout};
use palpate_stages::io::arrays::{npy_bytes, read_npy_plain};
use std::io::Write;
use std::path::Path;
use std::sync::Arc;
mod common;

fn run_graph(dir: &Path, toml: &str) -> Result<palpate_core::RunResult, String> {
    common::run_graph_file(dir, "g.toml", toml)
}

fn items<'a>(r: &'a palpate_core::RunResult, id: &str) -> &'a [Item] {
    &r.outputs[id]
}

fn signals(it: &Item) -> &palpate_core::Signals {
    match &it.payload {
        Payload::Signals(s) => s,
        _ => panic!("not signals"),
    }
}

fn spikes(it: &Item) -> &SpikeTrain {
    match &it.payload {
        Payload::Spikes(s) => s,
        _ => panic!("not spikes"),
    }
}

/// A test signal: taxel x, sample k (distinct for every pair, not round).
fn val(trial: usize, x: usize, k: usize) -> f64 {
    1.75 + 0.01 * trial as f64 + 0.1 * x as f64 + (k as f64 * 0.37).sin() / 3.0
}

fn csv_trial(trial: usize, taxels: usize, samples: usize, rate: f64) -> String {
    let mut s = String::from("time_ms");
    for x in 0..taxels {
        s.push_str(&format!(",taxel_{x}"));
    }
    s.push('\n');
    for k in 0..samples {
        s.push_str(&format!("{}", k as f64 * 1000.0 / rate));
        for x in 0..taxels {
            s.push_str(&format!(",{}", val(trial, x, k)));
        }
        s.push('\n');
    }
    s
}

const GRID2: &str = r#"layout = { kind = "grid", rows = 2, cols = 2, pitch_mm = 3.0, taxel_mm = 2.0 }"#;

fn assert_data(s: &palpate_core::Signals, trial: usize, samples: usize) {
    assert_eq!(s.n_samples(), samples);
    for (x, col) in s.data.iter().enumerate() {
        for (k, v) in col.iter().enumerate() {
            assert_eq!(*v, val(trial, x, k), "taxel {x} sample {k}");
        }
    }
}

#[test]
fn csv_glob_one_trial_per_file_with_toml_sidecar() {
    let d = tempfile::tempdir().unwrap();
    std::fs::create_dir(d.path().join("rec")).unwrap();
    for t in 0..3 {
        std::fs::write(d.path().join(format!("rec/t{t}.csv")), csv_trial(t, 4, 50, 500.0)).unwrap();
    }
    std::fs::write(
        d.path().join("labels.toml"),
        "[trials.t0]\nangle_deg = 45.0\n[trials.t1]\nangle_deg = 30.0\n[trials.t2]\nangle_deg = 45.0\nstimulus = \"ridge\"\n",
    )
    .unwrap();
    let r = run_graph(
        d.path(),
        &format!("[run]\nseed = 1\n[stages.src]\ntype = \"signal_file\"\npath = \"rec/*.csv\"\nlabels = \"labels.toml\"\n{GRID2}\n"),
    )
    .unwrap();
    let it = items(&r, "src");
    assert_eq!(it.len(), 3);
    let ids: Vec<&str> = it.iter().map(|i| i.meta.trial_id.as_str()).collect();
    assert_eq!(ids, ["t0", "t1", "t2"]);
    for (t, i) in it.iter().enumerate() {
        let s = signals(i);
        assert!(
            (s.sample_rate_hz - 500.0).abs() < 1e-9,
            "rate from the time column"
        );
        assert_eq!(s.layout.len(), 4);
        assert_data(s, t, 50);
    }
    assert_eq!(it[0].meta.label.angle_deg, Some(45.0));
    assert_eq!(it[2].meta.label.stimulus, Stimulus::Ridge);
    // Groups: repetition within a class (t2 is a ridge: its own class).
    let groups: Vec<usize> = it.iter().map(|i| i.meta.group).collect();
    assert_eq!(groups, [0, 0, 0]);
}

#[test]
fn a_label_file_declares_each_trials_speed() {
    let d = tempfile::tempdir().unwrap();
    std::fs::create_dir(d.path().join("rec")).unwrap();
    for t in 0..3 {
        std::fs::write(d.path().join(format!("rec/t{t}.csv")), csv_trial(t, 4, 20, 500.0)).unwrap();
    }
    let graph = |labels: &str| {
        std::fs::write(d.path().join("labels.toml"), labels).unwrap();
        run_graph(
            d.path(),
            &format!("[run]\nseed = 1\n[stages.src]\ntype = \"signal_file\"\npath = \"rec/*.csv\"\nlabels = \"labels.toml\"\n{GRID2}\n"),
        )
    };
    // The key, else a numeric condition of that name, else none.
    let r = graph(
        "[trials.t0]\nspeed_mm_s = 3.0\nconditions = { speed_mm_s = 9 }\n\
         [trials.t1]\nconditions = { speed_mm_s = 1.5 }\n[trials.t2]\nangle_deg = 30.0\n",
    )
    .unwrap();
    let speeds: Vec<Option<f64>> = items(&r, "src").iter().map(|i| i.meta.speed_mm_s).collect();
    assert_eq!(speeds, [Some(3.0), Some(1.5), None]);
    // A speed that is not a positive number is refused, naming the trial.
    for (bad, want) in [
        ("[trials.t0]\nconditions = { speed_mm_s = \"fast\" }\n", "`t0`"),
        ("[trials.t1]\nspeed_mm_s = -2.0\n", "speed_mm_s"),
        ("[trials.t2]\nconditions = { speed_mm_s = 0 }\n", "`t2`"),
    ] {
        let others = ["t0", "t1", "t2"]
            .iter()
            .filter(|t| !bad.contains(&format!("[trials.{t}]")))
            .map(|t| format!("[trials.{t}]\n"))
            .collect::<String>();
        let e = graph(&format!("{bad}{others}")).unwrap_err();
        assert!(e.contains(want) && e.contains("speed_mm_s"), "{bad}: {e}");
    }
}

#[test]
fn csv_many_trials_per_file_with_labels_in_columns() {
    let d = tempfile::tempdir().unwrap();
    let mut s = String::from("# exported by the lab rig\ntrial,angle_deg,speed_mm_s,taxel_0,taxel_1\n");
    for (name, angle, speed) in [("a", 10.0, 2.0), ("b", 20.0, 2.0), ("c", 10.0, 4.5)] {
        for k in 0..5 {
            s.push_str(&format!("{name},{angle},{speed},{},{}\n", k as f64, -(k as f64)));
        }
    }
    std::fs::write(d.path().join("all.csv"), s).unwrap();
    let r = run_graph(
        d.path(),
        "[stages.src]\ntype = \"signal_file\"\npath = \"all.csv\"\nsample_rate_hz = 1000.0\n\
         layout = { kind = \"positions\", positions_mm = [[0.0, 0.0], [3.0, 1.0]], taxel_mm = 2.0 }\n",
    )
    .unwrap();
    let it = items(&r, "src");
    let ids: Vec<&str> = it.iter().map(|i| i.meta.trial_id.as_str()).collect();
    assert_eq!(ids, ["all-a", "all-b", "all-c"]);
    let groups: Vec<usize> = it.iter().map(|i| i.meta.group).collect();
    assert_eq!(groups, [0, 0, 1], "c is the second repetition of 10 degrees");
    let speeds: Vec<Option<f64>> = it.iter().map(|i| i.meta.speed_mm_s).collect();
    assert_eq!(
        speeds,
        [Some(2.0), Some(2.0), Some(4.5)],
        "each trial's declared speed"
    );
    assert_eq!(signals(&it[1]).data[1], vec![0.0, -1.0, -2.0, -3.0, -4.0]);
    assert!(matches!(signals(&it[0]).layout, TaxelLayout::Positions { .. }));
}

#[test]
fn csv_custom_column_names_and_time_in_seconds() {
    let d = tempfile::tempdir().unwrap();
    std::fs::write(
        d.path().join("r.csv"),
        "time_s,ch2,ch1\n0,1,2\n0.002,3,4\n0.004,5,6\n",
    )
    .unwrap();
    let r = run_graph(
        d.path(),
        "[stages.src]\ntype = \"signal_file\"\npath = \"r.csv\"\ncolumns = [\"ch1\", \"ch2\"]\n\
         layout = { kind = \"grid\", rows = 1, cols = 2, pitch_mm = 3.0, taxel_mm = 2.0 }\n",
    )
    .unwrap();
    let s = signals(&items(&r, "src")[0]);
    assert!((s.sample_rate_hz - 500.0).abs() < 1e-9);
    assert_eq!(s.data, vec![vec![2.0, 4.0, 6.0], vec![1.0, 3.0, 5.0]]);
}

/// Files as spreadsheets and loggers write them: `;`- or tab-separated (the
/// delimiter is sniffed from the header), with columns palpate has no use for
/// (`ignore_columns`), or with host time stamps that jitter (the time column
/// ignored, the rate given). Each reads the same samples as the plain file;
/// what it cannot read is an error that says what to do.
#[test]
fn spreadsheet_and_logger_csv_variants_read_the_same_samples() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    let plain = csv_trial(0, 4, 12, 1000.0);
    let src = |file: &str, extra: &str| format!("path = \"{file}\"\n{GRID2}\n{extra}");
    let read = |file: &str, extra: &str| -> palpate_core::Signals {
        let r = run_graph(
            p,
            &format!("[stages.src]\ntype = \"signal_file\"\n{}\n", src(file, extra)),
        )
        .unwrap_or_else(|e| panic!("{file}: {e}"));
        signals(&items(&r, "src")[0]).clone()
    };
    for (name, sep) in [("semi.csv", ";"), ("tab.csv", "\t")] {
        std::fs::write(p.join(name), plain.replace(',', sep)).unwrap();
        let s = read(name, "");
        assert_data(&s, 0, 12);
        assert!((s.sample_rate_hz - 1000.0).abs() < 1e-9, "{name}");
    }
    // A force channel beside the taxels: an error naming the key that skips it.
    let with_force: String = plain
        .lines()
        .enumerate()
        .map(|(k, l)| {
            format!(
                "{l},{}\n",
                if k == 0 {
                    "force".to_string()
                } else {
                    format!("{k}")
                }
            )
        })
        .collect();
    std::fs::write(p.join("force.csv"), &with_force).unwrap();
    let e = source_error(p, &src("force.csv", ""));
    assert!(
        e.contains("unknown column `force`") && e.contains("ignore_columns"),
        "{e}"
    );
    assert_data(&read("force.csv", "ignore_columns = [\"force\"]"), 0, 12);
    // A taxel column past the layout's is a larger array, not a column to skip.
    let wide = plain
        .replacen("taxel_3\n", "taxel_3,taxel_4\n", 1)
        .replace('\n', ",9\n")
        .replacen("taxel_4,9\n", "taxel_4\n", 1);
    std::fs::write(p.join("wide.csv"), wide).unwrap();
    let e = source_error(p, &src("wide.csv", ""));
    assert!(
        e.contains("`taxel_4` is past the layout's 4 taxels") && !e.contains("ignore_columns"),
        "{e}"
    );
    // A taxel column cannot be skipped: that would drop a taxel silently.
    let e = source_error(p, &src("force.csv", "ignore_columns = [\"force\", \"taxel_2\"]"));
    assert!(
        e.contains("`taxel_2` is taxel 2") && e.contains("ignore_columns"),
        "{e}"
    );
    // Host time stamps jittering by 30 % of a sample: refused (a missing row
    // looks the same), with the way out in the message; taken with it.
    let jitter: String = plain
        .lines()
        .enumerate()
        .map(|(k, l)| {
            if k == 0 {
                format!("{l}\n")
            } else {
                let (_, rest) = l.split_once(',').unwrap();
                let t = (k - 1) as f64 + if k % 2 == 0 { 0.3 } else { -0.3 };
                format!("{t},{rest}\n")
            }
        })
        .collect();
    std::fs::write(p.join("jitter.csv"), jitter).unwrap();
    let e = source_error(p, &src("jitter.csv", ""));
    assert!(
        e.contains("off the uniform grid") && e.contains("ignore_columns") && e.contains("sample_rate_hz"),
        "{e}"
    );
    let s = read(
        "jitter.csv",
        "ignore_columns = [\"time_ms\"]\nsample_rate_hz = 1000.0",
    );
    assert_data(&s, 0, 12);
    // An absurd time is printed as a number, not 301 digits.
    let far: String = plain
        .lines()
        .enumerate()
        .map(|(k, l)| match (k, l.split_once(',')) {
            (3, Some((_, rest))) => format!("1e300,{rest}\n"),
            _ => format!("{l}\n"),
        })
        .collect();
    std::fs::write(p.join("far.csv"), far).unwrap();
    let e = source_error(p, &src("far.csv", ""));
    assert!(e.contains("1e300 ms") && e.len() < 600, "{e}");
    // A delimiter after every value (loggers that print `v,` per value),
    // in `,`- and `;`-separated files: the same samples; a value under the
    // unnamed last column is an error naming its line, not dropped.
    for (name, sep) in [("trail.csv", ","), ("trail_semi.csv", ";")] {
        let trail = plain.replace(',', sep).replace('\n', &format!("{sep}\n"));
        std::fs::write(p.join(name), &trail).unwrap();
        assert_data(&read(name, ""), 0, 12);
    }
    let stray: String = plain
        .replace('\n', ",\n")
        .lines()
        .enumerate()
        .map(|(k, l)| {
            if k == 3 {
                format!("{l}7\n")
            } else {
                format!("{l}\n")
            }
        })
        .collect();
    std::fs::write(p.join("stray.csv"), stray).unwrap();
    let e = source_error(p, &src("stray.csv", ""));
    assert!(
        e.contains("stray.csv, line 4") && e.contains("`7`") && e.contains("header is empty"),
        "{e}"
    );
    // An unnamed column elsewhere stays an unknown column.
    std::fs::write(p.join("hole.csv"), plain.replacen("time_ms,", "time_ms,,", 1)).unwrap();
    assert!(source_error(p, &src("hole.csv", "")).contains("unknown column ``"));
    // A decimal comma in a `;`-separated file: an error that names it.
    let comma = plain
        .replace(',', ";")
        .replacen(&format!("{}", val(0, 1, 0)), "1,85", 1);
    std::fs::write(p.join("comma.csv"), comma).unwrap();
    let e = source_error(p, &src("comma.csv", ""));
    assert!(
        e.contains("line 2") && e.contains("`1,85`") && e.contains("decimal comma"),
        "{e}"
    );
}

/// A label file may name a one-trial file's trial by the file's name; naming
/// one trial both ways is an error, as is a name no file holds.
#[test]
fn a_label_file_may_name_trials_by_their_file_names() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    std::fs::write(p.join("a.csv"), csv_trial(0, 4, 6, 1000.0)).unwrap();
    std::fs::write(p.join("b.csv"), csv_trial(1, 4, 6, 1000.0)).unwrap();
    let graph = format!(
        "[stages.src]\ntype = \"signal_file\"\npaths = [\"a.csv\", \"b.csv\"]\nlabels = \"l.csv\"\n{GRID2}\n"
    );
    std::fs::write(p.join("l.csv"), "trial;angle_deg\na.csv;30\nb;60\n").unwrap();
    let r = run_graph(p, &graph).unwrap();
    let angles: Vec<Option<f64>> = items(&r, "src")
        .iter()
        .map(|it| it.meta.label.angle_deg)
        .collect();
    assert_eq!(angles, [Some(30.0), Some(60.0)]);
    std::fs::write(p.join("l.csv"), "trial,angle_deg\na.csv,30\na,31\nb,60\n").unwrap();
    let e = run_graph(p, &graph).err().unwrap();
    assert!(
        e.contains("names trial `a` twice") && e.contains("`a.csv`"),
        "{e}"
    );
    std::fs::write(p.join("l.csv"), "trial,angle_deg\na,30\nb,60\nc.csv,90\n").unwrap();
    let e = run_graph(p, &graph).err().unwrap();
    assert!(e.contains("do not hold: `c.csv`"), "{e}");
}

fn flat(trials: &[usize], taxels: usize, samples: usize, taxel_major: bool) -> Vec<f64> {
    let mut v = Vec::new();
    for &t in trials {
        if taxel_major {
            for x in 0..taxels {
                v.extend((0..samples).map(|k| val(t, x, k)));
            }
        } else {
            for k in 0..samples {
                v.extend((0..taxels).map(|x| val(t, x, k)));
            }
        }
    }
    v
}

#[test]
fn npy_two_and_three_dimensional_and_taxel_major() {
    let d = tempfile::tempdir().unwrap();
    std::fs::write(
        d.path().join("one.npy"),
        npy_bytes(&[40, 4], &flat(&[0], 4, 40, false)).unwrap(),
    )
    .unwrap();
    std::fs::write(
        d.path().join("stack.npy"),
        npy_bytes(&[2, 40, 4], &flat(&[1, 2], 4, 40, false)).unwrap(),
    )
    .unwrap();
    let r = run_graph(
        d.path(),
        &format!("[stages.src]\ntype = \"signal_file\"\npaths = [\"one.npy\", \"stack.npy\"]\nsample_rate_hz = 1000.0\n{GRID2}\n"),
    )
    .unwrap();
    let it = items(&r, "src");
    let ids: Vec<&str> = it.iter().map(|i| i.meta.trial_id.as_str()).collect();
    assert_eq!(ids, ["one", "stack-0", "stack-1"]);
    for (t, i) in it.iter().enumerate() {
        assert_data(signals(i), t, 40);
    }
    // Taxel-major.
    let d = tempfile::tempdir().unwrap();
    std::fs::write(
        d.path().join("tm.npy"),
        npy_bytes(&[4, 30], &flat(&[0], 4, 30, true)).unwrap(),
    )
    .unwrap();
    let r = run_graph(
        d.path(),
        &format!("[stages.src]\ntype = \"signal_file\"\npath = \"tm.npy\"\nsample_rate_hz = 1000.0\ntaxel_major = true\n{GRID2}\n"),
    )
    .unwrap();
    assert_data(signals(&items(&r, "src")[0]), 0, 30);
}

fn npz(path: &Path, arrays: &[(&str, Vec<usize>, Vec<f64>)], deflate: bool) {
    let f = std::fs::File::create(path).unwrap();
    let mut z = zip::ZipWriter::new(f);
    let method = if deflate {
        zip::CompressionMethod::Deflated
    } else {
        zip::CompressionMethod::Stored
    };
    let opts = zip::write::SimpleFileOptions::default().compression_method(method);
    for (name, shape, data) in arrays {
        z.start_file(format!("{name}.npy"), opts).unwrap();
        z.write_all(&npy_bytes(shape, data).unwrap()).unwrap();
    }
    z.finish().unwrap();
}

#[test]
fn npz_arrays_per_trial_and_stacks_with_labels_and_rate() {
    let d = tempfile::tempdir().unwrap();
    npz(
        &d.path().join("sess.npz"),
        &[
            ("sample_rate_hz", vec![], vec![250.0]),
            ("first", vec![20, 4], flat(&[0], 4, 20, false)),
            ("second", vec![20, 4], flat(&[1], 4, 20, false)),
            ("angle_deg", vec![2], vec![15.0, 90.0]),
            ("group", vec![2], vec![3.0, 4.0]),
            ("speed_mm_s", vec![2], vec![5.0, 2.5]),
        ],
        true,
    );
    npz(
        &d.path().join("stacked.npz"),
        &[
            ("signals", vec![2, 20, 4], flat(&[2, 3], 4, 20, false)),
            ("sample_rate_hz", vec![1], vec![250.0]),
        ],
        false,
    );
    let r = run_graph(
        d.path(),
        &format!("[stages.src]\ntype = \"signal_file\"\npath = \"*.npz\"\n{GRID2}\n"),
    )
    .unwrap();
    let it = items(&r, "src");
    let ids: Vec<&str> = it.iter().map(|i| i.meta.trial_id.as_str()).collect();
    assert_eq!(ids, ["sess-first", "sess-second", "stacked-0", "stacked-1"]);
    for (t, i) in it.iter().enumerate() {
        assert_data(signals(i), t, 20);
        assert_eq!(signals(i).sample_rate_hz, 250.0);
    }
    assert_eq!(it[1].meta.label.angle_deg, Some(90.0));
    assert_eq!(it[1].meta.group, 4);
    // Each trial's declared speed (what WSS builds its templates for).
    assert_eq!(it[0].meta.speed_mm_s, Some(5.0));
    assert_eq!(it[1].meta.speed_mm_s, Some(2.5));
    assert_eq!(it[2].meta.speed_mm_s, None);
    assert_eq!(it[2].meta.label.stimulus, Stimulus::Unknown);
}

/// A MATLAB v5 file of real double matrices; `data` is given column-major, as
/// MATLAB stores it. Format: MATLAB's "MAT-File Format" (128-byte header, then
/// one miMATRIX element per variable: flags, dimensions, name, real part).
fn mat_v5(vars: &[(&str, Vec<usize>, Vec<f64>)]) -> Vec<u8> {
    fn pad8(b: &mut Vec<u8>) {
        while !b.len().is_multiple_of(8) {
            b.push(0);
        }
    }
    fn element(b: &mut Vec<u8>, ty: u32, payload: &[u8]) {
        b.extend(ty.to_le_bytes());
        b.extend((payload.len() as u32).to_le_bytes());
        b.extend(payload);
        pad8(b);
    }
    let mut out = Vec::new();
    let mut text = b"MATLAB 5.0 MAT-file, written by palpate's tests".to_vec();
    text.resize(116, b' ');
    out.extend(text);
    out.extend([0u8; 8]);
    out.extend(0x0100u16.to_le_bytes());
    out.extend(b"IM");
    for (name, dims, data) in vars {
        let mut m = Vec::new();
        let mut flags = 6u32.to_le_bytes().to_vec(); // mxDOUBLE_CLASS
        flags.extend([0u8; 4]);
        element(&mut m, 6, &flags); // miUINT32
        let d: Vec<u8> = dims.iter().flat_map(|&x| (x as i32).to_le_bytes()).collect();
        element(&mut m, 5, &d); // miINT32
        element(&mut m, 1, name.as_bytes()); // miINT8
        let r: Vec<u8> = data.iter().flat_map(|x| x.to_le_bytes()).collect();
        element(&mut m, 9, &r); // miDOUBLE
        element(&mut out, 14, &m); // miMATRIX
    }
    out
}

/// Column-major `data(sample, taxel, trial)`.
fn matlab_stack(trials: &[usize], taxels: usize, samples: usize) -> Vec<f64> {
    let mut v = Vec::new();
    for &t in trials {
        for x in 0..taxels {
            v.extend((0..samples).map(|k| val(t, x, k)));
        }
    }
    v
}

#[test]
fn mat_two_and_three_dimensional_with_fs() {
    let d = tempfile::tempdir().unwrap();
    std::fs::write(
        d.path().join("m.mat"),
        mat_v5(&[
            ("fs", vec![1, 1], vec![1000.0]),
            ("data", vec![25, 4, 2], matlab_stack(&[0, 1], 4, 25)),
            ("angle_deg", vec![1, 2], vec![40.0, 70.0]),
        ]),
    )
    .unwrap();
    std::fs::write(
        d.path().join("single.mat"),
        mat_v5(&[
            ("rec", vec![25, 4], matlab_stack(&[2], 4, 25)),
            ("fs", vec![1, 1], vec![1000.0]),
        ]),
    )
    .unwrap();
    let r = run_graph(
        d.path(),
        &format!("[stages.src]\ntype = \"signal_file\"\npaths = [\"m.mat\", \"single.mat\"]\n{GRID2}\n"),
    )
    .unwrap();
    let it = items(&r, "src");
    let ids: Vec<&str> = it.iter().map(|i| i.meta.trial_id.as_str()).collect();
    assert_eq!(ids, ["m-0", "m-1", "single"]);
    for (t, i) in it.iter().enumerate() {
        assert_data(signals(i), t, 25);
        assert_eq!(signals(i).sample_rate_hz, 1000.0);
    }
    assert_eq!(it[1].meta.label.angle_deg, Some(70.0));
}

/// SciPy's v5 files of int32 ADC counts (tests/data/make_mat5.py): an
/// int32 `fs` and a 2x16 int32 `data`, compressed or not, read as one trial
/// of 2 samples on 16 taxels with the counts as values; the char, cell,
/// struct and logical variables beside them are no signal. (The `matfile`
/// crate used before read no int32 variable.)
#[test]
fn mat_v5_int32_counts_and_fs() {
    let d = tempfile::tempdir().unwrap();
    let fixtures = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data");
    for f in ["mat5_int32.mat", "mat5_int32_z.mat"] {
        std::fs::copy(fixtures.join(f), d.path().join(f)).unwrap();
        let grid = r#"layout = { kind = "grid", rows = 4, cols = 4, pitch_mm = 3.0, taxel_mm = 2.0 }"#;
        let r = run_graph(
            d.path(),
            &format!(
                "[stages.src]\ntype = \"signal_file\"\npath = \"{f}\"\nvariables = [\"data\"]\n{grid}\n"
            ),
        )
        .unwrap_or_else(|e| panic!("{f}: {e}"));
        let it = items(&r, "src");
        assert_eq!(it.len(), 1, "{f}");
        let s = signals(&it[0]);
        assert_eq!((s.n_samples(), s.sample_rate_hz), (2, 1000.0), "{f}");
        for (x, col) in s.data.iter().enumerate() {
            for (k, v) in col.iter().enumerate() {
                let n = (16 * k + x) as f64;
                assert_eq!(
                    *v,
                    if n % 2.0 == 1.0 { -n } else { n },
                    "{f}: taxel {x} sample {k}"
                );
            }
        }
    }
}

/// MATLAB v7.3 (HDF5) files, written by libhdf5 through h5py as MATLAB lays
/// them out (tests/data/make_mat73.py): the same trials as the v5 files
/// above, a chunked and deflated stack, integer ADC counts, the variables
/// MATLAB stores that hold no signal passed over, complex data and a cut file
/// refused with the file's name.
#[test]
fn mat_v73_files_read_as_v5_ones() {
    let d = tempfile::tempdir().unwrap();
    let fixtures = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data");
    for f in ["mat73_stack.mat", "mat73_int16.mat", "mat73_complex.mat"] {
        std::fs::copy(fixtures.join(f), d.path().join(f)).unwrap();
    }
    let r = run_graph(
        d.path(),
        &format!("[stages.src]\ntype = \"signal_file\"\npath = \"mat73_stack.mat\"\n{GRID2}\n"),
    )
    .unwrap();
    let it = items(&r, "src");
    let ids: Vec<&str> = it.iter().map(|i| i.meta.trial_id.as_str()).collect();
    // `note` (char), `meta` (struct), `unused` (empty) and `#refs#` are no trials.
    assert_eq!(ids, ["mat73_stack-0", "mat73_stack-1"]);
    for (t, i) in it.iter().enumerate() {
        assert_data(signals(i), t, 25);
        assert_eq!(signals(i).sample_rate_hz, 1000.0);
    }
    assert_eq!(it[1].meta.label.angle_deg, Some(70.0));

    let r = run_graph(
        d.path(),
        &format!("[stages.src]\ntype = \"signal_file\"\npath = \"mat73_int16.mat\"\n{GRID2}\n"),
    )
    .unwrap();
    let s = signals(&items(&r, "src")[0]);
    assert_eq!((s.n_samples(), s.sample_rate_hz), (25, 500.0));
    for (x, col) in s.data.iter().enumerate() {
        for (k, v) in col.iter().enumerate() {
            assert_eq!(*v, (val(2, x, k) * 1000.0).round(), "taxel {x} sample {k}");
        }
    }

    let e = source_error(
        d.path(),
        &format!("path = \"mat73_complex.mat\"\nsample_rate_hz = 1000.0\n{GRID2}"),
    );
    assert!(
        e.contains("mat73_complex.mat") && e.contains("`data`") && e.contains("complex"),
        "{e}"
    );

    let b = std::fs::read(d.path().join("mat73_stack.mat")).unwrap();
    for cut in [600, b.len() / 2, b.len() - 100] {
        std::fs::write(d.path().join("cut.mat"), &b[..cut]).unwrap();
        let e = source_error(d.path(), &format!("path = \"cut.mat\"\n{GRID2}"));
        assert!(e.contains("cut.mat"), "cut at {cut}: {e}");
    }
}

/// A continuous log of three palpations (2 x 2 taxels, 500 Hz) as one CSV:
/// `segment = "contact"` cuts it into three trials with the samples in
/// contact, ids `<file>-<j>` whose angles come from the sidecar; `fixed`
/// cuts windows; a threshold the log never reaches is an error that gives
/// its levels; the keys are checked.
#[test]
fn one_log_of_several_palpations_is_cut_at_contact() {
    let d = tempfile::tempdir().unwrap();
    // (samples, in contact): 150 off, 300 on, 150 off, 250 on, 150 off, 200 on, 150 off.
    let runs = [
        (150, false),
        (300, true),
        (150, false),
        (250, true),
        (150, false),
        (200, true),
        (150, false),
    ];
    let level = |on: bool, x: usize, k: usize| {
        if on {
            1.75 + 0.01 * x as f64 + (k as f64 * 0.37).sin() / 20.0
        } else {
            3.3
        }
    };
    let mut csv = String::from("time_ms,taxel_0,taxel_1,taxel_2,taxel_3\n");
    let mut k = 0;
    let mut on_at = Vec::new();
    for &(len, on) in &runs {
        if on {
            on_at.push((k, len));
        }
        for _ in 0..len {
            csv.push_str(&format!("{}", k as f64 * 2.0));
            for x in 0..4 {
                csv.push_str(&format!(",{}", level(on, x, k)));
            }
            csv.push('\n');
            k += 1;
        }
    }
    std::fs::write(d.path().join("log.csv"), csv).unwrap();
    std::fs::write(
        d.path().join("labels.csv"),
        "trial,angle_deg\nlog-0,30\nlog-1,60\nlog-2,90\n",
    )
    .unwrap();
    let src =
        |extra: &str| format!("[stages.src]\ntype = \"signal_file\"\npath = \"log.csv\"\n{GRID2}\n{extra}\n");
    let r = run_graph(d.path(), &src("segment = \"contact\"\nlabels = \"labels.csv\"")).unwrap();
    let it = items(&r, "src");
    let ids: Vec<&str> = it.iter().map(|i| i.meta.trial_id.as_str()).collect();
    assert_eq!(ids, ["log-0", "log-1", "log-2"]);
    let angles: Vec<Option<f64>> = it.iter().map(|i| i.meta.label.angle_deg).collect();
    assert_eq!(angles, [Some(30.0), Some(60.0), Some(90.0)]);
    for (i, &(start, len)) in it.iter().zip(&on_at) {
        let s = signals(i);
        assert_eq!(
            (s.n_samples(), s.sample_rate_hz),
            (len, 500.0),
            "{}",
            i.meta.trial_id
        );
        for (x, col) in s.data.iter().enumerate() {
            for (j, v) in col.iter().enumerate() {
                assert_eq!(
                    *v,
                    level(true, x, start + j),
                    "{} taxel {x} sample {j}",
                    i.meta.trial_id
                );
            }
        }
    }

    // Fixed windows: 1350 samples in windows of 1 s (500 samples).
    let r = run_graph(d.path(), &src("segment = \"fixed\"\nwindow_ms = 1000.0")).unwrap();
    let lens: Vec<usize> = items(&r, "src").iter().map(|i| signals(i).n_samples()).collect();
    assert_eq!(lens, [500, 500, 350]);

    // The log never falls to 1.0 V: the error gives the levels it saw.
    let e = source_error(
        d.path(),
        &src("segment = \"contact\"\ncontact_v = 1.0\nrelease_v = 1.2")
            .replace("[stages.src]\ntype = \"signal_file\"\n", ""),
    );
    assert!(
        e.contains("log.csv") && e.contains("found no trial") && e.contains("ranged 1.7"),
        "{e}"
    );
    // A sensor whose output rises with pressure: the same log mirrored
    // (5.05 - v: 1.75 on the object, 3.3 in contact) gives the same trials.
    let mirrored: String = std::fs::read_to_string(d.path().join("log.csv"))
        .unwrap()
        .lines()
        .enumerate()
        .map(|(i, l)| match i {
            0 => format!("{l}\n"),
            _ => {
                let mut f = l.split(',');
                let t = f.next().unwrap_or_default().to_string();
                let vals: Vec<String> = f
                    .map(|v| format!("{}", 5.05 - v.parse::<f64>().unwrap()))
                    .collect();
                format!("{t},{}\n", vals.join(","))
            }
        })
        .collect();
    std::fs::write(d.path().join("log.csv"), mirrored).unwrap();
    let rises = "segment = \"contact\"\ncontact_polarity = \"rises\"\ncontact_v = 2.3\nrelease_v = 2.1";
    let r = run_graph(d.path(), &src(rises)).unwrap();
    let it = items(&r, "src");
    let lens: Vec<usize> = it.iter().map(|i| signals(i).n_samples()).collect();
    assert_eq!(lens, on_at.iter().map(|&(_, len)| len).collect::<Vec<_>>());
    assert_eq!(signals(&it[1]).data[2][7], 5.05 - level(true, 2, on_at[1].0 + 7));
    let e = source_error(
        d.path(),
        &src("segment = \"contact\"\ncontact_polarity = \"rises\"\ncontact_v = 4.0\nrelease_v = 3.9")
            .replace("[stages.src]\ntype = \"signal_file\"\n", ""),
    );
    assert!(
        e.contains("highest taxel ranged 1.75") && e.contains("or over contact_v = 4"),
        "{e}"
    );
    // Keys: the hysteresis (either way), a fixed window's length.
    let g = |extra: &str| palpate_core::load_str(&src(extra), "g.toml", "g", &Default::default());
    let e = g("segment = \"contact\"\ncontact_v = 2.0\nrelease_v = 2.0")
        .unwrap_err()
        .to_string();
    assert!(e.contains("release_v") && e.contains("above contact_v"), "{e}");
    let e = g("segment = \"contact\"\ncontact_polarity = \"rises\"\ncontact_v = 2.0\nrelease_v = 2.2")
        .unwrap_err()
        .to_string();
    assert!(e.contains("release_v") && e.contains("below contact_v"), "{e}");
    let e = g("segment = \"fixed\"").unwrap_err().to_string();
    assert!(e.contains("window_ms") && e.contains("required"), "{e}");
}

/// Runs a one-source graph expecting an error; returns its message.
fn source_error(dir: &Path, keys: &str) -> String {
    match run_graph(dir, &format!("[stages.src]\ntype = \"signal_file\"\n{keys}\n")) {
        Ok(_) => panic!("expected an error for {keys}"),
        Err(e) => e,
    }
}

#[test]
fn bad_inputs_give_clear_errors() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    // NaN in a CSV: file, line, column.
    let mut s = csv_trial(0, 4, 6, 1000.0);
    s = s.replacen(&format!(",{}", val(0, 2, 3)), ",NaN", 1);
    std::fs::write(p.join("nan.csv"), s).unwrap();
    let e = source_error(p, &format!("path = \"nan.csv\"\n{GRID2}"));
    assert!(
        e.contains("nan.csv") && e.contains("line 5") && e.contains("taxel_2") && e.contains("not finite"),
        "{e}"
    );
    // Infinite sample in an NPY: the index.
    let mut v = flat(&[0], 4, 10, false);
    v[7 * 4 + 1] = f64::INFINITY;
    std::fs::write(p.join("inf.npy"), npy_bytes(&[10, 4], &v).unwrap()).unwrap();
    let e = source_error(
        p,
        &format!("path = \"inf.npy\"\nsample_rate_hz = 1000.0\n{GRID2}"),
    );
    assert!(
        e.contains("inf.npy") && e.contains("[7, 1]") && e.contains("not finite"),
        "{e}"
    );
    // NaN in a MAT stack: MATLAB subscripts.
    let mut m = matlab_stack(&[0, 1], 4, 5);
    m[5 * 4 + 2 * 5 + 3] = f64::NAN; // data(4, 3, 2)
    std::fs::write(p.join("nan.mat"), mat_v5(&[("data", vec![5, 4, 2], m)])).unwrap();
    let e = source_error(
        p,
        &format!("path = \"nan.mat\"\nsample_rate_hz = 1000.0\n{GRID2}"),
    );
    assert!(e.contains("nan.mat") && e.contains("data(4, 3, 2)"), "{e}");
    // Truncated CSV (last row cut).
    let s = csv_trial(0, 4, 6, 1000.0);
    std::fs::write(p.join("cut.csv"), &s[..s.len() - 12]).unwrap();
    let e = source_error(p, &format!("path = \"cut.csv\"\n{GRID2}"));
    assert!(
        e.contains("cut.csv") && e.contains("line 7") && e.contains("truncated"),
        "{e}"
    );
    // Truncated NPY, MAT, NPZ.
    let b = npy_bytes(&[10, 4], &flat(&[0], 4, 10, false)).unwrap();
    std::fs::write(p.join("cut.npy"), &b[..b.len() - 5]).unwrap();
    let e = source_error(
        p,
        &format!("path = \"cut.npy\"\nsample_rate_hz = 1000.0\n{GRID2}"),
    );
    assert!(e.contains("cut.npy") && e.contains("truncated"), "{e}");
    let b = mat_v5(&[("data", vec![5, 4], matlab_stack(&[0], 4, 5))]);
    std::fs::write(p.join("cut.mat"), &b[..b.len() - 20]).unwrap();
    let e = source_error(
        p,
        &format!("path = \"cut.mat\"\nsample_rate_hz = 1000.0\n{GRID2}"),
    );
    assert!(e.contains("cut.mat") && e.contains("truncated"), "{e}");
    npz(
        &p.join("whole.npz"),
        &[("a", vec![10, 4], flat(&[0], 4, 10, false))],
        true,
    );
    let b = std::fs::read(p.join("whole.npz")).unwrap();
    std::fs::write(p.join("cut.npz"), &b[..b.len() / 2]).unwrap();
    let e = source_error(
        p,
        &format!("path = \"cut.npz\"\nsample_rate_hz = 1000.0\n{GRID2}"),
    );
    assert!(e.contains("cut.npz") && e.contains("truncated"), "{e}");
    // Wrong shape: 5 taxels for a 4-taxel layout.
    std::fs::write(p.join("wide.npy"), npy_bytes(&[10, 5], &[0.0; 50]).unwrap()).unwrap();
    let e = source_error(
        p,
        &format!("path = \"wide.npy\"\nsample_rate_hz = 1000.0\n{GRID2}"),
    );
    assert!(
        e.contains("wide.npy") && e.contains("wrong shape") && e.contains("4 taxels"),
        "{e}"
    );
    // Unknown column.
    std::fs::write(
        p.join("extra.csv"),
        "taxel_0,taxel_1,taxel_2,taxel_3,pressure\n1,2,3,4,5\n",
    )
    .unwrap();
    let e = source_error(
        p,
        &format!("path = \"extra.csv\"\nsample_rate_hz = 1000.0\n{GRID2}"),
    );
    assert!(
        e.contains("extra.csv") && e.contains("unknown column `pressure`"),
        "{e}"
    );
    // Mismatched sample rates across files.
    std::fs::create_dir(p.join("mix")).unwrap();
    std::fs::write(p.join("mix/a.csv"), csv_trial(0, 4, 6, 1000.0)).unwrap();
    std::fs::write(p.join("mix/b.csv"), csv_trial(0, 4, 6, 500.0)).unwrap();
    let e = source_error(p, &format!("path = \"mix/*.csv\"\n{GRID2}"));
    assert!(
        e.contains("mismatched sample rates") && e.contains("a.csv") && e.contains("b.csv"),
        "{e}"
    );
    // A file's rate against the key.
    let e = source_error(
        p,
        &format!("path = \"mix/b.csv\"\nsample_rate_hz = 1000.0\n{GRID2}"),
    );
    assert!(e.contains("b.csv") && e.contains("500"), "{e}");
    // No rate at all.
    std::fs::write(p.join("ok.npy"), npy_bytes(&[10, 4], &[0.5; 40]).unwrap()).unwrap();
    let e = source_error(p, &format!("path = \"ok.npy\"\n{GRID2}"));
    assert!(e.contains("sample_rate_hz"), "{e}");
    // A missing row (time column not uniform).
    let s = csv_trial(0, 4, 6, 1000.0);
    let lines: Vec<&str> = s.lines().collect();
    let gap = [&lines[..3], &lines[4..]].concat().join("\n") + "\n";
    std::fs::write(p.join("gap.csv"), gap).unwrap();
    let e = source_error(p, &format!("path = \"gap.csv\"\n{GRID2}"));
    assert!(e.contains("gap.csv") && e.contains("uniform"), "{e}");
    // Duplicate trial ids (same stem, same folder).
    std::fs::create_dir(p.join("dup")).unwrap();
    std::fs::write(p.join("dup/r.csv"), csv_trial(0, 4, 6, 1000.0)).unwrap();
    std::fs::write(
        p.join("dup/r.npy"),
        npy_bytes(&[6, 4], &flat(&[0], 4, 6, false)).unwrap(),
    )
    .unwrap();
    let e = source_error(
        p,
        &format!("path = \"dup/r.*\"\nsample_rate_hz = 1000.0\n{GRID2}"),
    );
    assert!(e.contains("`r`") && e.contains("unique"), "{e}");
    // A sidecar that misses a trial, or names one that is not there.
    std::fs::create_dir(p.join("same")).unwrap();
    std::fs::write(p.join("same/a.csv"), csv_trial(0, 4, 6, 1000.0)).unwrap();
    std::fs::write(p.join("same/b.csv"), csv_trial(1, 4, 6, 1000.0)).unwrap();
    std::fs::write(p.join("side.csv"), "trial,angle_deg\na,10\n").unwrap();
    let e = source_error(
        p,
        &format!("path = \"same/*.csv\"\nlabels = \"side.csv\"\n{GRID2}"),
    );
    assert!(e.contains("no entry") && e.contains("`b`"), "{e}");
    std::fs::write(p.join("side2.csv"), "trial,angle_deg\na,10\nb,20\nz,30\n").unwrap();
    let e = source_error(
        p,
        &format!("path = \"same/a.csv\"\nlabels = \"side2.csv\"\n{GRID2}"),
    );
    assert!(
        e.contains("side2.csv") && e.contains("do not hold") && e.contains("`z`"),
        "{e}"
    );
    // A missing file or unmatched pattern is a load error naming the key.
    let e = source_error(p, "path = \"nothing/*.csv\"");
    assert!(e.contains("path") && e.contains("matched no file"), "{e}");
}

fn structured_npy(records: &[(i16, i16, i64, i8)]) -> Vec<u8> {
    let mut header =
        "{'descr': [('x', '<i2'), ('y', '<i2'), ('t', '<i8'), ('p', '|i1')], 'fortran_order': False, 'shape': (N,), }"
            .replace('N', &records.len().to_string());
    while !(10 + header.len() + 1).is_multiple_of(64) {
        header.push(' ');
    }
    header.push('\n');
    let mut b = b"\x93NUMPY\x01\x00".to_vec();
    b.extend((header.len() as u16).to_le_bytes());
    b.extend(header.as_bytes());
    for &(x, y, t, p) in records {
        b.extend(x.to_le_bytes());
        b.extend(y.to_le_bytes());
        b.extend(t.to_le_bytes());
        b.extend(p.to_le_bytes());
    }
    b
}

#[test]
fn spike_files_map_events_to_taxels() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    // CSV, µs, x = column, y = row on a 2 x 3 grid.
    std::fs::write(p.join("ev.csv"), "x,y,t,p\n2,1,1500,1\n0,0,250,0\n1,1,250,1\n").unwrap();
    // Structured NPY as event tools save it.
    std::fs::write(
        p.join("ev2.npy"),
        structured_npy(&[(0, 1, 3000, 1), (2, 0, 1000, -1)]),
    )
    .unwrap();
    std::fs::write(
        p.join("lab.toml"),
        "[trials.ev]\nangle_deg = 60.0\nduration_ms = 10.0\n[trials.ev2]\nangle_deg = 60.0\n",
    )
    .unwrap();
    let grid = r#"layout = { kind = "grid", rows = 2, cols = 3, pitch_mm = 3.0, taxel_mm = 2.0 }"#;
    let r = run_graph(
        p,
        &format!("[stages.src]\ntype = \"spike_file\"\npaths = [\"ev.csv\", \"ev2.npy\"]\nlabels = \"lab.toml\"\n{grid}\n"),
    )
    .unwrap();
    let it = items(&r, "src");
    let a = spikes(&it[0]);
    let ev: Vec<(u32, f64)> = a.events.iter().map(|e| (e.taxel, e.t_ms)).collect();
    assert_eq!(ev, vec![(0, 0.25), (4, 0.25), (5, 1.5)]);
    assert_eq!(a.duration_ms, 10.0, "sidecar duration");
    let b = spikes(&it[1]);
    let ev: Vec<(u32, f64)> = b.events.iter().map(|e| (e.taxel, e.t_ms)).collect();
    assert_eq!(ev, vec![(2, 1.0), (3, 3.0)]);
    assert_eq!(b.duration_ms, 4.0, "last event + 1 ms");
    assert_eq!((it[0].meta.group, it[1].meta.group), (0, 1));
    // Polarity filter and ms unit with a first-event origin.
    let r = run_graph(
        p,
        &format!("[stages.src]\ntype = \"spike_file\"\npath = \"ev.csv\"\npolarity = \"on\"\ntime_unit = \"ms\"\ntime_origin = \"first_event\"\n{grid}\n"),
    )
    .unwrap();
    let a = spikes(&items(&r, "src")[0]);
    let ev: Vec<(u32, f64)> = a.events.iter().map(|e| (e.taxel, e.t_ms)).collect();
    assert_eq!(ev, vec![(4, 0.0), (5, 1250.0)]);
    // A delimiter ending every line (a logger's `v,` per value), in the
    // events and in a CSV label file: the same events and labels.
    std::fs::write(p.join("ev3.csv"), "x,y,t,p,\n2,1,1500,1,\n0,0,250,0,\n").unwrap();
    std::fs::write(p.join("lab.csv"), "trial,angle_deg,\nev3,30,\n").unwrap();
    let r = run_graph(
        p,
        &format!("[stages.src]\ntype = \"spike_file\"\npath = \"ev3.csv\"\nlabels = \"lab.csv\"\n{grid}\n"),
    )
    .unwrap();
    let c = &items(&r, "src")[0];
    let ev: Vec<(u32, f64)> = spikes(c).events.iter().map(|e| (e.taxel, e.t_ms)).collect();
    assert_eq!(ev, vec![(0, 0.25), (5, 1.5)]);
    assert_eq!(c.meta.label.angle_deg, Some(30.0));
    std::fs::write(p.join("lab.csv"), "trial,angle_deg,\nev3,30,x\n").unwrap();
    let e = run_graph(
        p,
        &format!("[stages.src]\ntype = \"spike_file\"\npath = \"ev3.csv\"\nlabels = \"lab.csv\"\n{grid}\n"),
    )
    .err()
    .unwrap();
    assert!(e.contains("lab.csv, line 2") && e.contains("`x`"), "{e}");
    // Errors: outside the grid, non-integer coordinates, NaN time.
    for (body, want) in [
        ("x,y,t,\n0,0,1,2\n", "a value `2` in the last column"),
        ("x,y,t\n3,0,5\n", "outside the 2 x 3 grid"),
        ("x,y,t\n0.5,0,5\n", "whole numbers"),
        ("x,y,t\n0,0,nan\n", "not finite"),
        ("x,y,t,q\n0,0,1,1\n", "unknown column `q`"),
    ] {
        std::fs::write(p.join("bad.csv"), body).unwrap();
        let e = run_graph(
            p,
            &format!("[stages.src]\ntype = \"spike_file\"\npath = \"bad.csv\"\n{grid}\n"),
        )
        .err()
        .unwrap();
        assert!(e.contains("bad.csv") && e.contains(want), "{e}");
    }
}

#[test]
fn signals_round_trip_through_csv_and_npy_sinks() {
    for format in ["csv", "npy"] {
        let d = tempfile::tempdir().unwrap();
        let p = d.path();
        std::fs::create_dir(p.join("in")).unwrap();
        for t in 0..3 {
            std::fs::write(p.join(format!("in/edge-{t}.csv")), csv_trial(t, 4, 30, 1000.0)).unwrap();
        }
        std::fs::write(
            p.join("lab.csv"),
            "trial,angle_deg,group,speed_mm_s\nedge-0,10,5,2.5\nedge-1,20,,\nedge-2,10,,4\n",
        )
        .unwrap();
        let out = p.join("out").display().to_string();
        let r = run_graph(
            p,
            &format!(
                "[run]\nout = \"{out}\"\n[stages.src]\ntype = \"signal_file\"\npath = \"in/*.csv\"\nlabels = \"lab.csv\"\n{GRID2}\n\
                 [stages.save]\ntype = \"write_signals\"\ninputs = [\"src\"]\nformat = \"{format}\"\n"
            ),
        )
        .unwrap();
        let first = items(&r, "src").to_vec();
        assert!(p.join(format!("out/save/edge-1.{format}")).is_file());
        // No `layout` or `sample_rate_hz` key: the sidecar the sink wrote
        // declares the 2 x 2 array and the rate (NPY files carry none).
        let back_graph = |layout: &str| {
            run_graph(
                p,
                &format!(
                    "[stages.back]\ntype = \"signal_file\"\npath = \"out/save/*.{format}\"\nlabels = \"out/save/labels.toml\"\n{layout}\n"
                ),
            )
        };
        // The same rate set again is fine; another one names the label file.
        assert!(back_graph("sample_rate_hz = 1000.0").is_ok());
        let e = back_graph("sample_rate_hz = 500.0").unwrap_err();
        assert!(
            e.contains("500") && e.contains("labels.toml") && e.contains("1000"),
            "{e}"
        );
        let r2 = back_graph("").unwrap();
        let back = items(&r2, "back");
        assert_eq!(signals(&back[0]).layout, signals(&first[0]).layout);
        // The same layout set again is fine; another one names the sidecar.
        assert!(back_graph(GRID2).is_ok());
        let e =
            back_graph(r#"layout = { kind = "grid", rows = 1, cols = 4, pitch_mm = 3.0, taxel_mm = 2.0 }"#)
                .unwrap_err();
        assert!(
            e.contains("`layout`") && e.contains("labels.toml") && e.contains("a 2 x 2 grid"),
            "{e}"
        );
        assert_eq!(back.len(), first.len());
        for (a, b) in first.iter().zip(back) {
            assert_eq!(a.meta.trial_id, b.meta.trial_id);
            assert_eq!(a.meta.label, b.meta.label);
            assert_eq!(a.meta.group, b.meta.group);
            assert_eq!(a.meta.speed_mm_s, b.meta.speed_mm_s);
            let (sa, sb) = (signals(a), signals(b));
            assert_eq!(sa.data, sb.data, "{format}: same bits");
            assert!((sa.sample_rate_hz - sb.sample_rate_hz).abs() < 1e-9);
        }
        assert_eq!(back[0].meta.group, 5);
        assert_eq!(back[2].meta.group, 1);
        let speeds: Vec<Option<f64>> = back.iter().map(|i| i.meta.speed_mm_s).collect();
        assert_eq!(speeds, [Some(2.5), None, Some(4.0)]);
    }
}

#[test]
fn spikes_round_trip_through_csv_and_npy_sinks() {
    for format in ["csv", "npy"] {
        // Whole microseconds: the NPY default is tonic's int64 microsecond times.
        let d = tempfile::tempdir().unwrap();
        let p = d.path();
        let mut s = String::from("trial,x,y,t,angle_deg\n");
        for (k, (x, y, t)) in [(0, 0, 100.0), (1, 1, 2000.0), (1, 0, 77.0), (0, 1, 999.0)]
            .iter()
            .enumerate()
        {
            s.push_str(&format!(
                "{},{x},{y},{t},{}\n",
                if k < 2 { "a" } else { "b" },
                if k < 2 { 30 } else { 60 }
            ));
        }
        std::fs::write(p.join("ev.csv"), s).unwrap();
        let out = p.join("out").display().to_string();
        let r = run_graph(
            p,
            &format!(
                "[run]\nout = \"{out}\"\n[stages.src]\ntype = \"spike_file\"\npath = \"ev.csv\"\nduration_ms = 5.0\n{GRID2}\n\
                 [stages.save]\ntype = \"write_spikes\"\ninputs = [\"src\"]\nformat = \"{format}\"\n"
            ),
        )
        .unwrap();
        let first = items(&r, "src").to_vec();
        let r2 = run_graph(
            p,
            // No `layout` key: the sidecar declares the 2 x 2 grid (read as
            // the default 4 x 4, every event would land on the wrong taxel).
            &format!("[stages.back]\ntype = \"spike_file\"\npath = \"out/save/*.{format}\"\nlabels = \"out/save/labels.toml\"\n"),
        )
        .unwrap();
        let back = items(&r2, "back");
        assert_eq!(back.len(), 2);
        for (a, b) in first.iter().zip(back) {
            assert_eq!(a.meta.trial_id, b.meta.trial_id);
            assert_eq!(a.meta.label, b.meta.label);
            assert_eq!(spikes(a), spikes(b), "{format}");
        }
    }
}

#[test]
fn images_and_estimates_sinks_write_what_they_get() {
    use palpate_core::{
        BuildContext, ClassScore, Estimate, SinkContext, SinkInput, SpikeImages, Stage, StageConfig,
        TrialMeta,
    };
    let d = tempfile::tempdir().unwrap();
    let ctx = BuildContext {
        stage_id: "s".into(),
        seed: 0,
        out_dir: d.path().into(),
        base_dir: d.path().into(),
    };
    let meta = |id: &str, a: Option<f64>| {
        Arc::new(TrialMeta {
            trial_id: id.into(),
            label: palpate_core::Label {
                stimulus: Stimulus::Edge,
                angle_deg: a,
            },
            ..Default::default()
        })
    };
    let counts: Vec<f64> = (0..3 * 4).map(|i| (i * 7 % 5) as f64).collect();
    let img = Item {
        meta: meta("t/1", Some(45.0)),
        payload: SpikeImages {
            layout: TaxelLayout::Grid {
                rows: 2,
                cols: 2,
                pitch_mm: 3.0,
                taxel_mm: 2.0,
            },
            window_ms: 100.0,
            hop_ms: 10.0,
            n_frames: 3,
            counts: counts.clone(),
        }
        .into(),
    };
    for format in ["npy", "csv"] {
        let cfg: Box<dyn StageConfig> =
            toml::from_str(&format!("[write_images]\nformat = \"{format}\"\ndir = \"img\"\n")).unwrap();
        let Ok(Stage::Sink(sink)) = cfg.build(&ctx) else {
            panic!("a sink")
        };
        let items = [img.clone()];
        let rep = sink
            .consume(
                &[SinkInput {
                    stage_id: "bin",
                    items: &items,
                }],
                &SinkContext {
                    stage_id: "w",
                    out_dir: d.path(),
                },
            )
            .unwrap();
        assert!(rep.files.iter().any(|f| f.ends_with(format!("img/t_1.{format}"))));
        let path = d.path().join(format!("img/t_1.{format}"));
        if format == "npy" {
            let a = read_npy_plain(&std::fs::read(&path).unwrap(), "img").unwrap();
            assert_eq!(a.shape, vec![3, 2, 2]);
            assert_eq!(a.data, counts);
        } else {
            let text = std::fs::read_to_string(&path).unwrap();
            let lines: Vec<&str> = text.lines().collect();
            assert_eq!(lines[0], "frame,t_start_ms,taxel_0,taxel_1,taxel_2,taxel_3");
            let row2: Vec<f64> = lines[3].split(',').map(|c| c.parse().unwrap()).collect();
            assert_eq!(row2[..2], [2.0, 20.0]);
            assert_eq!(row2[2..], counts[8..12]);
        }
    }
    // Estimates: two estimators, one "no edge".
    let est = |a: Option<f64>, s: &[(f64, f64)]| Estimate {
        angle_deg: a,
        class_deg: a,
        scores: s
            .iter()
            .map(|&(angle_deg, score)| ClassScore { angle_deg, score })
            .collect(),
        best_frame: a.map(|_| 4),
        decision_time_ms: Some(512.5),
        uncertain: false,
    };
    let wss = vec![
        Item {
            meta: meta("a", Some(45.0)),
            payload: est(Some(45.0), &[(40.0, 0.2), (45.0, 0.9)]).into(),
        },
        Item {
            meta: meta("b", None),
            payload: est(None, &[(40.0, 0.1), (45.0, 0.05)]).into(),
        },
    ];
    let ann = vec![Item {
        meta: meta("a", Some(45.0)),
        payload: est(Some(50.0), &[(50.0, 1.0)]).into(),
    }];
    for format in ["csv", "npy"] {
        let cfg: Box<dyn StageConfig> =
            toml::from_str(&format!("[write_estimates]\nformat = \"{format}\"\n")).unwrap();
        let Ok(Stage::Sink(sink)) = cfg.build(&ctx) else {
            panic!("a sink")
        };
        sink.consume(
            &[
                SinkInput {
                    stage_id: "wss",
                    items: &wss,
                },
                SinkInput {
                    stage_id: "ann",
                    items: &ann,
                },
            ],
            &SinkContext {
                stage_id: "est",
                out_dir: d.path(),
            },
        )
        .unwrap();
        if format == "csv" {
            let text = std::fs::read_to_string(d.path().join("est/estimates.csv")).unwrap();
            let lines: Vec<&str> = text.lines().collect();
            assert!(lines[0].ends_with("score_40,score_45,score_50"), "{}", lines[0]);
            assert_eq!(lines[2], "wss,b,edge,,0,,,,512.5,0.1,0.05,");
            assert_eq!(lines[3], "ann,a,edge,45,0,50,50,4,512.5,,,1");
        } else {
            let a = read_npy_plain(&std::fs::read(d.path().join("est/estimates.npy")).unwrap(), "e").unwrap();
            assert_eq!(a.shape, vec![3, 9]);
            assert_eq!(a.data[..6], [45.0, 0.0, 45.0, 45.0, 4.0, 512.5]);
            assert!(a.data[9 + 2].is_nan(), "no edge is NaN");
            assert_eq!(a.data[9 + 6], 0.1);
            let c = read_npy_plain(
                &std::fs::read(d.path().join("est/estimates_classes.npy")).unwrap(),
                "c",
            )
            .unwrap();
            assert_eq!(c.data, vec![40.0, 45.0, 50.0]);
        }
    }
    // A sink folder outside the output is refused.
    let cfg: Box<dyn StageConfig> = toml::from_str("[write_signals]\ndir = \"../x\"\n").unwrap();
    let e = cfg.build(&ctx).err().unwrap();
    assert_eq!(e.key.as_deref(), Some("dir"));
}

#[test]
fn every_io_stage_is_registered() {
    palpate_stages::link();
    for name in [
        "signal_file",
        "spike_file",
        "write_signals",
        "write_spikes",
        "write_images",
        "write_estimates",
    ] {
        assert!(palpate_core::registry::find(name).is_some(), "{name}");
    }
    let _ = load_str; // keeps the import list honest across edits
}

#[test]
fn read_signal_files_works_outside_a_graph_and_spikes_on_explicit_layouts() {
    use palpate_stages::io::signal_file::{read_signal_files, SignalFileConfig};
    let d = tempfile::tempdir().unwrap();
    std::fs::write(d.path().join("a.csv"), csv_trial(0, 16, 20, 1000.0)).unwrap();
    let cfg = SignalFileConfig {
        path: Some("a.csv".into()),
        ..Default::default()
    };
    let t = read_signal_files(&cfg, d.path()).unwrap();
    assert_eq!(t.len(), 1);
    assert_eq!(t[0].0.trial_id, "a");
    assert_data(&t[0].1, 0, 20);
    let bad = SignalFileConfig {
        path: Some("missing.csv".into()),
        ..Default::default()
    };
    assert!(read_signal_files(&bad, d.path())
        .unwrap_err()
        .message
        .contains("missing.csv"));
    // Spikes on a skin that is not a grid: x is the taxel index, y must be 0.
    std::fs::write(d.path().join("s.csv"), "x,y,t\n2,0,1000\n0,0,2000\n").unwrap();
    let pos = r#"layout = { kind = "positions", positions_mm = [[0.0, 0.0], [2.0, 0.0], [1.0, 1.7]], taxel_mm = 1.0 }"#;
    let r = run_graph(
        d.path(),
        &format!("[stages.src]\ntype = \"spike_file\"\npath = \"s.csv\"\n{pos}\n"),
    )
    .unwrap();
    let ev: Vec<(u32, f64)> = spikes(&items(&r, "src")[0])
        .events
        .iter()
        .map(|e| (e.taxel, e.t_ms))
        .collect();
    assert_eq!(ev, vec![(2, 1.0), (0, 2.0)]);
    std::fs::write(d.path().join("s.csv"), "x,y,t\n1,1,1000\n").unwrap();
    let e = run_graph(
        d.path(),
        &format!("[stages.src]\ntype = \"spike_file\"\npath = \"s.csv\"\n{pos}\n"),
    )
    .err()
    .unwrap();
    assert!(e.contains("y must be 0"), "{e}");
}

/// Two sinks whose files share a name (`mae` writes `m_trials.csv` for a
/// sink `m`, and a sink `m_trials` writes `m_trials.csv` too): the run fails
/// naming both and the file, where before the second silently overwrote the
/// first's table.
#[test]
fn two_sinks_writing_one_file_fail_the_run() {
    let d = tempfile::tempdir().unwrap();
    let scene = concat!(env!("CARGO_MANIFEST_DIR"), "/../graphs/scenes/ideal.toml");
    let chain = format!(
        "[stages.scene]\ntype = \"scene\"\nfile = \"{scene}\"\nangles = [30, 60]\ntrials_per_angle = 1\n\
         [stages.filter]\ntype = \"lowpass\"\ninputs = [\"scene\"]\n\
         [stages.norm]\ntype = \"normalize\"\ninputs = [\"filter\"]\n\
         [stages.drive]\ntype = \"drive\"\ninputs = [\"norm\"]\n\
         [stages.enc]\ntype = \"izhikevich\"\ninputs = [\"drive\"]\n\
         [stages.bins]\ntype = \"bin\"\ninputs = [\"enc\"]\n\
         [stages.wss]\ntype = \"wss\"\ninputs = [\"bins\"]\nangles = [30, 60]\n\
         [stages.m]\ntype = \"mae\"\ninputs = [\"wss\"]\n"
    );
    let e = match run_graph(
        d.path(),
        &format!("{chain}[stages.m_trials]\ntype = \"mae\"\ninputs = [\"wss\"]\n"),
    ) {
        Ok(_) => panic!("two sinks writing m_trials.csv ran"),
        Err(e) => e,
    };
    assert!(
        e.contains("`m`") && e.contains("`m_trials`") && e.contains("m_trials.csv"),
        "{e}"
    );
    // Other ids: the same run goes through.
    run_graph(
        d.path(),
        &format!("{chain}[stages.other]\ntype = \"mae\"\ninputs = [\"wss\"]\n"),
    )
    .unwrap();
}
