//! Every error class of graph loading names its stage and line, and all errors
//! are gathered before failing.

mod common;
use common::load;
use palpate_core::{Diagnostic, Severity};

fn errors(text: &str) -> Vec<Diagnostic> {
    match load(text) {
        Ok(_) => panic!("graph loaded but should not have"),
        Err(e) => {
            e.0.into_iter()
                .filter(|d| d.severity == Severity::Error)
                .collect()
        }
    }
}

fn only(text: &str) -> Diagnostic {
    let e = errors(text);
    assert_eq!(e.len(), 1, "{e:#?}");
    e.into_iter().next().unwrap()
}

const GOOD: &str = r#"
[run]
seed = 3

[stages.src]
type = "t_source"
samples = 10

[stages.est]
type = "t_estimator"
inputs = ["src"]

[stages.sink]
type = "t_sink"
inputs = ["est"]
"#;

#[test]
fn a_good_graph_loads_in_order() {
    let g = load(GOOD).unwrap();
    assert!(g.warnings.is_empty(), "{:?}", g.warnings);
    let order: Vec<&str> = g.order.iter().map(|&i| g.nodes[i].id.as_str()).collect();
    assert_eq!(order, ["src", "est", "sink"]);
    assert_eq!(g.run.seed, 3);
    assert!(g.to_dot().contains("\"src\" -> \"est\""));
    assert!(g.to_mermaid().contains("src -->|analog signals| est"));
}

#[test]
fn unknown_type_lists_close_matches() {
    let d = only(&GOOD.replace("type = \"t_estimator\"", "type = \"t_estimater\""));
    assert_eq!(d.stage.as_deref(), Some("est"));
    assert_eq!(d.line, Some(10));
    assert!(
        d.message.contains("unknown stage type `t_estimater`"),
        "{}",
        d.message
    );
    assert!(d.message.contains("`t_estimator`"), "{}", d.message);
}

#[test]
fn unknown_key_names_key_and_line() {
    let d = only(&GOOD.replace("samples = 10", "samples = 10\nsampels = 3"));
    assert_eq!(
        (d.stage.as_deref(), d.key.as_deref(), d.line),
        (Some("src"), Some("sampels"), Some(8))
    );
    assert!(d.message.contains("did you mean `samples`"), "{}", d.message);
}

#[test]
fn missing_key_names_key_and_stage_line() {
    let d = only(&GOOD.replace("samples = 10\n", ""));
    assert_eq!(
        (d.stage.as_deref(), d.key.as_deref(), d.line),
        (Some("src"), Some("samples"), Some(5))
    );
    assert!(d.message.contains("missing key `samples`"), "{}", d.message);
}

#[test]
fn mistyped_key_names_key_and_line() {
    let d = only(&GOOD.replace("samples = 10", "samples = \"ten\""));
    assert_eq!(
        (d.stage.as_deref(), d.key.as_deref(), d.line),
        (Some("src"), Some("samples"), Some(7))
    );
    assert!(d.message.contains("invalid type"), "{}", d.message);
}

#[test]
fn out_of_range_value_names_key_and_line() {
    let d = only(&GOOD.replace("samples = 10", "samples = 0"));
    assert_eq!(
        (d.stage.as_deref(), d.key.as_deref(), d.line),
        (Some("src"), Some("samples"), Some(7))
    );
}

#[test]
fn unknown_input_names_stage_and_suggests() {
    let d = only(&GOOD.replace("inputs = [\"src\"]", "inputs = [\"scr\"]"));
    assert_eq!((d.stage.as_deref(), d.line), (Some("est"), Some(11)));
    assert!(
        d.message.contains("unknown input `scr`") && d.message.contains("`src`"),
        "{}",
        d.message
    );
}

#[test]
fn kind_mismatch_names_both_stages() {
    let text = GOOD.replace(
        "[stages.est]\ntype = \"t_estimator\"\ninputs = [\"src\"]",
        "[stages.spk]\ntype = \"t_spikes\"\ninputs = [\"src\"]\n\n[stages.est]\ntype = \"t_estimator\"\ninputs = [\"spk\"]",
    );
    let d = only(&text);
    assert_eq!((d.stage.as_deref(), d.line), (Some("est"), Some(15)));
    assert_eq!(
        d.message,
        "stage `est` takes analog signals but `spk` gives spike events"
    );
}

#[test]
fn cycle_names_its_stages() {
    let text = r#"
[stages.src]
type = "t_source"
samples = 4

[stages.a]
type = "t_scale"
inputs = ["b"]

[stages.b]
type = "t_scale"
inputs = ["a"]

[stages.est]
type = "t_estimator"
inputs = ["b"]

[stages.sink]
type = "t_sink"
inputs = ["est"]
"#;
    let d = only(text);
    assert_eq!((d.stage.as_deref(), d.line), (Some("a"), Some(6)));
    assert!(
        d.message.contains("cycle through stages `a` -> `b`"),
        "{}",
        d.message
    );
}

#[test]
fn no_source_is_an_error() {
    let text = r#"
[stages.a]
type = "t_scale"
inputs = ["a"]
"#;
    let e = errors(text);
    assert!(e.iter().any(|d| d.message.contains("no source")), "{e:#?}");
}

#[test]
fn unread_output_is_a_warning() {
    let g = load(&format!(
        "{GOOD}\n[stages.extra]\ntype = \"t_scale\"\ninputs = [\"src\"]\n"
    ))
    .unwrap();
    assert_eq!(g.warnings.len(), 1);
    let w = &g.warnings[0];
    assert_eq!(
        (w.severity, w.stage.as_deref(), w.line),
        (Severity::Warning, Some("extra"), Some(17))
    );
    assert!(w.message.contains("read by no stage"));
}

#[test]
fn five_mistakes_give_five_errors_each_with_stage_and_line() {
    let text = r#"
[run]
seed = 1

[stages.src]
type = "t_source"
samples = 10
colour = "red"

[stages.scale]
type = "t_scale"
inputs = ["src"]
factor = "big"

[stages.spk]
type = "t_spikes"
inputs = ["src"]

[stages.est]
type = "t_estimator"
inputs = ["spk"]

[stages.oops]
type = "t_sinc"
inputs = ["est"]

[stages.sink]
type = "t_sink"
inputs = ["estimate"]
"#;
    let e = errors(text);
    assert_eq!(e.len(), 5, "{e:#?}");
    for d in &e {
        assert!(d.stage.is_some() && d.line.is_some(), "{d:?}");
        let shown = d.to_string();
        assert!(shown.starts_with("test.toml:"), "{shown}");
        assert!(
            shown.contains(&format!("stage `{}`", d.stage.as_ref().unwrap())),
            "{shown}"
        );
    }
    let lines: Vec<usize> = e.iter().map(|d| d.line.unwrap()).collect();
    for want in [8, 13, 21, 24, 29] {
        assert!(lines.contains(&want), "line {want} missing from {lines:?}");
    }
}

#[test]
fn invalid_toml_reports_the_line() {
    let e = errors("[stages.src]\ntype = \"t_source\"\nsamples = = 3\n");
    assert_eq!(e[0].line, Some(3), "{e:?}");
}

#[test]
fn run_table_keys_are_checked() {
    let d = only(&GOOD.replace("seed = 3", "sead = 3"));
    assert_eq!((d.key.as_deref(), d.line), (Some("sead"), Some(3)));
    let d = only(&GOOD.replace("seed = 3", "seed = -3"));
    assert_eq!((d.key.as_deref(), d.line), (Some("seed"), Some(3)));
}

#[test]
fn set_overrides_keys_and_rejects_unknown_stages() {
    let opts = palpate_core::LoadOptions {
        overrides: vec![
            palpate_core::LoadOptions::parse_set("stages.src.samples=42").unwrap(),
            palpate_core::LoadOptions::parse_set("run.seed=9").unwrap(),
        ],
        ..Default::default()
    };
    let g = palpate_core::load_str(GOOD, "t.toml", "t", &opts).unwrap();
    assert_eq!(g.run.seed, 9);
    let json = serde_json::to_value(&g.nodes[0].config).unwrap();
    assert_eq!(json["t_source"]["samples"], 42);
    let opts = palpate_core::LoadOptions {
        overrides: vec![("stages.nope.samples".into(), toml::Value::Integer(1))],
        ..Default::default()
    };
    let e = palpate_core::load_str(GOOD, "t.toml", "t", &opts).unwrap_err();
    assert!(e.0[0].message.contains("does not declare"), "{e}");
}

/// `--set run.protocol=...` replaces the graph's protocol: merged into it,
/// another kind made two protocols at once (a load error pointing at the
/// file) and the same kind kept the old one's other keys.
#[test]
fn set_replaces_the_protocol_rather_than_merging_into_it() {
    let text = GOOD.replace(
        "seed = 3",
        "seed = 3\nprotocol = { hold_out = { test_share = 0.3, seed = 7 } }",
    );
    let load = |set: &str| {
        let opts = palpate_core::LoadOptions {
            overrides: vec![palpate_core::LoadOptions::parse_set(set).unwrap()],
            ..Default::default()
        };
        palpate_core::load_str(&text, "t.toml", "t", &opts).unwrap_or_else(|e| panic!("{set}: {e}"))
    };
    assert_eq!(
        load("run.protocol={ k_fold = { k = 5 } }").run.protocol,
        palpate_core::Protocol::KFold { k: 5, seed: 0 }
    );
    assert_eq!(
        load("run.protocol={ hold_out = { test_share = 0.5 } }")
            .run
            .protocol,
        palpate_core::Protocol::HoldOut {
            test_share: 0.5,
            seed: 0
        }
    );
    assert_eq!(
        load("run.protocol=leave_one_trial_out").run.protocol,
        palpate_core::Protocol::LeaveOneTrialOut
    );
}

#[test]
fn typetag_and_schema_registries_agree() {
    let schema: Vec<&str> = palpate_core::registry::registrations()
        .iter()
        .map(|r| r.type_name)
        .collect();
    let typetag = palpate_core::registry::typetag_names();
    assert_eq!(schema, typetag);
    for t in ["t_source", "t_scale", "t_spikes", "t_estimator", "t_sink"] {
        assert!(schema.contains(&t), "{t} not registered: {schema:?}");
    }
    let doc = palpate_core::registry::stage_doc(palpate_core::registry::find("t_scale").unwrap());
    assert_eq!(doc.keys[0].name, "factor");
    assert_eq!(doc.keys[0].default.as_deref(), Some("2.0"));
    assert!(doc.keys[0].doc.contains("Default 2"));
    let src = palpate_core::registry::stage_doc(palpate_core::registry::find("t_source").unwrap());
    let samples = src.keys.iter().find(|k| k.name == "samples").unwrap();
    assert_eq!(samples.default, None);
}

#[test]
fn graph_schema_describes_every_type_and_the_run_table() {
    let s = palpate_core::registry::graph_schema();
    let variants = s["properties"]["stages"]["additionalProperties"]["oneOf"]
        .as_array()
        .unwrap();
    let consts: Vec<&str> = variants
        .iter()
        .map(|v| v["properties"]["type"]["const"].as_str().unwrap())
        .collect();
    assert!(
        consts.contains(&"t_source") && consts.contains(&"t_sink"),
        "{consts:?}"
    );
    let src = variants
        .iter()
        .find(|v| v["properties"]["type"]["const"] == "t_source")
        .unwrap();
    assert_eq!(src["required"], serde_json::json!(["type", "samples"]));
    assert_eq!(src["additionalProperties"], false);
    assert!(s["properties"]["run"]["properties"]["seed"].is_object());
    // Every $ref resolves inside the document.
    fn refs(v: &serde_json::Value, out: &mut Vec<String>) {
        match v {
            serde_json::Value::Object(o) => o.iter().for_each(|(k, x)| {
                if k == "$ref" {
                    out.push(x.as_str().unwrap().to_string());
                } else {
                    refs(x, out)
                }
            }),
            serde_json::Value::Array(a) => a.iter().for_each(|x| refs(x, out)),
            _ => {}
        }
    }
    let mut all = Vec::new();
    refs(&s, &mut all);
    for r in all {
        assert!(s.pointer(r.trim_start_matches('#')).is_some(), "dangling {r}");
    }
}

#[test]
fn a_run_time_alias_stands_for_its_target_type() {
    use palpate_core::registry::{register_alias, Alias};
    let alias = Alias {
        target: "t_dynamic",
        name_key: "stage",
        keys_into: "config",
    };
    register_alias("my_gain", alias).unwrap();
    // A built-in name cannot be taken, nor can a missing target be named.
    assert!(register_alias("t_scale", alias).unwrap_err().contains("built-in"));
    assert!(register_alias(
        "x",
        Alias {
            target: "nope",
            ..alias
        }
    )
    .is_err());
    let direct = GOOD.replace(
        "[stages.est]",
        "[stages.gain]\ntype = \"t_dynamic\"\ninputs = [\"src\"]\nstage = \"my_gain\"\nconfig = { factor = 3.0 }\n\n[stages.est]",
    )
    .replace("inputs = [\"src\"]\n\n[stages.sink]", "inputs = [\"gain\"]\n\n[stages.sink]");
    let via_alias = GOOD
        .replace(
            "[stages.est]",
            "[stages.gain]\ntype = \"my_gain\"\ninputs = [\"src\"]\nfactor = 3.0\n\n[stages.est]",
        )
        .replace(
            "inputs = [\"src\"]\n\n[stages.sink]",
            "inputs = [\"gain\"]\n\n[stages.sink]",
        );
    let a = load(&direct).unwrap();
    let b = load(&via_alias).unwrap();
    let gain = |g: &palpate_core::Graph| {
        let n = g.nodes.iter().find(|n| n.id == "gain").unwrap();
        (n.type_name.clone(), format!("{:?}", n.config))
    };
    assert_eq!(gain(&a), gain(&b));
    assert_eq!(gain(&b).0, "t_dynamic");
    // A key the run-time stage does not have is named, on its stage.
    let d = only(&via_alias.replace("factor = 3.0", "factr = 3.0"));
    assert_eq!(d.stage.as_deref(), Some("gain"));
    assert!(d.message.contains("factr"), "{}", d.message);
}

#[test]
fn a_seed_takes_the_whole_u64_range_and_a_wrong_one_says_what_a_seed_is() {
    let with = |seed: &str| GOOD.replace("seed = 3", &format!("seed = {seed}"));
    assert_eq!(
        load(&with("9223372036854775807")).unwrap().run.seed,
        i64::MAX as u64
    );
    // Above TOML's integers, as a string of digits.
    assert_eq!(
        load(&with("\"18446744073709551615\"")).unwrap().run.seed,
        u64::MAX
    );
    assert_eq!(load(&with("\"7\"")).unwrap().run.seed, 7);
    for bad in [
        "-1",
        "\"18446744073709551616\"",
        "\"12a\"",
        "\"+5\"",
        "\"\"",
        "1.5",
    ] {
        let d = only(&with(bad));
        assert!(
            d.message.contains("a seed is a whole number") || d.message.contains("whole number from 0"),
            "{bad}: {d}"
        );
    }
    // The value `--set`, a sweep and `daq run` write for a seed reads back.
    for s in [0, 3, i64::MAX as u64, i64::MAX as u64 + 1, u64::MAX] {
        let v = palpate_core::graph::seed_value(s);
        assert_eq!(load(&with(&v.to_string())).unwrap().run.seed, s);
    }
}
