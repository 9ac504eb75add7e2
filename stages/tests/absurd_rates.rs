//! Absurd sample rates reaching the signal chain (from a `sample_rate_hz`
//! key, a label sidecar or a CSV time column): the low-pass refuses a rate
//! its f64 design cannot hold, naming itself and `cutoff_hz`, instead of
//! passing NaN on for the next stage to be blamed for (`stage norm ...
//! normalize: taxel 0, sample 0 is NaN`, from about 1e50 Hz up); messages
//! print such rates in a few characters, not 300 digits.

mod common;

use std::path::Path;

const TAXELS: usize = 16;
const ROWS: usize = 200;

/// A CSV recording `rec.csv` of the default 4 x 4 array in `dir`, with a
/// `time_ms` column of `i * step_ms` when given.
fn write_csv(dir: &Path, step_ms: Option<f64>) {
    let mut text = String::new();
    if step_ms.is_some() {
        text.push_str("time_ms,");
    }
    let names: Vec<String> = (0..TAXELS).map(|t| format!("taxel_{t}")).collect();
    text.push_str(&names.join(","));
    text.push('\n');
    for i in 0..ROWS {
        if let Some(s) = step_ms {
            text.push_str(&format!("{:e},", i as f64 * s));
        }
        let row: Vec<String> = (0..TAXELS)
            .map(|t| format!("{}", 1.5 + ((i + 3 * t) as f64 * 0.07).sin()))
            .collect();
        text.push_str(&row.join(","));
        text.push('\n');
    }
    std::fs::write(dir.join("rec.csv"), text).unwrap();
}

/// The quickstart's front end (10 Hz order-2 low-pass, then normalize) on
/// `rec.csv`, the source given `source_keys`; the run's error, if any.
fn run(dir: &Path, source_keys: &str, mode: &str) -> Result<(), String> {
    let graph = format!(
        r#"
[stages.src]
type = "signal_file"
path = "rec.csv"
{source_keys}

[stages.filter]
type = "lowpass"
inputs = ["src"]
cutoff_hz = 10.0
order = 2
mode = "{mode}"

[stages.norm]
type = "normalize"
inputs = ["filter"]
"#
    );
    let r = common::run_graph_file(dir, "g.toml", &graph)?;
    // A run that passes must pass finite numbers on.
    let norm = r.outputs.get("norm").expect("norm's outputs kept");
    for item in norm.iter() {
        let s = item.payload.signals().unwrap();
        assert!(s.data.iter().flatten().all(|v| v.is_finite()));
    }
    Ok(())
}

/// The refusal names the low-pass and its key, not the normalizer.
fn assert_named(what: &str, e: &str) {
    assert!(
        e.contains("cutoff_hz") && !e.contains("normalize") && !e.contains("NaN"),
        "{what}: {e}"
    );
    // Every number in exponent form: no line runs to hundreds of characters.
    assert!(e.lines().all(|l| l.len() < 400), "{what}: {e}");
}

#[test]
fn a_rate_the_lowpass_cannot_design_is_refused_by_the_lowpass() {
    let d = tempfile::tempdir().unwrap();
    let dir = d.path();
    for mode in ["zero_phase", "causal"] {
        write_csv(dir, None);
        // 1e12 Hz "worked" but was already wrong: a 10 Hz cutoff is 1e-11
        // of it, where the order-3+ designs round to unstable sections.
        for rate in ["1e12", "1e50", "1e300", "1.7976931348623157e308"] {
            let e = run(dir, &format!("sample_rate_hz = {rate}"), mode).unwrap_err();
            assert_named(&format!("{mode}, key {rate}"), &e);
            assert!(e.contains("1e-7"), "{e}");
        }
        // The rate from a label sidecar.
        std::fs::write(
            dir.join("labels.toml"),
            "sample_rate_hz = 1e300\n[trials.rec]\nangle_deg = 45.0\n",
        )
        .unwrap();
        let e = run(dir, "labels = \"labels.toml\"", mode).unwrap_err();
        assert_named(&format!("{mode}, sidecar"), &e);
        // The rate from a time column 1e-300 ms apart: 1e303 Hz.
        write_csv(dir, Some(1e-300));
        let e = run(dir, "", mode).unwrap_err();
        assert_named(&format!("{mode}, time_ms 1e-300"), &e);
        // 1e300 ms apart: 1e-297 Hz, under a 10 Hz cutoff's Nyquist bound;
        // the message's Nyquist frequency is ~5e-298, not 298 zeros.
        write_csv(dir, Some(1e300));
        let e = run(dir, "", mode).unwrap_err();
        assert_named(&format!("{mode}, time_ms 1e300"), &e);
        assert!(e.contains("Nyquist frequency") && e.contains("e-298 Hz"), "{e}");
        // At the bound (10 Hz is 1e-7 of 1e8 Hz) the chain runs, finite.
        write_csv(dir, None);
        run(dir, "sample_rate_hz = 1e8", mode).unwrap();
        run(dir, "sample_rate_hz = 1000.0", mode).unwrap();
    }
}

/// `rec.csv` at `rate` Hz through the drive and the encoder `encoder`: the
/// run's error, if any.
fn encode(dir: &Path, rate: &str, encoder: &str) -> Result<(), String> {
    let graph = format!(
        r#"
[stages.src]
type = "signal_file"
path = "rec.csv"
sample_rate_hz = {rate}

[stages.drive]
type = "drive"
inputs = ["src"]
kind = "sa_i"
gain = 20.0

[stages.enc]
type = "{encoder}"
inputs = ["drive"]
"#
    );
    common::run_graph_file(dir, "g.toml", &graph).map(|_| ())
}

#[test]
fn a_rate_that_makes_a_trial_absurdly_long_is_refused_by_the_encoder_not_an_abort() {
    // 200 samples at 1e-6 Hz last 2e8 s: 4e11 steps of 0.5 ms per taxel.
    // The step plan asked for 1.6 TB and the allocation failure aborted the
    // process (a Python session with it); now the encoder fails the trial.
    let d = tempfile::tempdir().unwrap();
    let dir = d.path();
    write_csv(dir, None);
    for encoder in ["izhikevich", "lif"] {
        for rate in ["1e-6", "1e-300", "0.001"] {
            let e = encode(dir, rate, encoder).unwrap_err();
            assert!(
                e.contains(encoder) && e.contains("over the cap of 268435456 neuron steps"),
                "{encoder} at {rate} Hz: {e}"
            );
            assert!(e.lines().all(|l| l.len() < 400), "{e}");
        }
        // 200 samples at 0.02 Hz are 10 000 s, 20 M steps x 16 taxels: over;
        // at 1 Hz, 200 s: 6.4 M neuron steps, well under: runs.
        assert!(encode(dir, "0.02", encoder).is_err());
        encode(dir, "1.0", encoder).unwrap();
    }
}
