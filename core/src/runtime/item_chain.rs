//! Depth-first execution of the item-level stages under a sweep cache.
//!
//! Under a [`Cache`] the item-level stages (every source, and every map whose
//! inputs are all item-level, `runtime/items.rs`) are planned trial by
//! trial: each trial of each stage is served from the cache, computed, or
//! left out (nobody reads it). This module runs that plan **one trial at a
//! time through a connected component of those stages** (a scene and the
//! signal chain below it), trials in parallel, instead of one stage at a
//! time over every trial. A trial's intermediate signals are dropped once
//! its last reader in the component is done, so peak memory is O(threads x
//! one trial's chain) plus what the cache keeps and the outputs a later
//! stage reads in full (the spike images a trained estimator or WSS takes),
//! not a whole stage's output and its input for every trial at once.
//!
//! Why: stage-at-a-time held two signal stages for every trial: a
//! two-point sweep of a WSS key on the quickstart peaked at 1.15 GB on the
//! 4 x 4 lab array (103 MB without the sweep) and 7.2 GB on an 8 x 8 array
//! (249 MB), and spent its extra time faulting in fresh pages and reading
//! signals back from memory (37.6 s against 11.9 s for one point on 8 x 8;
//! `/usr/bin/time`, 2026-12-01). A 16 x 16 array would not have fitted in
//! 24 GiB.
//!
//! What the cache sees is what it saw stage-at-a-time: the same trials
//! looked up (the plan does that before anything runs), the same trials
//! offered to it with the same costs, in the same order (per block of
//! [`CHUNK`] trials, stage by stage, trials in order), whatever the thread
//! count. Results do not change: each trial's payload is the same pure
//! function of its inputs, config and seed. When several trials fail, the
//! first failing trial in trial order is reported, with the first stage in
//! graph order that failed on it (as `chain` does).

use super::chain::trial_payload;
use super::{interrupted, tick, Cache, RunError, RunOptions, StageTiming};
use crate::graph::Graph;
use crate::payload::{Item, Payload, TrialMeta};
use crate::stage::Stage;
use rayon::prelude::*;
use std::sync::Arc;
use std::time::Duration;

use super::items::ItemPlan;

/// Trials run between two hand-overs to the cache: the computed payloads the
/// cache may keep wait for the end of their block, so a block bounds what is
/// held beyond the cache's own budget; fixed (not the thread count) so that
/// the cache sees the same sequence on any pool.
const CHUNK: usize = 32;

/// One item-level stage of a component, as the plan left it.
pub(super) struct ItemNode<'a> {
    /// Graph node index.
    pub node: usize,
    /// Its trial plan (keys, listed trials).
    pub plan: &'a ItemPlan,
    /// Each trial's metadata as its output carries it (provenance appended).
    pub metas: Arc<Vec<Arc<TrialMeta>>>,
    /// Each trial's hit: its payload and the time computing it took.
    pub hits: Vec<Option<(Payload, Duration)>>,
    /// Each trial's known time (from the run that computed it).
    pub known: Vec<Option<Duration>>,
    /// The stage-level timing of a run that computed every trial.
    pub stored: Option<StageTiming>,
    /// Which trials to compute.
    pub compute: Vec<bool>,
    /// The same trials' keys of each stage reading this one, when every
    /// reader is item-level (else empty: see [`Cache::covered`]).
    pub readers: Vec<&'a [u64]>,
    /// Whether every trial's item must outlive the component (a stage
    /// outside it reads this one, or the caller keeps every output).
    pub keep: bool,
}

/// What an item-level stage gave: its items by trial where kept (`None`
/// when not kept; a trial nobody wanted is `None` inside) and its timing.
pub(super) struct ItemDone {
    pub items: Option<Vec<Option<Item>>>,
    pub timing: StageTiming,
}

/// One trial through the component: per stage, the item kept for after the
/// component, the payload computed (when offered to the cache), the stage's time on the
/// trial (computed, or known from the run that computed it), whether it was
/// computed here, and its cost with everything upstream.
struct TrialRun {
    kept: Vec<Option<Item>>,
    computed: Vec<Option<Payload>>,
    own: Vec<Option<Duration>>,
    cost: Vec<Duration>,
}

/// Runs the component `nodes` (item-level stages in graph order, connected,
/// sharing their trials) depth-first under `cache` (see the module docs).
pub(super) fn run_component(
    graph: &Graph,
    mut nodes: Vec<ItemNode<'_>>,
    cache: &Cache,
    opts: &RunOptions<'_>,
) -> Result<Vec<ItemDone>, RunError> {
    let m = nodes.len();
    let n_trials = nodes.first().map_or(0, |c| c.plan.keys.len());
    let mut pos = vec![None; graph.nodes.len()];
    for (p, c) in nodes.iter().enumerate() {
        pos[c.node] = Some(p);
    }
    // Each stage's inputs by position; readers inside the component.
    let inputs: Vec<Vec<usize>> = nodes
        .iter()
        .map(|c| {
            graph.input_index[c.node]
                .iter()
                .map(|&j| {
                    pos[j].ok_or_else(|| {
                        RunError::new(
                            &graph.nodes[c.node].id,
                            None,
                            "an item-level stage reads a stage outside its component (internal planning error)",
                        )
                    })
                })
                .collect()
        })
        .collect::<Result<_, _>>()?;
    let mut readers = vec![0usize; m];
    for ins in &inputs {
        for &q in ins {
            readers[q] += 1;
        }
    }
    // Hits move into the trial that uses them.
    let mut hits: Vec<Vec<Option<Payload>>> = (0..n_trials).map(|_| vec![None; m]).collect();
    for (p, c) in nodes.iter_mut().enumerate() {
        for (t, h) in std::mem::take(&mut c.hits).into_iter().enumerate() {
            if let (Some(row), Some((payload, _))) = (hits.get_mut(t), h) {
                row[p] = Some(payload);
            }
        }
    }
    // Progress counts the trials some stage computes (the others are served).
    let todo = (0..n_trials)
        .filter(|&t| nodes.iter().any(|c| c.compute[t]))
        .count();
    let label = super::chain::label(graph, &nodes.iter().map(|c| c.node).collect::<Vec<_>>());
    if let (Some(p), true) = (opts.progress, todo > 0) {
        p.start(&label, todo);
    }

    // `offer[p]`: whether stage `p`'s computed payload of trial `t` is
    // offered to the cache (not covered by its readers' trials); decided
    // before the block runs, so that a payload the cache does not want is
    // dropped with the trial.
    let one_trial = |t: usize, mut hit: Vec<Option<Payload>>, offer: &[bool]| -> Result<TrialRun, RunError> {
        let mut slots: Vec<Option<Item>> = vec![None; m];
        let mut left = readers.clone();
        let mut run = TrialRun {
            kept: vec![None; m],
            computed: vec![None; m],
            own: vec![None; m],
            cost: vec![Duration::ZERO; m],
        };
        let mut computed_any = false;
        for (p, c) in nodes.iter().enumerate() {
            let node = &graph.nodes[c.node];
            let id = node.id.as_str();
            let meta = &c.metas[t];
            let item = if let Some(payload) = hit[p].take() {
                run.own[p] = c.known[t];
                Some(Item {
                    meta: meta.clone(),
                    payload,
                })
            } else if c.compute[t] {
                interrupted(opts, id)?;
                let (payload, dt) = match &node.stage {
                    Stage::Source(_) => trial_payload(graph, c.node, &c.plan.listed[t], &[])?,
                    _ => {
                        let mut items: Vec<&Item> = Vec::with_capacity(inputs[p].len());
                        for &q in &inputs[p] {
                            items.push(slots[q].as_ref().ok_or_else(|| {
                                RunError::new(
                                    id,
                                    Some(&meta.trial_id),
                                    format!(
                                        "input `{}` has no item for this trial (internal planning error)",
                                        graph.nodes[nodes[q].node].id
                                    ),
                                )
                            })?);
                        }
                        trial_payload(graph, c.node, &items[0].meta, &items)?
                    }
                };
                run.own[p] = Some(dt);
                run.computed[p] = offer[p].then(|| payload.clone());
                computed_any = true;
                Some(Item {
                    meta: meta.clone(),
                    payload,
                })
            } else {
                run.own[p] = c.known[t];
                None
            };
            run.cost[p] =
                run.own[p].unwrap_or_default() + inputs[p].iter().map(|&q| run.cost[q]).sum::<Duration>();
            // Frees what no later stage of this trial reads.
            for &q in &inputs[p] {
                left[q] -= 1;
                if left[q] == 0 {
                    slots[q] = None;
                }
            }
            if c.keep {
                run.kept[p] = item.clone();
            }
            if readers[p] > 0 {
                slots[p] = item;
            }
        }
        if computed_any {
            tick(opts);
        }
        Ok(run)
    };

    let mut items: Vec<Option<Vec<Option<Item>>>> = nodes
        .iter()
        .map(|c| c.keep.then(|| Vec::with_capacity(n_trials)))
        .collect();
    let mut own: Vec<Vec<Option<Duration>>> = vec![Vec::with_capacity(n_trials); m];
    let mut hits = hits.into_iter();
    for start in (0..n_trials).step_by(CHUNK) {
        let end = (start + CHUNK).min(n_trials);
        // A covered trial keeps its time alone: its readers' trials will be
        // served instead.
        let covered: Vec<Vec<bool>> = nodes
            .iter()
            .map(|c| {
                let readers: Vec<&[u64]> = c.readers.iter().map(|r| &r[start..end]).collect();
                cache.covered(&c.plan.keys[start..end], &readers)
            })
            .collect();
        let block: Vec<(usize, Vec<Option<Payload>>, Vec<bool>)> = (start..end)
            .zip(hits.by_ref())
            .map(|(t, h)| (t, h, covered.iter().map(|c| !c[t - start]).collect()))
            .collect();
        let done: Vec<Result<TrialRun, RunError>> = block
            .into_par_iter()
            .map(|(t, h, offer)| one_trial(t, h, &offer))
            .collect();
        let mut runs = Vec::with_capacity(done.len());
        for r in done {
            runs.push(r?);
        }
        // The cache sees the block stage by stage, trials in order.
        for (p, c) in nodes.iter().enumerate() {
            let batch: Vec<_> = runs
                .iter_mut()
                .enumerate()
                .filter(|(k, _)| c.compute[start + k])
                .map(|(k, r)| {
                    let dt = r.own[p].unwrap_or_default();
                    (c.plan.keys[start + k], r.computed[p].take(), dt, r.cost[p])
                })
                .collect();
            if !batch.is_empty() {
                cache.put_items(batch);
            }
        }
        for r in runs {
            for (p, item) in r.kept.into_iter().enumerate() {
                if let Some(list) = items[p].as_mut() {
                    list.push(item);
                }
            }
            for (list, d) in own.iter_mut().zip(r.own) {
                list.push(d);
            }
        }
    }
    if let (Some(p), true) = (opts.progress, todo > 0) {
        p.finish(&label);
    }

    let mut out = Vec::with_capacity(m);
    for ((c, items), own) in nodes.into_iter().zip(items).zip(own) {
        let node = &graph.nodes[c.node];
        let computed = c.compute.iter().filter(|&&x| x).count();
        let per_trial: Vec<Duration> = own.iter().map(|d| d.unwrap_or_default()).collect();
        let base = StageTiming {
            id: node.id.clone(),
            type_name: node.type_name.clone(),
            role: node.stage.role(),
            ..StageTiming::default()
        };
        let timing = if computed == 0 {
            // Nothing computed: the timing of the run that computed it all,
            // or the trials' own times.
            match c.stored {
                Some(t) => StageTiming {
                    id: base.id,
                    type_name: base.type_name,
                    role: base.role,
                    cached: true,
                    ..t
                },
                None => StageTiming {
                    total: per_trial.iter().sum(),
                    per_trial,
                    cached: true,
                    ..base
                },
            }
        } else {
            // The time spent here: the trials computed in this run.
            let total = c
                .compute
                .iter()
                .zip(&own)
                .filter(|(&x, _)| x)
                .map(|(_, d)| d.unwrap_or_default())
                .sum();
            let timing = StageTiming {
                total,
                per_trial,
                ..base
            };
            if computed == n_trials {
                cache.put_timing(c.plan.stage_key, timing.clone());
            }
            timing
        };
        out.push(ItemDone { items, timing });
    }
    Ok(out)
}
