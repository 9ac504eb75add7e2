//! Where the user guide (the mdBook in `docs/guide/`) documents each built-in
//! stage type, and the metric definitions `palpate run --explain` prints.
//!
//! The guide is the reference a user reads; `palpate stages TYPE` names the
//! page and section of the type, and the tests below check that every
//! registered built-in type has one and that the section exists, so the
//! pointer cannot go stale silently.

/// The guide's source folder, relative to the repository's root.
pub const GUIDE_SRC: &str = "docs/guide/src";

/// The guide page (relative to [`GUIDE_SRC`]) documenting each built-in stage
/// type; the section is the type's name (`## \`type\``, anchor `#type`).
const PAGES: &[(&str, &str)] = &[
    ("scene", "stages/sources.md"),
    ("daq", "stages/sources.md"),
    ("signal_file", "stages/sources.md"),
    ("spike_file", "stages/sources.md"),
    ("image_file", "stages/sources.md"),
    ("union", "stages/sources.md"),
    ("lowpass", "stages/signals.md"),
    ("normalize", "stages/signals.md"),
    ("derivative", "stages/signals.md"),
    ("drive", "stages/signals.md"),
    ("izhikevich", "stages/encoders.md"),
    ("lif", "stages/encoders.md"),
    ("bin", "stages/spikes.md"),
    ("jitter", "stages/spikes.md"),
    ("crop", "stages/spikes.md"),
    ("subarea", "stages/spikes.md"),
    ("dead_taxels", "stages/spikes.md"),
    ("wss", "stages/estimators.md"),
    ("ann", "stages/estimators.md"),
    ("edbn", "stages/estimators.md"),
    ("svm", "stages/estimators.md"),
    ("random_forest", "stages/estimators.md"),
    ("knn", "stages/estimators.md"),
    ("logistic", "stages/estimators.md"),
    ("mae", "stages/sinks.md"),
    ("confusion", "stages/sinks.md"),
    ("raster_plot", "stages/sinks.md"),
    ("image_strip", "stages/sinks.md"),
    ("write_signals", "stages/sinks.md"),
    ("write_spikes", "stages/sinks.md"),
    ("write_images", "stages/sinks.md"),
    ("write_estimates", "stages/sinks.md"),
    ("spike_timing", "stages/sinks.md"),
    ("signal_levels", "stages/sinks.md"),
];

/// The trained baselines share one section of the estimators page.
const SHARED: &[(&str, &str)] = &[
    ("ann", "trained-baselines-ann-edbn-svm-random_forest-knn-logistic"),
    (
        "edbn",
        "trained-baselines-ann-edbn-svm-random_forest-knn-logistic",
    ),
    ("svm", "trained-baselines-ann-edbn-svm-random_forest-knn-logistic"),
    (
        "random_forest",
        "trained-baselines-ann-edbn-svm-random_forest-knn-logistic",
    ),
    ("knn", "trained-baselines-ann-edbn-svm-random_forest-knn-logistic"),
    (
        "logistic",
        "trained-baselines-ann-edbn-svm-random_forest-knn-logistic",
    ),
    ("raster_plot", "raster_plot-and-image_strip"),
    ("image_strip", "raster_plot-and-image_strip"),
];

/// The guide page and anchor of a built-in stage type, e.g.
/// `docs/guide/src/stages/signals.md#lowpass`; `None` for a type the guide
/// does not know (a plugin's).
pub fn stage_page(type_name: &str) -> Option<String> {
    let page = PAGES.iter().find(|(t, _)| *t == type_name)?.1;
    let anchor = SHARED
        .iter()
        .find(|(t, _)| *t == type_name)
        .map_or(type_name, |(_, a)| a);
    Some(format!("{GUIDE_SRC}/{page}#{anchor}"))
}

/// The definitions behind a summary, printed by `palpate run --explain`
/// (the guide's "Metrics" page says the same at more length).
pub const EXPLAIN: &str = "\
Definitions (docs/guide/src/metrics.md has them at length):
  error        the angle between answer and true edge lines, degrees:
               d = |answer - true angle| mod 180, error = min(d, 180 - d)
               (170 for 10 is 20 off); within 0..90 simply |answer - true|.
  no edge      the estimator declined to answer: WSS when no frame has a spike or
               its best score is under `threshold`; a trained estimator when no
               frame of the trial is active. Left out of the MAE, counted wrong.
  accuracy     share of labelled trials answered within `correct_within_deg`
               (default 0: the exact class); 'N of M wrong' counts the others.
  MAE (SD)     mean absolute error over answered trials, and the population SD of
               those errors. With classes 5 deg apart errors are 0, 5, 10 ...:
               an SD several times the MAE means a few whole-class misses.
  largest per-class MAE
               the MAE of the worst true angle.
  MAE at A deg truth and answer binned into classes of width A from the smallest
               true angle; error = distance between the bins. A 5-degree miss
               costs 0 or A depending on the bin edges, so it can exceed the MAE.
  decision time
               median palpation an answer needed, ms from the edge's first contact
               with the array (from the trial's start when the crossing is not
               known). Batch WSS uses every frame, so its decision time is the rest
               of the trial: a length of data, not a compute time (see timing).
  SR           spike rate of a frame: its spike count over the trial's largest;
               WSS weights frames by 1 - SR (default), 1 or 1 + SR.
  confusion    row = true angle, column = answered class or 'no edge'; each cell
               is the share of its row, so rows sum to 100 %.
";

#[cfg(test)]
mod tests {
    use super::*;

    /// mdBook's anchor for a heading: lower case, spaces to `-`, other
    /// punctuation dropped (`_` and `-` kept).
    fn anchor(heading: &str) -> String {
        heading
            .trim()
            .to_lowercase()
            .chars()
            .filter_map(|c| match c {
                ' ' => Some('-'),
                c if c.is_alphanumeric() || c == '_' || c == '-' => Some(c),
                _ => None,
            })
            .collect()
    }

    #[test]
    fn every_built_in_stage_type_has_a_guide_section_that_exists() {
        crate::link();
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
        for reg in crate::core::registry::registrations() {
            let t = crate::core::registry::stage_doc(reg).type_name;
            let link = stage_page(&t).unwrap_or_else(|| panic!("stage type `{t}` has no guide page"));
            let (file, want) = link.split_once('#').unwrap();
            let text = std::fs::read_to_string(root.join(file)).unwrap_or_else(|e| panic!("{file}: {e}"));
            let anchors: Vec<String> = text
                .lines()
                .filter_map(|l| l.strip_prefix("## "))
                .map(anchor)
                .collect();
            assert!(
                anchors.iter().any(|a| a == want),
                "{file} has no section #{want} for `{t}`; sections: {anchors:?}"
            );
        }
        assert_eq!(stage_page("no_such_type"), None);
    }

    #[test]
    fn explain_defines_every_term_of_the_summary() {
        for term in [
            "no edge",
            "accuracy",
            "MAE (SD)",
            "decision time",
            "SR",
            "MAE at A deg",
        ] {
            assert!(EXPLAIN.contains(term), "{term}");
        }
    }
}
