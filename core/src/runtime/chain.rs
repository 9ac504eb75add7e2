//! Depth-first execution of a graph's per-trial part.
//!
//! The *per-trial set* of a graph is every source, and every map and
//! model-based (untrained) estimator whose inputs are all in the set: the
//! stages whose output for trial `t` depends only on trial `t`. Its connected
//! components are the *chains* (the quickstart has one: scene -> filter ->
//! norm -> drive -> enc -> bins -> wss). A model-based estimator is fitted
//! once, on nothing, before its chain runs, and predicts each trial inside
//! it. A chain runs one trial at a time from its sources to its last stage,
//! trials in parallel, except that the part from its first estimator on
//! runs for a block of `TRIAL_BLOCK` trials after the part before it has
//! run for each of them (so that consecutive estimates find the estimator's
//! working set, WSS's template spectra, still in cache), and keeps only the
//! outputs something outside the chain
//! reads (a trained estimator or a sink: estimates or spike images, never
//! signals). Each trial's intermediate payloads are
//! dropped as soon as their last reader in the chain is done, so peak memory
//! is O(threads x one trial's chain) plus the kept outputs, instead of
//! O(trials x samples) for every stage's output at once.
//!
//! Under a protocol that scores a subset of the trials (hold-out,
//! train/test), a model-based estimator in a chain skips the trials the
//! protocol does not score, and so does every stage below it on those
//! trials: the same estimates as stage-at-a-time, where the estimator gets
//! the held-out trials only ([`crate::protocol::folds`]).
//!
//! Results do not change: every per-trial computation is the same pure
//! function of (config, inputs, seed) with the same seeds, gathered in trial
//! order. When several trials fail, the first failing trial in trial order is
//! reported (with the first stage, in graph order, that failed on it).

use super::{check_unique_ids, tick, timed, with_provenance, RunError, RunOptions, StageTiming};
use crate::graph::Graph;
use crate::payload::Payload;
use crate::payload::{Item, Provenance, TrialMeta};
use crate::stage::{derive_seed, settings_json, FitContext, Model, Stage, TrialContext};
use rayon::prelude::*;
use std::time::Duration;

/// One connected component of the per-trial set.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(super) struct Chain {
    /// Graph node indices, in the graph's execution order.
    pub nodes: Vec<usize>,
}

/// What running a chain gives, per chain node (same positions as [`Chain::nodes`]).
pub(super) struct ChainOutput {
    /// The node's items in trial order, for nodes that are kept.
    pub items: Vec<Option<Vec<Item>>>,
    /// The node's timing (`total` = the sum of its per-trial times).
    pub timings: Vec<StageTiming>,
}

/// The chains of a graph, in the order of their first node.
pub(super) fn chains(graph: &Graph) -> Vec<Chain> {
    components(graph, &per_trial_set(graph))
}

/// The connected components of the nodes marked in `member` (linked by
/// input edges between members), in the order of their first node, each
/// in the graph's execution order.
pub(super) fn components(graph: &Graph, member: &[bool]) -> Vec<Chain> {
    let n = graph.nodes.len();
    let mut parent: Vec<usize> = (0..n).collect();
    fn find(p: &mut [usize], mut x: usize) -> usize {
        while p[x] != x {
            p[x] = p[p[x]];
            x = p[x];
        }
        x
    }
    for &i in &graph.order {
        if member[i] {
            for &j in graph.input_index[i].iter().filter(|&&j| member[j]) {
                let (a, b) = (find(&mut parent, i), find(&mut parent, j));
                parent[a] = b;
            }
        }
    }
    let mut by_root: Vec<Option<usize>> = vec![None; n];
    let mut out: Vec<Chain> = Vec::new();
    for &i in &graph.order {
        if !member[i] {
            continue;
        }
        let r = find(&mut parent, i);
        match by_root[r] {
            Some(c) => out[c].nodes.push(i),
            None => {
                by_root[r] = Some(out.len());
                out.push(Chain { nodes: vec![i] });
            }
        }
    }
    out
}

/// True for every node in the per-trial set (see the module docs).
pub(super) fn per_trial_set(graph: &Graph) -> Vec<bool> {
    let mut per_trial = vec![false; graph.nodes.len()];
    for &i in &graph.order {
        per_trial[i] = match &graph.nodes[i].stage {
            Stage::Source(_) => true,
            Stage::Map(_) => graph.input_index[i].iter().all(|&j| per_trial[j]),
            Stage::Estimator(e) => !e.trained() && graph.input_index[i].iter().all(|&j| per_trial[j]),
            Stage::Sink(_) => false,
        };
    }
    per_trial
}

/// The progress label of a chain: its first and last stage (`scene .. bins`).
pub(super) fn label(graph: &Graph, nodes: &[usize]) -> String {
    match (nodes.first(), nodes.last()) {
        (Some(&a), Some(&b)) if a != b => format!("{} .. {}", graph.nodes[a].id, graph.nodes[b].id),
        (Some(&a), _) => graph.nodes[a].id.clone(),
        _ => String::new(),
    }
}

/// One trial's payload from source or map `i`, timed: a source produces
/// the trial `meta` lists, a map processes `inputs` (whose first item's
/// metadata is `meta`); the seed derives from the stage and trial ids.
/// Shared by the depth-first runners, with and without a cache.
pub(super) fn trial_payload(
    graph: &Graph,
    i: usize,
    meta: &TrialMeta,
    inputs: &[&Item],
) -> Result<(Payload, Duration), RunError> {
    let id = graph.nodes[i].id.as_str();
    let ctx = TrialContext {
        stage_id: id,
        meta,
        seed: derive_seed(graph.run.seed, &[id, &meta.trial_id]),
    };
    let (payload, dt) = match &graph.nodes[i].stage {
        Stage::Source(src) => timed(|| src.produce(&ctx)),
        Stage::Map(map) => timed(|| map.process(inputs, &ctx)),
        _ => {
            return Err(RunError::new(
                id,
                None,
                "not a per-trial stage (internal planning error)",
            ))
        }
    };
    let payload = payload.map_err(|e| RunError::new(id, Some(&meta.trial_id), e.message))?;
    Ok((payload, dt))
}

/// For each node, whether its output must outlive the trial: something outside
/// the per-trial set reads it, or the caller keeps every output.
pub(super) fn kept(graph: &Graph, keep_all: bool) -> Vec<bool> {
    let per_trial = per_trial_set(graph);
    let mut keep = vec![keep_all; graph.nodes.len()];
    for (i, inputs) in graph.input_index.iter().enumerate() {
        if !per_trial[i] {
            for &j in inputs {
                keep[j] = true;
            }
        }
    }
    keep
}

/// Trials whose estimates run back to back (see `run_chain`): the first
/// estimate of a block finds the estimator's working set cold, the other
/// seven warm; eight lab trials' spike images are ~2 MB a thread.
const TRIAL_BLOCK: usize = 8;

/// A trial's kept items (by chain position) and every chain node's time on
/// it (`None`: the node skipped the trial, see the module docs).
type TrialOutcome = Result<(Vec<Option<Item>>, Vec<Option<Duration>>), RunError>;

/// Runs a chain depth-first, trial by trial (see the module docs).
pub(super) fn run_chain(
    graph: &Graph,
    chain: &Chain,
    keep: &[bool],
    opts: &RunOptions<'_>,
) -> Result<ChainOutput, RunError> {
    let seed = graph.run.seed;
    let len = chain.nodes.len();
    let mut pos: Vec<Option<usize>> = vec![None; graph.nodes.len()];
    for (p, &i) in chain.nodes.iter().enumerate() {
        pos[i] = Some(p);
    }
    let at = |j: usize| -> Result<usize, RunError> {
        pos[j].ok_or_else(|| {
            RunError::new(
                &graph.nodes[j].id,
                None,
                "a per-trial stage reads a stage outside its chain (internal ordering error)",
            )
        })
    };
    let mut readers = vec![0usize; len];
    for &i in &chain.nodes {
        for &j in &graph.input_index[i] {
            readers[at(j)?] += 1;
        }
    }
    let provs: Vec<Provenance> = chain
        .nodes
        .iter()
        .map(|&i| {
            let node = &graph.nodes[i];
            Provenance {
                stage: node.id.clone(),
                type_name: node.type_name.clone(),
                settings: settings_json(node.config.as_ref()),
            }
        })
        .collect();

    // Every source's trials; several sources in one chain must agree.
    let mut metas: Vec<Option<Vec<TrialMeta>>> = vec![None; len];
    let mut first: Option<usize> = None;
    for (p, &i) in chain.nodes.iter().enumerate() {
        let Stage::Source(src) = &graph.nodes[i].stage else {
            continue;
        };
        let id = graph.nodes[i].id.as_str();
        let mut m = src.trials().map_err(|e| RunError::new(id, None, e.message))?;
        for (k, meta) in m.iter_mut().enumerate() {
            meta.index = k;
        }
        check_unique_ids(id, &m)?;
        if let Some(f) = first {
            let other = metas[f].as_deref().unwrap_or_default();
            let same = other.len() == m.len() && other.iter().zip(&m).all(|(a, b)| a.trial_id == b.trial_id);
            if !same {
                return Err(RunError::new(
                    id,
                    None,
                    format!(
                        "carries different trials from source `{}`, and a per-trial stage reads both; \
                         a per-trial stage needs inputs from the same trials",
                        graph.nodes[chain.nodes[f]].id
                    ),
                ));
            }
        } else {
            first = Some(p);
        }
        metas[p] = Some(m);
    }
    let n_trials = first.and_then(|f| metas[f].as_ref()).map_or(0, Vec::len);

    // Under a hold-out or train/test split a model-based estimator is scored
    // on the held-out trials only, as stage-at-a-time (`protocol::folds`):
    // it skips the others, and so does every stage of the trial below it.
    // The split reads only labels and conditions, which the sources list
    // before anything runs.
    let mut scored: Option<Vec<bool>> = None;
    if graph.run.protocol.scores_a_subset() {
        if let Some(&e) = chain
            .nodes
            .iter()
            .find(|&&i| matches!(graph.nodes[i].stage, Stage::Estimator(_)))
        {
            let listed: Vec<&TrialMeta> = first
                .and_then(|f| metas[f].as_ref())
                .into_iter()
                .flatten()
                .collect();
            let folds = crate::protocol::folds_of(false, &graph.run.protocol, &listed)
                .map_err(|msg| RunError::new(&graph.nodes[e].id, None, msg))?;
            let mut mask = vec![false; n_trials];
            for t in folds.into_iter().flat_map(|(_, test)| test) {
                mask[t] = true;
            }
            scored = Some(mask);
        }
    }

    // Model-based estimators fit once, on nothing (fold 0, as in a batch run).
    let mut models: Vec<Option<Box<dyn Model>>> = Vec::with_capacity(len);
    let mut fit_times: Vec<Option<Duration>> = vec![None; len];
    for (p, &i) in chain.nodes.iter().enumerate() {
        let Stage::Estimator(est) = &graph.nodes[i].stage else {
            models.push(None);
            continue;
        };
        let id = graph.nodes[i].id.as_str();
        let fctx = FitContext {
            stage_id: id,
            fold: 0,
            seed: derive_seed(seed, &[id, "fold0"]),
        };
        let (model, dt) = timed(|| est.fit(&[], &fctx));
        let model = model.map_err(|e| RunError::new(id, None, format!("fitting fold 0: {}", e.message)))?;
        models.push(Some(model));
        fit_times[p] = Some(dt);
    }
    let label = label(graph, &chain.nodes);
    if let Some(p) = opts.progress {
        p.start(&label, n_trials);
    }

    // Chain positions `..first_estimator` run trial by trial, then
    // `first_estimator..` for the block's trials back to back (between two
    // estimates a lab trial's signal stages write ~11 MB, which evicts WSS's
    // template spectra from L3). The second part is a suffix of the graph order, so a
    // trial's first failing stage in graph order is still the one reported.
    // What it reads waits for the block: spike images in the usual chain (a
    // signal only if a signal stage follows the first estimator).
    let first_estimator = chain
        .nodes
        .iter()
        .position(|&i| matches!(graph.nodes[i].stage, Stage::Estimator(_)))
        .unwrap_or(len);
    // One trial's state between the two parts.
    struct State {
        slots: Vec<Option<Item>>,
        left: Vec<usize>,
        /// Each position's time on the trial; `None` where the trial is
        /// skipped: an estimator on a trial it does not score, and every
        /// stage that reads a skipped one.
        times: Vec<Option<Duration>>,
    }
    let step = |t: usize, p: usize, st: &mut State| -> Result<(), RunError> {
        let State { slots, left, times } = st;
        let i = chain.nodes[p];
        let node = &graph.nodes[i];
        let id = node.id.as_str();
        super::interrupted(opts, id)?;
        let unscored = matches!(node.stage, Stage::Estimator(_)) && scored.as_ref().is_some_and(|m| !m[t]);
        let mut skip = unscored;
        for &j in &graph.input_index[i] {
            skip |= times[at(j)?].is_none();
        }
        // Frees what no later stage of this trial reads (unless kept).
        let release = |slots: &mut [Option<Item>], left: &mut [usize]| -> Result<(), RunError> {
            for &j in &graph.input_index[i] {
                let q = at(j)?;
                left[q] -= 1;
                if left[q] == 0 && !keep[j] {
                    slots[q] = None;
                }
            }
            Ok(())
        };
        if skip {
            times[p] = None;
            return release(slots, left);
        }
        let (item, dt) = match &node.stage {
            Stage::Source(_) => {
                let meta = metas[p]
                    .as_ref()
                    .and_then(|m| m.get(t))
                    .ok_or_else(|| RunError::new(id, None, "source without trials (internal error)"))?;
                let (payload, dt) = trial_payload(graph, i, meta, &[])?;
                (with_provenance(meta, &provs[p], payload), dt)
            }
            Stage::Map(_) => {
                let mut items: Vec<&Item> = Vec::with_capacity(graph.input_index[i].len());
                for &j in &graph.input_index[i] {
                    let item = slots[at(j)?].as_ref().ok_or_else(|| {
                        RunError::new(
                            id,
                            None,
                            format!(
                                "input `{}` has no output (internal ordering error)",
                                graph.nodes[j].id
                            ),
                        )
                    })?;
                    items.push(item);
                }
                let meta = &items[0].meta;
                if let Some(k) = items.iter().position(|it| it.meta.trial_id != meta.trial_id) {
                    return Err(super::mixed_trials(graph, id, i, k));
                }
                let (payload, dt) = trial_payload(graph, i, meta, &items)?;
                (with_provenance(meta, &provs[p], payload), dt)
            }
            Stage::Estimator(_) => {
                let input = graph.input_index[i]
                    .first()
                    .ok_or_else(|| RunError::new(id, None, "an estimator without input (internal error)"))?;
                let item = slots[at(*input)?].as_ref().ok_or_else(|| {
                    RunError::new(id, None, "input has no output (internal ordering error)")
                })?;
                let model = models[p]
                    .as_ref()
                    .ok_or_else(|| RunError::new(id, None, "estimator not fitted (internal error)"))?;
                let ctx = TrialContext {
                    stage_id: id,
                    meta: &item.meta,
                    seed: derive_seed(seed, &[id, &item.meta.trial_id]),
                };
                let (est, dt) = timed(|| model.predict(item, &ctx));
                let est = est.map_err(|e| RunError::new(id, Some(&item.meta.trial_id), e.message))?;
                (with_provenance(&item.meta, &provs[p], Payload::from(est)), dt)
            }
            Stage::Sink(_) => {
                return Err(RunError::new(
                    id,
                    None,
                    "a sink in a per-trial chain (internal error)",
                ))
            }
        };
        times[p] = Some(dt);
        release(slots, left)?;
        if readers[p] > 0 || keep[i] {
            slots[p] = Some(item);
        }
        Ok(())
    };
    let one_block = |b: usize| -> Vec<TrialOutcome> {
        let trials = b * TRIAL_BLOCK..((b + 1) * TRIAL_BLOCK).min(n_trials);
        let states: Vec<Result<State, RunError>> = trials
            .clone()
            .map(|t| {
                let mut st = State {
                    slots: vec![None; len],
                    left: readers.clone(),
                    times: vec![Some(Duration::ZERO); len],
                };
                for p in 0..first_estimator {
                    step(t, p, &mut st)?;
                }
                Ok(st)
            })
            .collect();
        trials
            .zip(states)
            .map(|(t, st)| {
                let mut st = st?;
                for p in first_estimator..len {
                    step(t, p, &mut st)?;
                }
                tick(opts);
                for (slot, &i) in st.slots.iter_mut().zip(&chain.nodes) {
                    if !keep[i] {
                        *slot = None;
                    }
                }
                Ok((st.slots, st.times))
            })
            .collect()
    };
    let done: Vec<TrialOutcome> = (0..n_trials.div_ceil(TRIAL_BLOCK))
        .into_par_iter()
        .map(one_block)
        .collect::<Vec<_>>()
        .into_iter()
        .flatten()
        .collect();
    if let Some(p) = opts.progress {
        p.finish(&label);
    }

    let mut items: Vec<Option<Vec<Item>>> = chain
        .nodes
        .iter()
        .map(|&i| keep[i].then(|| Vec::with_capacity(n_trials)))
        .collect();
    let mut timings: Vec<StageTiming> = chain
        .nodes
        .iter()
        .map(|&i| StageTiming {
            id: graph.nodes[i].id.clone(),
            type_name: graph.nodes[i].type_name.clone(),
            role: graph.nodes[i].stage.role(),
            per_trial: Vec::with_capacity(n_trials),
            ..StageTiming::default()
        })
        .collect();
    for r in done {
        let (slots, times) = r?;
        for (p, slot) in slots.into_iter().enumerate() {
            if let (Some(list), Some(item)) = (items[p].as_mut(), slot) {
                list.push(item);
            }
        }
        for (p, dt) in times.into_iter().enumerate() {
            timings[p].per_trial.extend(dt);
        }
    }
    for (t, fit) in timings.iter_mut().zip(fit_times) {
        t.fits.extend(fit);
        t.total = t.per_trial.iter().sum::<Duration>() + fit.unwrap_or_default();
    }
    Ok(ChainOutput { items, timings })
}
