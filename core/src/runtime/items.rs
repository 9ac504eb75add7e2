//! Trial-level keys for a sweep's cache.
//!
//! A stage key ([`super::stage_keys`]) follows every change of a stage's
//! config, so a sweep that shifts one condition of a two-condition scene
//! changes the scene's key and, through it, the keys of every stage below:
//! every point re-simulated and re-encoded the unchanged condition's trials
//! too (`graphs/shift/shift.toml`: 170 of 340 trials at each of its 7 points).
//!
//! The *item-level* stages (every source, and every map whose inputs are all
//! item-level) are therefore cached one trial at a time, each trial under
//! its own key:
//!
//! * a source's trial `t`: `H(seed, id, type, context, F_t, m_t)`, where
//!   `F_t` is the source's fingerprint of the trial
//!   ([`crate::stage::Source::trial_fingerprint`]; by default the stage's
//!   whole settings) and `m_t` the trial's metadata without provenance
//!   (id, index, label, group, crossing, conditions);
//! * a map's trial `t`: `H(seed, id, type, settings, context, m_t, k_1t ..
//!   k_nt)` over its inputs' keys of the same trial.
//!
//! `H` is [`derive_seed`]; `context` is the folder relative paths resolve
//! against and the evaluation protocol, as in the stage keys. A trial's
//! payload is a pure function of what its key covers (its stage's config,
//! its inputs' payloads, its metadata and its seed, which derives from the
//! graph's seed, the stage id and the trial id), so equal keys give equal
//! bits. Item metadata is rebuilt from the current run (provenance names
//! the current settings), never taken from the run that computed the
//! payload; it is built at the stage's turn and dropped with its output, as
//! without a cache.

use super::{check_unique_ids, mixed_trials, RunError};
use crate::graph::Graph;
use crate::payload::TrialMeta;
use crate::stage::{derive_seed, settings_json, Stage};
use std::sync::Arc;

/// One item-level stage's trials in this run.
pub(super) struct ItemPlan {
    /// The stage's key (its stage-level timing is kept under it).
    pub stage_key: u64,
    /// Each trial's key, in trial order.
    pub keys: Vec<u64>,
    /// The trials as the source upstream listed them (index filled, no
    /// provenance), shared by every stage below it: an item's metadata is
    /// its source's plus provenance. A source's `produce` is given these.
    pub listed: Arc<Vec<TrialMeta>>,
}

/// Whether each node is item-level: a source, or a map whose inputs are all
/// item-level.
pub(super) fn item_level(graph: &Graph) -> Vec<bool> {
    let mut level = vec![false; graph.nodes.len()];
    for &i in &graph.order {
        level[i] = match &graph.nodes[i].stage {
            Stage::Source(_) => true,
            Stage::Map(_) => graph.input_index[i].iter().all(|&j| level[j]),
            _ => false,
        };
    }
    level
}

/// The metadata a trial's key covers: everything but provenance.
fn meta_label(m: &TrialMeta) -> String {
    m.identity().to_string()
}

/// Every item-level stage's plan, by node (`None` for the others). Lists
/// each source's trials (a source that cannot list them, two trials that
/// share an id, or a map whose inputs carry different trials is the error
/// running the stage would give).
pub(super) fn plans(
    graph: &Graph,
    stage_keys: &[u64],
    context: &str,
) -> Result<Vec<Option<ItemPlan>>, RunError> {
    let level = item_level(graph);
    let seed = graph.run.seed;
    let mut out: Vec<Option<ItemPlan>> = (0..graph.nodes.len()).map(|_| None).collect();
    for &i in &graph.order {
        if !level[i] {
            continue;
        }
        let node = &graph.nodes[i];
        let id = node.id.as_str();
        let settings = settings_json(node.config.as_ref()).to_string();
        let plan = match &node.stage {
            Stage::Source(src) => {
                let mut listed = src.trials().map_err(|e| RunError::new(id, None, e.message))?;
                for (k, m) in listed.iter_mut().enumerate() {
                    m.index = k;
                }
                check_unique_ids(id, &listed)?;
                let keys = listed
                    .iter()
                    .map(|m| {
                        let f = src.trial_fingerprint(m).unwrap_or_else(|| settings.clone());
                        derive_seed(seed, &[id, &node.type_name, context, &f, &meta_label(m)])
                    })
                    .collect();
                ItemPlan {
                    stage_key: stage_keys[i],
                    keys,
                    listed: Arc::new(listed),
                }
            }
            _ => {
                let inputs = &graph.input_index[i];
                let first = out[inputs[0]].as_ref().ok_or_else(|| internal(graph, i))?;
                for (k, &j) in inputs.iter().enumerate().skip(1) {
                    let other = out[j].as_ref().ok_or_else(|| internal(graph, i))?;
                    let same = Arc::ptr_eq(&other.listed, &first.listed)
                        || other.listed.len() == first.listed.len()
                            && other
                                .listed
                                .iter()
                                .zip(first.listed.iter())
                                .all(|(a, b)| a.trial_id == b.trial_id);
                    if !same {
                        return Err(mixed_trials(graph, id, i, k));
                    }
                }
                let mut keys = Vec::with_capacity(first.listed.len());
                for (t, m) in first.listed.iter().enumerate() {
                    let label = meta_label(m);
                    let input_keys: Vec<String> = inputs
                        .iter()
                        .filter_map(|&j| out[j].as_ref().map(|p| p.keys[t].to_string()))
                        .collect();
                    let mut labels: Vec<&str> = vec![id, &node.type_name, &settings, context, &label];
                    labels.extend(input_keys.iter().map(String::as_str));
                    keys.push(derive_seed(seed, &labels));
                }
                ItemPlan {
                    stage_key: stage_keys[i],
                    keys,
                    listed: first.listed.clone(),
                }
            }
        };
        out[i] = Some(plan);
    }
    Ok(out)
}

fn internal(graph: &Graph, i: usize) -> RunError {
    RunError::new(
        &graph.nodes[i].id,
        None,
        "an input has no trial plan (internal ordering error)",
    )
}
