//! Classification trees (CART, Breiman et al. 1984) grown for the
//! `random_forest` baseline, as scikit-learn's `RandomForestClassifier` grows
//! them.
//!
//! Each tree is fitted on a bootstrap sample of the `n` training rows (`n`
//! draws with replacement, kept as a multiplicity per distinct row). A node
//! is split on the best of `m` features drawn without replacement from the
//! row's `dim` (more are drawn, in the same random order, while none of them
//! can split the node, as scikit-learn does), at the threshold that
//! minimises the weighted Gini impurity of the children:
//!
//! ```text
//! N_L (1 − Σ_c p_Lc²) + N_R (1 − Σ_c p_Rc²)  =  N − (S_L / N_L + S_R / N_R),   S = Σ_c n_c²
//! ```
//!
//! (`n_c` bootstrap-weighted class counts), over thresholds halfway between
//! consecutive distinct values of the node's rows, each child keeping at
//! least `min_samples_leaf` distinct rows. A node becomes a leaf when it is
//! pure, at `max_depth`, or when no feature splits it; it predicts its
//! majority class (ties: the lower class index).
//!
//! # Growing: ranks instead of per-node value sorts
//!
//! The split search needs, per drawn feature, the node's rows in ascending
//! order of value, swept once while `S_L`, `S_R` are updated in O(1) per row
//! (`(n + w)² − n² = w (2n + w)` for a row of multiplicity `w`). Sorting the
//! `(value, row)` pairs at every node (the first version) cost
//! `O(m · n log n)` per node, and gathering `x[row · dim + f]` from the
//! row-major matrix missed the cache on every row.
//!
//! Instead, [`Prepared`] replaces, once per forest (all trees share it), each
//! feature's values by their *rank* among that feature's distinct values,
//! ordered as `f64::total_cmp` orders them (a hash table numbers the distinct
//! bit patterns in one pass, then the few distinct values are sorted), and
//! stores the ranks feature-major: the column a node reads is contiguous and
//! small. At a node, the drawn feature's ranks are gathered for the node's
//! rows and ordered by a counting sort over the feature's ranks (or, when the
//! feature has more than four distinct values per row of the node, a
//! comparison sort of `rank << 32 | row` keys), and the sweep runs over that
//! order: `O(m · (n + R))` per node for `R` distinct values, where the value
//! sort was `O(m · n log n)`.
//!
//! This gives the same trees, bit for bit, as sorting the values (the
//! reference kept in the tests): every quantity the sweep compares depends
//! only on the *set* of rows left of a boundary between two distinct values
//! — `S_L`, `S_R`, `N_L`, the count of distinct rows (`min_samples_leaf`) are
//! exact integers, the scores the same `f64` expression of them — and a
//! boundary is a candidate under the same test as before (`next > v`, in
//! `f64`, on the ranks' values, so `-0.0` and `0.0`, distinct in total order,
//! still do not split), in the same ascending order, features in the same
//! drawn order, ties to the first. The generator is drawn from in the same
//! order (bootstrap, then per node the partial Fisher–Yates draws), so the
//! same seed gives the same tree. (NaN values, which the features never hold,
//! are ranked too and grow a tree without panicking, but the first version's
//! order among equal NaNs was arbitrary, so there is nothing to match.)
//!
//! When the node's rows span few ranks of the feature (at most
//! `HIST · rows / classes`, e.g. spike counts at the nodes near the root),
//! the rows are not ordered at all: one pass adds each row's bootstrap
//! weight to a histogram over (rank, class) (two histograms, alternate rows
//! to each, then summed: consecutive rows of one trial often hit one cell,
//! which made one histogram a chain of load-add-stores), and the sweep runs over the
//! ranks, adding a rank's class weights at once (`(L + W)² − L² =
//! W (2L + W)`, the same integers as row by row) and scoring the boundary
//! between each pair of consecutive ranks present, in the same order as the
//! row sweep, with the same state: so the same splits. A row sweep in rank
//! order read each row's class and weight at random and updated the class's
//! running count row after row (runs of rows of one class are a chain
//! through memory).
//!
//! A feature found constant on a node's rows is constant on every
//! descendant's (a subset of them), so each node passes its children the
//! set of features known constant (up to the first 128 features); a drawn
//! feature in that set is skipped without reading its values. The draws
//! are unchanged (a skipped feature is still drawn, as it was drawn and
//! then found constant), so the trees are too. On the peers data (80
//! spike-count features, many all-zero deep in a tree) a third of the rows
//! read per tree were reads of features that turned out constant.
//!
//! The counting sort keeps four interleaved counts per rank (rows of one
//! rank, e.g. the many zero spike counts, then increment four counters in
//! turn rather than one, which would serialise on the store). The sweep
//! keeps `S_L` and the cross term `X = Σ_c N_c L_c`, and takes
//! `S_R = Σ_c N_c² − 2X + S_L` at the boundaries: the same integer as
//! updating `S_R` row by row.
//!
//! # The node's classes, ranks as bits, perfect splits (2026-12-06)
//!
//! Once per node (not per drawn feature), the classes with rows at the
//! node are numbered `0..kc` in class order and each row's (multiplicity,
//! node class) is copied in node order: the passes over a feature then
//! read it in sequence instead of gathering it by row, and the histogram
//! has `kc` cells per rank, not `k` (a class without rows at the node adds
//! `0` to every sum: the same integers). Deep in a tree a node has a few of
//! the 17 classes, so the histogram sweep over (rank, class), which the
//! counting sort used to be cheaper than, now pays off at every node.
//!
//! A feature with at most `MASKED` (64) distinct values (every feature of
//! the peers data: 40 to 60) is swept as a histogram at every node: one
//! pass reads each row's rank, sets its bit in a word of the ranks present
//! and adds the row to cell `rank · kc + class` (two histograms, alternate
//! rows, as above; kept out of line, where the loop's pointers stay in
//! registers), and the sweep visits the set bits in ascending order, each
//! present rank's cells summed, added to the left side and set back to
//! zero (so nothing is cleared beforehand, whatever the span). The
//! boundaries are those between consecutive ranks present, in the same
//! order as the row sweep's, with the same state: the same splits. Wider
//! features keep the counting sort or the comparison sort above (sorting
//! `rank << 32 | position` keys).
//!
//! No boundary scores more than `N` (`S_L ≤ N_L²`, so `S_L / N_L ≤ N_L`
//! and, rounded, the sum is at most `N_L + N_R = N`, while the squares are
//! exact, `N < 2^26`). Once a node's best split scores `N` (both children
//! pure), the features still to be drawn are drawn, as before, but not
//! read: none could score more, and ties go to the first. The score's
//! integers go to `f64` by the signed conversion below `2^31` rows (one
//! instruction; the same value). The partition writes each row to both
//! sides and advances the one it goes to, without a branch.
//!
//! Same trees: the reference test, the proptest and the peers forest
//! scores (`PEERS_DUMP_SCORES=1 cargo run --release --example peers --
//! --out <dir> --seed 1 --only random_forest`, `scores_test.npy`
//! `cmp`-identical to 687a64f's). Measured on the peers training set
//! (2295 x 80, 17 classes, `X_train.npy` of that run): `Prepared::new`
//! and the 15 trees of a fit, one thread, thread CPU time, the 687a64f
//! code and this one compiled into one throwaway harness (not kept) and
//! interleaved, 20 rounds of 5 fits each, on a loaded 2-core host: median
//! **15.3-16.1 -> 10.4-11.5 ms** per fit (0.69-0.72x, six runs), same
//! trees. What is left: the histogram pass ~25 %, the sweep ~12 %, the
//! scores ~5 %, `Prepared::new` ~5 %, the generator ~5 % (`perf`).
//!
//! # Predicting: every tree's walks in lock step
//!
//! Trees keep their nodes in depth-first order. For prediction, [`Flat`]
//! lays all of a forest's trees out in one array of 16-byte steps
//! (threshold, feature, left child; the right child is next to it) in which
//! a leaf leads to itself (threshold `+inf`), so that every step of a walk
//! is the same few loads and one compare, without a branch on the path.
//! [`Flat::vote`] moves up to 1024 walks (row, tree) together: a block of
//! 1024 rows through one tree at a time, or, with fewer rows, every row
//! through as many trees as fit (e.g. 64 rows through 15 trees; blocks of
//! 32 to 256 rows through every tree gave the same times on the peers
//! workload, docs/benches.md, 2026-12-02). The first 10 steps move every
//! walk, after that only the walks not yet on a leaf, kept in a list
//! compacted without a branch. The first version walked a block of 32
//! rows through one tree at a time, so
//! each tree's few deep walks ran nearly alone at the end, their load
//! latencies exposed; and it tested for leaves and bounds at every step.
//! On the peers workload (3154 rows, 15 trees of ~1300 nodes, ~860k node
//! steps; `RAYON_NUM_THREADS=1 target/release/examples/peers --out <dir> --seed 1 --only
//! random_forest`, best of 6 runs each, alternating, on a loaded 2-core
//! machine) the predict time went from 2.55 ms to 1.96 ms (on-CPU 2.34 ms to
//! 1.71 ms), with the same votes.
//!
//! The votes are those of the per-tree walk (kept in the tests as the
//! reference), malformed trees included: a tree with a child before its
//! parent, whose walks the layout cannot bound, is walked row by row.
//!
//! Determinism: tree `t` draws only from its own generator, seeded from the
//! forest's seed and `t`, so trees can grow in parallel and the forest has
//! the same bits on any number of threads.

use rand::Rng;
use rand_chacha::rand_core::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

/// A node of a [`Tree`]: a split (`feature < u32::MAX`) or a leaf.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Node {
    /// Split feature, or `u32::MAX` for a leaf.
    pub feature: u32,
    /// Rows with `x[feature] <= threshold` go left.
    pub threshold: f64,
    /// Left child (right child = `left + 1`); a leaf's class otherwise.
    pub left_or_class: u32,
}

/// One fitted tree, nodes in depth-first order from the root (node 0).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Tree {
    /// The nodes.
    pub nodes: Vec<Node>,
}

impl Tree {
    /// The class this tree predicts for `x` (standardised like its training rows).
    #[inline]
    pub fn predict(&self, x: &[f64]) -> usize {
        let mut i = 0usize;
        loop {
            let n = &self.nodes[i];
            if n.feature == u32::MAX {
                return n.left_or_class as usize;
            }
            let go_right = x[n.feature as usize] > n.threshold;
            i = n.left_or_class as usize + usize::from(go_right);
        }
    }

    /// The class of `x` (`dim` wide), as [`Self::predict`] but never
    /// panicking: a walk that stops at a split on a feature beyond `dim`,
    /// leaves the tree, or is still on a split after as many steps as the
    /// tree has nodes (a malformed tree, which `check_shape` rejects on
    /// load) gives `usize::MAX`. [`Flat`] walks the trees it cannot lay
    /// out (a child before its parent) this way.
    fn predict_checked(&self, x: &[f64], dim: usize) -> usize {
        let mut i = 0usize;
        for _ in 0..self.nodes.len() {
            let Some(n) = self.nodes.get(i) else {
                return usize::MAX;
            };
            let f = n.feature as usize;
            if n.feature == u32::MAX {
                return n.left_or_class as usize;
            }
            let Some(&v) = x.get(f).filter(|_| f < dim) else {
                return usize::MAX;
            };
            i = n.left_or_class.wrapping_add(u32::from(v > n.threshold)) as usize;
        }
        match self.nodes.get(i) {
            Some(n) if n.feature == u32::MAX => n.left_or_class as usize,
            _ => usize::MAX,
        }
    }
}

/// A node of a [`Flat`] forest: rows with `z[feature] > threshold` go to
/// `left + 1`, the others to `left`. A leaf (or a dead end) is a node that
/// leads to itself: `threshold = +inf`, `left` = its own index.
#[derive(Clone, Copy, Debug)]
#[repr(C)]
struct Step {
    threshold: f64,
    feature: u32,
    left: u32,
}

/// Most walks (row, tree) that [`Flat::vote`] keeps in flight together (a
/// power of two).
const WALKS: usize = 1024;

/// Steps that [`Flat::vote`] takes with every walk before it starts dropping
/// those on a leaf (~10 % of the walks end sooner on the peers data).
const EARLY: usize = 10;

/// A forest's trees laid out for prediction: one array of `Step`s, tree
/// after tree (each followed by two dead ends), so that a walk is the same
/// three loads and a compare at every node, leaves included. Built once per
/// forest (`Forest` caches it); votes as `Tree::predict_checked` would.
#[derive(Clone, Debug, Default)]
pub struct Flat {
    /// Features per row.
    dim: usize,
    /// The laid-out trees' nodes.
    steps: Vec<Step>,
    /// Per node of `steps`: its class if a leaf, else `u32::MAX` (no vote).
    class: Vec<u32>,
    /// Root of each laid-out tree in `steps`.
    roots: Vec<u32>,
    /// Most steps of a walk (the largest laid-out tree's node count).
    longest: usize,
    /// Trees with a child before its parent: walked row by row.
    cyclic: Vec<Tree>,
}

impl Flat {
    /// Lays out `trees` for rows `dim` wide.
    pub fn new(trees: &[Tree], dim: usize) -> Flat {
        let mut f = Flat {
            dim,
            ..Flat::default()
        };
        for t in trees {
            let len = t.nodes.len();
            let acyclic = t.nodes.iter().enumerate().all(|(i, n)| {
                n.feature == u32::MAX || n.feature as usize >= dim || n.left_or_class as usize > i
            });
            let base = f.steps.len();
            if !acyclic || base + len + 2 > u32::MAX as usize {
                f.cyclic.push(t.clone());
                continue;
            }
            f.roots.push(base as u32);
            f.longest = f.longest.max(len + 1);
            let stop = |i: usize| Step {
                threshold: f64::INFINITY,
                feature: 0,
                left: (base + i) as u32,
            };
            for (i, n) in t.nodes.iter().enumerate() {
                if n.feature == u32::MAX {
                    f.steps.push(stop(i));
                    f.class.push(n.left_or_class);
                } else if n.feature as usize >= dim {
                    f.steps.push(stop(i));
                    f.class.push(u32::MAX);
                } else {
                    // A child beyond the tree goes to the dead ends after it.
                    let left = (n.left_or_class as usize).min(len);
                    f.steps.push(Step {
                        threshold: n.threshold,
                        feature: n.feature,
                        left: (base + left) as u32,
                    });
                    f.class.push(u32::MAX);
                }
            }
            f.steps.extend([stop(len), stop(len + 1)]);
            f.class.extend([u32::MAX; 2]);
        }
        f
    }

    /// Adds, for each row `r` of `z` (row-major, `dim` wide) and each tree,
    /// one vote to `votes[r * k + c]` for the tree's class `c` of the row, if
    /// `c < k` (rows as many as both hold).
    ///
    /// Up to `WALKS` walks (row, tree) go down together, a step at a time,
    /// each step moving every walk one node down, branch-free: so the load
    /// latencies of many walks overlap, and a tree's few deep walks share
    /// their steps with other trees' walks. The first `EARLY` steps move
    /// every walk (few have reached a leaf, which leads to itself); after
    /// that, the walks still going are kept in a list compacted without a
    /// branch, and the walk ends when the list is empty.
    pub fn vote(&self, z: &[f64], k: usize, votes: &mut [u32]) {
        let dim = self.dim;
        let rows = z
            .len()
            .checked_div(dim)
            .unwrap_or(0)
            .min(votes.len().checked_div(k).unwrap_or(0));
        // Rows at a time: each walk's row offset fits its state's 32 bits.
        let per = (u32::MAX as usize / dim.max(1)).clamp(1, WALKS);
        // Per walk: row offset in `z` << 32 | node.
        let mut state = [0u64; WALKS];
        let mut live = [[0u16; WALKS]; 2];
        for r0 in (0..rows).step_by(per) {
            let nr = per.min(rows - r0);
            let zc = &z[r0 * dim..(r0 + nr) * dim];
            let vc = &mut votes[r0 * k..(r0 + nr) * k];
            for roots in self.roots.chunks(WALKS / nr) {
                // Walk w = tree · nr + row.
                let n = roots.len() * nr;
                for (s, w) in state[..n].iter_mut().zip(0..) {
                    *s = ((w % nr * dim) as u64) << 32 | u64::from(roots[w / nr]);
                }
                let early = EARLY.min(self.longest);
                for _ in 0..early {
                    for s in &mut state[..n] {
                        // SAFETY: see `step`; the offsets are below `(nr - 1) · dim`.
                        (*s, _) = unsafe { self.step(zc, *s) };
                    }
                }
                live[0][..n].iter_mut().zip(0..).for_each(|(l, w)| *l = w);
                let mut n_live = n;
                for round in early..self.longest {
                    if n_live == 0 {
                        break;
                    }
                    let [a, b] = &mut live;
                    let (from, to) = if round % 2 == 0 { (a, b) } else { (b, a) };
                    let mut kept = 0;
                    for &w in &from[..n_live] {
                        let w = usize::from(w) & (WALKS - 1);
                        // SAFETY: as above.
                        let (s, moved) = unsafe { self.step(zc, state[w]) };
                        state[w] = s;
                        to[kept & (WALKS - 1)] = w as u16;
                        kept += usize::from(moved);
                    }
                    n_live = kept;
                }
                for (w, &s) in state[..n].iter().enumerate() {
                    let c = self.class[s as u32 as usize] as usize;
                    if c < k {
                        vc[w % nr * k + c] += 1;
                    }
                }
            }
        }
        for t in &self.cyclic {
            for (x, v) in z
                .chunks_exact(dim.max(1))
                .zip(votes.chunks_exact_mut(k.max(1)))
                .take(rows)
            {
                if let Some(v) = v.get_mut(t.predict_checked(x, dim)) {
                    *v += 1;
                }
            }
        }
    }

    /// A walk's state (`offset << 32 | node`) one node down, and whether it moved.
    ///
    /// # Safety
    /// `node` is an index of `self.steps` (a root, or what a step gave) and
    /// `offset + dim <= zc.len()`. [`Flat::new`] lays out only nodes whose
    /// feature is below `dim` (leaves use feature 0) and whose both children
    /// are indices of `steps`, so the next node is one again; `vote` calls it
    /// only with `dim >= 1` (else there are no rows).
    #[inline(always)]
    unsafe fn step(&self, zc: &[f64], s: u64) -> (u64, bool) {
        let at = s as u32;
        // SAFETY: the caller's contract.
        let node = unsafe { *self.steps.get_unchecked(at as usize) };
        let v = unsafe { *zc.get_unchecked((s >> 32) as usize + node.feature as usize) };
        let next = node.left + u32::from(v > node.threshold);
        (s & !0xFFFF_FFFF | u64::from(next), next != at)
    }
}

/// A [`Flat`] layout of a forest's trees, built on first use and kept (the
/// trees of a fitted or loaded forest do not change). Any two compare equal:
/// it holds nothing the trees do not say.
#[derive(Clone, Debug, Default)]
pub struct FlatCache(std::sync::OnceLock<Flat>);

impl FlatCache {
    /// The layout of `trees` for rows `dim` wide (built by the first call).
    pub fn get(&self, trees: &[Tree], dim: usize) -> &Flat {
        self.0.get_or_init(|| Flat::new(trees, dim))
    }
}

impl PartialEq for FlatCache {
    fn eq(&self, _: &FlatCache) -> bool {
        true
    }
}

/// Growth settings.
#[derive(Clone, Copy, Debug)]
pub struct Growth {
    /// Features tried per split.
    pub m: usize,
    /// Largest depth; 0 = unlimited.
    pub max_depth: usize,
    /// Fewest distinct rows in a leaf.
    pub min_samples_leaf: usize,
}

/// The generator of tree `t` of a forest seeded `seed`.
pub fn tree_rng(seed: u64, t: usize) -> ChaCha8Rng {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(t as u64 + 1);
    rng
}

/// `f64::total_cmp`'s order as the order of unsigned integers.
fn order_key(v: f64) -> u64 {
    let b = v.to_bits();
    if b >> 63 == 1 {
        !b
    } else {
        b | 1 << 63
    }
}

/// The value whose [`order_key`] is `key`.
fn from_order_key(key: u64) -> f64 {
    f64::from_bits(if key >> 63 == 1 { key & !(1 << 63) } else { !key })
}

/// Training rows prepared once for all the trees of a forest: each feature's
/// values as ranks among its distinct values (see the module docs).
#[derive(Clone, Debug)]
pub struct Prepared {
    /// Rows.
    n: usize,
    /// Features per row.
    dim: usize,
    /// Classes (at least one more than the largest class of a row).
    k: usize,
    /// Class per row.
    y: Vec<u32>,
    /// `rank[f · n + i]`: the rank of row `i`'s value of feature `f`.
    rank: Vec<u32>,
    /// Feature `f`'s distinct values, ascending in total order, are
    /// `values[start[f]..start[f + 1]]` (rank `r` is `values[start[f] + r]`).
    start: Vec<usize>,
    /// The distinct values of every feature.
    values: Vec<f64>,
}

impl Prepared {
    /// Prepares the rows of `x` (row-major, `dim` wide; the first
    /// `y.len()` rows, fewer if `x` is shorter) with classes `y` in `0..k`.
    pub fn new(x: &[f64], y: &[usize], dim: usize, k: usize) -> Prepared {
        let n = x.len().checked_div(dim).map_or(y.len(), |rows| y.len().min(rows));
        let y = &y[..n];
        let k = y.iter().map(|&c| c.saturating_add(1)).max().unwrap_or(0).max(k);
        // Order keys, feature-major, read a block of rows at a time.
        let mut keys = vec![0u64; n * dim];
        const ROWS: usize = 64;
        for r0 in (0..n).step_by(ROWS) {
            let r1 = (r0 + ROWS).min(n);
            for f in 0..dim {
                for (key, i) in keys[f * n + r0..f * n + r1].iter_mut().zip(r0..r1) {
                    *key = order_key(x[i * dim + f]);
                }
            }
        }
        // Per feature: number the distinct keys by a hash table (open
        // addressing, at most half full; `gen` marks this feature's slots),
        // sort the few distinct keys, renumber by rank.
        let cap = (2 * n).next_power_of_two().max(2);
        let shift = 64 - cap.trailing_zeros();
        let mut slot_key = vec![0u64; cap];
        let mut slot_id = vec![0u32; cap];
        let mut slot_gen = vec![0u32; cap];
        let mut ids = vec![0u32; n];
        let mut distinct: Vec<u64> = Vec::new();
        let mut order: Vec<u32> = Vec::new();
        let mut rank_of: Vec<u32> = Vec::new();
        let mut rank = vec![0u32; n * dim];

        let mut start = Vec::with_capacity(dim + 1);
        let mut values = Vec::new();
        start.push(0);
        for f in 0..dim {
            let gen = f as u32 + 1;
            distinct.clear();
            let (mut last_key, mut last_id) = (None, 0u32);
            for (id, &key) in ids.iter_mut().zip(&keys[f * n..(f + 1) * n]) {
                if last_key == Some(key) {
                    *id = last_id;
                    continue;
                }
                let mut h = (key.wrapping_mul(0x9E37_79B9_7F4A_7C15) >> shift) as usize;
                loop {
                    if slot_gen[h] != gen {
                        slot_gen[h] = gen;
                        slot_key[h] = key;
                        slot_id[h] = distinct.len() as u32;
                        distinct.push(key);
                    }
                    if slot_key[h] == key {
                        *id = slot_id[h];
                        break;
                    }
                    h = (h + 1) & (cap - 1);
                }
                (last_key, last_id) = (Some(key), *id);
            }
            order.clear();
            order.extend(0..distinct.len() as u32);
            order.sort_unstable_by_key(|&i| distinct[i as usize]);
            rank_of.clear();
            rank_of.resize(distinct.len(), 0);
            for (r, &i) in order.iter().enumerate() {
                rank_of[i as usize] = r as u32;
                values.push(from_order_key(distinct[i as usize]));
            }
            for (r, &id) in rank[f * n..(f + 1) * n].iter_mut().zip(&ids) {
                *r = rank_of[id as usize];
            }
            start.push(values.len());
        }
        Prepared {
            n,
            dim,
            k,
            y: y.iter().map(|&c| c as u32).collect(),
            rank,
            start,
            values,
        }
    }

    /// The ranks of feature `f` (one per row) and its distinct values.
    fn feature(&self, f: usize) -> (&[u32], &[f64]) {
        (
            &self.rank[f * self.n..(f + 1) * self.n],
            &self.values[self.start[f]..self.start[f + 1]],
        )
    }
}

/// Grows one tree on a bootstrap sample of the rows of `x` (row-major, `dim`
/// wide) with classes `y` in `0..k`, drawing from `rng`. (A forest prepares
/// the rows once, [`Prepared::new`], and calls [`grow_prepared`] per tree.)
pub fn grow(x: &[f64], y: &[usize], dim: usize, k: usize, g: &Growth, rng: &mut ChaCha8Rng) -> Tree {
    grow_prepared(&Prepared::new(x, y, dim, k), g, rng)
}

/// Grows one tree on a bootstrap sample of the prepared rows, drawing from `rng`.
pub fn grow_prepared(p: &Prepared, g: &Growth, rng: &mut ChaCha8Rng) -> Tree {
    let n = p.n;
    let mut weight = vec![0u32; n];
    for _ in 0..n {
        weight[rng.random_range(0..n)] += 1;
    }
    let mut rows: Vec<u32> = (0..n as u32).filter(|&i| weight[i as usize] > 0).collect();
    let len = rows.len();
    let widest = (0..p.dim).map(|f| p.start[f + 1] - p.start[f]).max().unwrap_or(0);
    let mut b = Builder {
        p,
        g: *g,
        cw: weight
            .iter()
            .zip(&p.y)
            .map(|(&w, &c)| u64::from(w) << 32 | u64::from(c))
            .collect(),
        features: (0..p.dim as u32).collect(),
        ranks: vec![0; len],
        keys: vec![0; len],
        spill: vec![0; len],
        bins: vec![0; LANES * widest],
        hist: vec![0; 2 * (HIST * len + p.k).max(MASKED * p.k)],
        counts: vec![0; p.k],
        left: vec![0; p.k],
        class_of: vec![0; p.k],
        node_cw: vec![0; len],
        node_counts: Vec::with_capacity(p.k),
    };
    let mut nodes = vec![leaf(0)];
    // Depth-first with an explicit stack: (node, rows range, depth, the
    // features known to be constant on the node's rows).
    let mut stack = vec![(0usize, 0usize, len, 0usize, 0u128)];
    while let Some((node, lo, hi, depth, mut constant)) = stack.pop() {
        let part = &mut rows[lo..hi];
        b.class_counts(part);
        nodes[node] = leaf(first_max(&b.counts));
        let pure = b.counts.iter().filter(|&&c| c > 0).count() <= 1;
        if pure || (g.max_depth > 0 && depth >= g.max_depth) || part.len() < 2 * g.min_samples_leaf.max(1) {
            continue;
        }
        let Some((feature, threshold)) = b.best_split(part, rng, &mut constant) else {
            continue;
        };
        let mid = lo + b.partition(part, feature as usize, threshold);
        let left = nodes.len();
        nodes.push(leaf(0));
        nodes.push(leaf(0));
        nodes[node] = Node {
            feature,
            threshold,
            left_or_class: left as u32,
        };
        // Right pushed first so the left subtree is grown first.
        stack.push((left + 1, mid, hi, depth + 1, constant));
        stack.push((left, lo, mid, depth + 1, constant));
    }
    Tree { nodes }
}

fn leaf(class: usize) -> Node {
    Node {
        feature: u32::MAX,
        threshold: 0.0,
        left_or_class: class as u32,
    }
}

/// Index of the largest count (first on ties).
fn first_max(c: &[u64]) -> usize {
    let mut best = 0;
    for (i, &v) in c.iter().enumerate() {
        if v > c[best] {
            best = i;
        }
    }
    best
}

/// Features with at most this many distinct values are swept as a
/// histogram of (rank, class) with the ranks present as the bits of a word.
const MASKED: usize = 64;

/// Interleaved counts per rank in the counting sort.
const LANES: usize = 4;

/// A node's drawn feature is swept as a histogram of (rank, class) when its
/// rows span at most `HIST · rows / classes` ranks (module docs).
const HIST: usize = 2;

/// The threshold between two consecutive distinct values `v < next`:
/// halfway, or `v` itself where halfway rounds up to `next`.
fn halfway(v: f64, next: f64) -> f64 {
    let thr = v + (next - v) / 2.0;
    if thr >= next {
        v
    } else {
        thr
    }
}

/// The set bits of a word, lowest first.
struct Bits(u64);

impl Iterator for Bits {
    type Item = usize;

    #[inline]
    fn next(&mut self) -> Option<usize> {
        let b = self.0;
        if b == 0 {
            return None;
        }
        self.0 = b & (b - 1);
        Some(b.trailing_zeros() as usize)
    }
}

/// The histogram pass of a feature with at most 64 distinct values: adds
/// each row's `1 << 32 |` multiplicity to cell `rank · k + class` of
/// histogram `q % L` for the row at position `q`, and returns the ranks
/// present as bits. Kept out of line: inside `best_split` the loop's
/// pointers lived on the stack.
#[inline(never)]
fn fill_masked<const L: usize>(rows: &[u32], ncw: &[u64], col: &[u32], k: usize, hs: [&mut [u64]; L]) -> u64 {
    let cell = |r: u32, e: u64| r as usize * k + e as u32 as usize;
    let add = |e: u64| 1 << 32 | e >> 32;
    let mut masks = [0u64; L];
    let (rc, ec) = (rows.chunks_exact(L), ncw.chunks_exact(L));
    let (rr, er) = (rc.remainder(), ec.remainder());
    for (i, e) in rc.zip(ec) {
        for l in 0..L {
            let r = col[i[l] as usize];
            masks[l] |= 1u64.wrapping_shl(r);
            hs[l][cell(r, e[l])] += add(e[l]);
        }
    }
    for (l, (&i, &e)) in rr.iter().zip(er).enumerate() {
        let r = col[i as usize];
        masks[l] |= 1u64.wrapping_shl(r);
        hs[l][cell(r, e)] += add(e);
    }
    masks.iter().fold(0, |a, m| a | m)
}

/// The histogram sweep: for each `(bin, rank)` of `bins` (ascending
/// ranks), the bin's `k` cells summed over the histograms `hs` (rows `<<
/// 32 |` weight per node class) added to the left side, all of them set
/// back to zero; `offer(v, next, rows_left, [S_L, X, N_L])` at the
/// boundary between each two consecutive ranks with rows, with the row
/// sweep's state there (every row of the ranks below on the left).
/// `present`: every bin has rows (one pass per bin, else two).
#[allow(clippy::too_many_arguments)]
#[inline]
fn sweep_hist<const L: usize>(
    mut hs: [&mut [u64]; L],
    k: usize,
    bins: impl Iterator<Item = (usize, usize)>,
    present: bool,
    counts: &[u64],
    left: &mut [u64],
    vals: &[f64],
    mut offer: impl FnMut(f64, f64, usize, [u64; 3]),
) {
    left.iter_mut().for_each(|c| *c = 0);
    let (mut s_left, mut cross, mut n_left, mut rows_left) = (0u64, 0u64, 0u64, 0usize);
    let mut prev: Option<usize> = None;
    for (j, r) in bins {
        let cells = j * k..(j + 1) * k;
        if !present {
            let here: u64 = hs
                .iter()
                .map(|h| h[cells.clone()].iter().map(|x| x >> 32).sum::<u64>())
                .sum();
            if here == 0 {
                continue;
            }
        }
        if let Some(pr) = prev {
            offer(vals[pr], vals[r], rows_left, [s_left, cross, n_left]);
        }
        let mut bs = hs.each_mut().map(|h| &mut h[j * k..][..k]);
        let (left, counts) = (&mut left[..k], &counts[..k]);
        let mut here = 0u64;
        for c in 0..k {
            let mut e = 0;
            for b in bs.iter_mut() {
                e += b[c];
                b[c] = 0;
            }
            let (lc, nc) = (left[c], counts[c]);
            let w = e & 0xFFFF_FFFF;
            here += e >> 32;
            // (L + W)² − L² = W (2L + W): the rows' own increments summed,
            // the same integer.
            s_left += w * (2 * lc + w);
            cross += w * nc;
            left[c] = lc + w;
            n_left += w;
        }
        rows_left += here as usize;
        prev = Some(r);
    }
}

/// The row sweep: `keys` (`rank << 32 | position`, ascending) in order,
/// each position's `ncw` entry (multiplicity `<< 32 |` node class) added
/// to the left side, calling `offer(v, next, rows_left, [S_L, X, N_L])` at
/// each boundary between two ranks. `S_L = Σ L_c²` and `S_R = Σ (N_c −
/// L_c)² = Σ N_c² − 2 Σ N_c L_c + S_L` from the cross term `X = Σ N_c L_c`
/// (exact integers, so the same `S_R` as one updated row by row).
fn sweep_rows(
    keys: &[u64],
    ncw: &[u64],
    counts: &[u64],
    left: &mut [u64],
    vals: &[f64],
    mut offer: impl FnMut(f64, f64, usize, [u64; 3]),
) {
    left.iter_mut().for_each(|c| *c = 0);
    let mut s_left = 0u64;
    let mut cross = 0u64;
    let mut n_left = 0u64;
    for (q, &key) in keys.iter().enumerate() {
        let rw = ncw[key as u32 as usize];
        let (c, w) = (rw as u32 as usize, rw >> 32);
        let lc = left[c];
        // (n + w)² − n² = w (2n + w)
        s_left += w * (2 * lc + w);
        cross += w * counts[c];
        left[c] = lc + w;
        n_left += w;
        let Some(&next_key) = keys.get(q + 1) else {
            break;
        };
        let (r, next_r) = ((key >> 32) as usize, (next_key >> 32) as usize);
        if next_r == r {
            continue;
        }
        offer(vals[r], vals[next_r], q + 1, [s_left, cross, n_left]);
    }
}

/// One tree's growth state and scratch (sized once per tree).
struct Builder<'a> {
    p: &'a Prepared,
    g: Growth,
    /// Per row: bootstrap multiplicity `<< 32 |` class.
    cw: Vec<u64>,
    /// Feature order, reshuffled (partially) at every node.
    features: Vec<u32>,
    /// The node's ranks of the feature being tried.
    ranks: Vec<u32>,
    /// The node's rows as `rank << 32 | position` (in the node), ascending.
    keys: Vec<u64>,
    /// Rows going right while partitioning (one slot per row of the tree).
    spill: Vec<u32>,
    /// Counting-sort bins.
    bins: Vec<u32>,
    /// Two histograms of (rank, node class), each `hist.len() / 2` cells:
    /// rows `<< 32 |` weight; all zero between uses.
    hist: Vec<u64>,
    /// The node's weighted class counts.
    counts: Vec<u64>,
    /// Weighted class counts left of the sweep.
    left: Vec<u64>,
    /// Per class: its number among the node's classes.
    class_of: Vec<u32>,
    /// Per row of the node, in node order: multiplicity `<< 32 |` node class.
    node_cw: Vec<u64>,
    /// The node's weighted counts of its classes (those with rows).
    node_counts: Vec<u64>,
}

impl Builder<'_> {
    fn class_counts(&mut self, rows: &[u32]) {
        self.counts.iter_mut().for_each(|c| *c = 0);
        for &i in rows {
            let cw = self.cw[i as usize];
            self.counts[cw as u32 as usize] += cw >> 32;
        }
    }

    /// The best (feature, threshold) of the node holding `rows` (at least
    /// one), whose class counts are in `self.counts`, or `None`.
    ///
    /// `constant` has bit `f` set for features `f < 128` known to be
    /// constant on the rows (found so at an ancestor: a subset of constant
    /// rows is constant); such a feature, when drawn, is passed over without
    /// reading its values, as reading them would find it constant again.
    /// The features found constant here are added, for the children. The
    /// draws are the same either way, so the same tree.
    ///
    /// The node's classes are renumbered `0..kc` (those with rows here, in
    /// class order) and each row's (multiplicity, class) copied in node
    /// order, once per node; a drawn feature whose best split is already
    /// perfect (the score `N`, which no boundary exceeds) is drawn but not
    /// read (module docs).
    fn best_split(&mut self, rows: &[u32], rng: &mut ChaCha8Rng, constant: &mut u128) -> Option<(u32, f64)> {
        let Builder {
            p,
            g,
            cw,
            features,
            ranks,
            keys,
            bins,
            hist,
            counts: all_counts,
            left,
            class_of,
            node_cw,
            node_counts,
            ..
        } = self;
        let dim = p.dim;
        if dim == 0 || rows.is_empty() {
            return None;
        }
        let len = rows.len();
        // The node's classes, numbered in class order: a class without rows
        // here adds nothing to any sum, so the sums are the same integers.
        node_counts.clear();
        for (c, &n) in all_counts.iter().enumerate() {
            class_of[c] = node_counts.len() as u32;
            if n > 0 {
                node_counts.push(n);
            }
        }
        let counts = &node_counts[..];
        let k = counts.len();
        if k == 0 {
            return None; // no weight (not reached: every row has some)
        }
        // Per row of the node, in node order: multiplicity `<< 32 |` node class.
        let ncw = &mut node_cw[..len];
        for (e, &i) in ncw.iter_mut().zip(rows) {
            let rw = cw[i as usize];
            *e = rw >> 32 << 32 | u64::from(class_of[rw as u32 as usize]);
        }
        let ncw = &*ncw;
        let total: u64 = counts.iter().sum();
        let s_all: u64 = counts.iter().map(|c| c * c).sum();
        // No score exceeds `N` (`S_L ≤ N_L²`, so `S_L / N_L ≤ N_L` in `f64`
        // too while the squares are exact, and the sum rounds to at most
        // `N_L + N_R = N`): once a split scores `N`, no later one is taken.
        let perfect = if total < 1 << 26 {
            total as f64
        } else {
            f64::INFINITY
        };
        // Every sum below 2^62.
        let small = total < 1 << 31;
        let min_leaf = g.min_samples_leaf.max(1);
        let m = g.m.clamp(1, dim);
        // Scores the boundary between consecutive distinct values `v` and
        // `next` with `rows_left` of the node's rows on its left, whose
        // `[Σ L_c², Σ N_c L_c, Σ L_c]` are `sums` (the right side's follow:
        // `S_R = Σ N_c² − 2X + S_L`, exact integers), keeping the first best.
        // A candidate leaves `min_leaf` rows on each side and separates two
        // values that compare unequal.
        let offer = |best: &mut Option<(f64, u32, f64)>,
                     f: usize,
                     v: f64,
                     next: f64,
                     rows_left: usize,
                     [s_left, cross, n_left]: [u64; 3]| {
            if next <= v || rows_left < min_leaf || len - rows_left < min_leaf {
                return;
            }
            let n_right = total - n_left;
            let s_right = s_all + s_left - 2 * cross;
            // Below 2^63 the signed conversion is the same value, in one instruction.
            let float = |x: u64| if small { x as i64 as f64 } else { x as f64 };
            let score = float(s_left) / float(n_left) + float(s_right) / float(n_right);
            if best.is_none_or(|(b, _, _)| score > b) {
                *best = Some((score, f as u32, halfway(v, next)));
            }
        };
        let ranks = &mut ranks[..len];
        let keys = &mut keys[..len];
        let half = hist.len() / 2;
        let (h, h2) = hist.split_at_mut(half);
        let mut best: Option<(f64, u32, f64)> = None;
        for t in 0..dim {
            if t >= m && best.is_some() {
                break;
            }
            // Partial Fisher–Yates: feature t of this node's random order.
            let j = rng.random_range(t..dim);
            features.swap(t, j);
            let f = features[t] as usize;
            let bit = if f < 128 { 1u128 << f } else { 0 };
            if *constant & bit != 0 || best.is_some_and(|(b, _, _)| b >= perfect) {
                continue;
            }
            let (col, vals) = p.feature(f);
            let offer = |v: f64, next: f64, rows_left: usize, sums: [u64; 3]| {
                offer(&mut best, f, v, next, rows_left, sums)
            };
            let add = |e: u64| 1 << 32 | e >> 32;
            if vals.len() <= MASKED {
                // At most 64 ranks: their histogram, by rank, in the pass
                // that reads them, and the ranks present as bits.
                // Two histograms, rows alternating between them, summed in
                // the sweep: consecutive rows often fall in one cell (rows
                // of a trial share a class and, near the root, a spike
                // count), and one histogram made them a chain of
                // load-add-stores through that cell.
                let mask = fill_masked(rows, ncw, col, k, [&mut *h, &mut *h2]);
                let present = Bits(mask).map(|r| (r, r));
                let (lo, hi) = (mask.trailing_zeros() as usize, 63 - mask.leading_zeros() as usize);
                if vals[lo] >= vals[hi] {
                    // Constant here; the cells back to zero.
                    for (j, _) in present {
                        h[j * k..(j + 1) * k].fill(0);
                        h2[j * k..(j + 1) * k].fill(0);
                    }
                    *constant |= bit;
                    continue;
                }
                sweep_hist([&mut *h, &mut *h2], k, present, true, counts, left, vals, offer);
                continue;
            }
            let (mut lo, mut hi) = (u32::MAX, 0u32);
            if vals.len() <= 4 * len {
                for (r, &i) in ranks.iter_mut().zip(rows) {
                    let v = col[i as usize];
                    *r = v;
                    lo = lo.min(v);
                    hi = hi.max(v);
                }
                if vals[lo as usize] >= vals[hi as usize] {
                    *constant |= bit;
                    continue; // constant here
                }
                let span = (hi - lo) as usize + 1;
                if span * k <= HIST * len {
                    // Few ranks for the rows: a histogram of the ranks
                    // from `lo` (module docs), two as above.
                    let cell = |r: u32, e: u64| (r - lo) as usize * k + e as u32 as usize;
                    let (pairs, rest) = ranks.split_at(len & !1);
                    for (r, e) in pairs.chunks_exact(2).zip(ncw.chunks_exact(2)) {
                        h[cell(r[0], e[0])] += add(e[0]);
                        h2[cell(r[1], e[1])] += add(e[1]);
                    }
                    for (&r, &e) in rest.iter().zip(&ncw[len & !1..]) {
                        h[cell(r, e)] += add(e);
                    }
                    let lo = lo as usize;
                    let bins = (0..span).map(|j| (j, lo + j));
                    sweep_hist([&mut *h, &mut *h2], k, bins, false, counts, left, vals, offer);
                    continue;
                }
                // The rows in ascending order of rank by a counting sort,
                // four interleaved counts per rank, so that runs of rows of
                // one rank (common: many zeros) are four chains, not one.
                // Keys `rank << 32 | position`.
                let bins = &mut bins[LANES * lo as usize..LANES * (hi as usize + 1)];
                bins.iter_mut().for_each(|c| *c = 0);
                for (q, &r) in ranks.iter().enumerate() {
                    bins[LANES * (r - lo) as usize + q % LANES] += 1;
                }
                let mut at = 0;
                for c in bins.iter_mut() {
                    (*c, at) = (at, at + *c);
                }
                for (q, &r) in ranks.iter().enumerate() {
                    let at = &mut bins[LANES * (r - lo) as usize + q % LANES];
                    keys[*at as usize] = u64::from(r) << 32 | q as u64;
                    *at += 1;
                }
            } else {
                // Many distinct values for the rows: a sort of the keys.
                for ((key, &i), q) in keys.iter_mut().zip(rows).zip(0u64..) {
                    let v = col[i as usize];
                    lo = lo.min(v);
                    hi = hi.max(v);
                    *key = u64::from(v) << 32 | q;
                }
                if vals[lo as usize] >= vals[hi as usize] {
                    *constant |= bit;
                    continue; // constant here
                }
                keys.sort_unstable();
            }
            sweep_rows(keys, ncw, counts, left, vals, offer);
        }
        best.map(|(_, f, thr)| (f, thr))
    }

    /// Puts the rows of `rows` with `x[feature] <= threshold` first, both
    /// sides in their order; returns how many go left.
    fn partition(&mut self, rows: &mut [u32], feature: usize, threshold: f64) -> usize {
        let (col, vals) = self.p.feature(feature);
        let spill = &mut self.spill[..rows.len()];
        // Without a branch on the side: each row is written to both, and
        // the side it goes to advances (`l <= q`, so `rows[q]` is read first).
        let (mut l, mut r) = (0, 0);
        for q in 0..rows.len() {
            let i = rows[q];
            let left = vals[col[i as usize] as usize] <= threshold;
            rows[l] = i;
            spill[r] = i;
            l += usize::from(left);
            r += usize::from(!left);
        }
        rows[l..].copy_from_slice(&spill[..r]);
        l
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The first versions, kept as references: the growth the ranks must
    /// match (per node and drawn feature, the `(value, row)` pairs sorted by
    /// `f64::total_cmp` and swept), and the per-tree blocked prediction the
    /// flat layout must match.
    mod reference {
        use super::super::{first_max, leaf, Growth, Node, Tree};
        use rand::Rng;
        use rand_chacha::ChaCha8Rng;

        /// Rows that [`predict_rows`] walks down a tree together.
        const BLOCK: usize = 32;

        /// [`Tree::predict`] of each row of `z` (row-major, `dim` wide) into
        /// `out` (one class per row, `out.len()` rows).
        ///
        /// The rows go down a block at a time, level by level: a step moves each
        /// row of the block that is not yet on a leaf from its node to
        /// `left + (z[feature] > threshold)`, without a branch on the row's path
        /// (the rows still walking are kept in a list compacted branch-free at
        /// every step), so the load latencies of the block's rows overlap instead
        /// of adding up. Unlike [`Tree::predict`] this never panics: a row
        /// missing from `z`, a row stopped at a split on a feature beyond `dim`,
        /// and a row whose walk leaves the tree (a malformed tree, which
        /// `check_shape` rejects on load) get class `usize::MAX`.
        pub fn predict_rows(tree: &Tree, z: &[f64], dim: usize, out: &mut [usize]) {
            let nodes = &tree.nodes[..];
            let have = z.len().checked_div(dim).unwrap_or(0);
            for (b, out) in out.chunks_mut(BLOCK).enumerate() {
                let first = b * BLOCK;
                let rows = out.len().min(have.saturating_sub(first));
                let zb = &z[first * dim..(first + rows) * dim];
                let mut at = [0u32; BLOCK];
                // The rows still walking, read from one list and written to the
                // other (so the compacting stores never alias the next loads).
                let mut live = [[0u8; BLOCK]; 2];
                live[0].iter_mut().enumerate().for_each(|(r, l)| *l = r as u8);
                let mut n_live = rows;
                // A walk from the root of a valid tree (children after their
                // parent) reaches a leaf in fewer steps than there are nodes.
                for step in 0..nodes.len() {
                    if n_live == 0 {
                        break;
                    }
                    let [a, b] = &mut live;
                    let (from, to) = if step % 2 == 0 { (a, b) } else { (b, a) };
                    let mut kept = 0;
                    for &r in &from[..n_live] {
                        let r = usize::from(r);
                        let Some(n) = nodes.get(at[r] as usize) else {
                            continue; // off the tree: stops
                        };
                        let f = n.feature as usize;
                        let split = f < dim;
                        let v = zb[r * dim + f.min(dim - 1)];
                        let next = n.left_or_class.wrapping_add(u32::from(v > n.threshold));
                        at[r] = if split { next } else { at[r] };
                        to[kept] = r as u8;
                        kept += usize::from(split);
                    }
                    n_live = kept;
                }
                for (r, o) in out.iter_mut().enumerate() {
                    *o = match nodes.get(at[r] as usize) {
                        Some(n) if r < rows && n.feature == u32::MAX => n.left_or_class as usize,
                        _ => usize::MAX,
                    };
                }
            }
        }

        /// The votes per row and class (classes `< k`) of `trees` by [`predict_rows`].
        pub fn votes(trees: &[Tree], z: &[f64], dim: usize, k: usize) -> Vec<u32> {
            let rows = z.len() / dim.max(1);
            let mut votes = vec![0u32; rows * k];
            let mut out = vec![0usize; rows];
            for t in trees {
                predict_rows(t, z, dim, &mut out);
                for (v, &c) in votes.chunks_exact_mut(k.max(1)).zip(&out) {
                    if let Some(v) = v.get_mut(c) {
                        *v += 1;
                    }
                }
            }
            votes
        }

        pub fn grow(x: &[f64], y: &[usize], dim: usize, k: usize, g: &Growth, rng: &mut ChaCha8Rng) -> Tree {
            let n = y.len();
            let mut weight = vec![0u32; n];
            for _ in 0..n {
                weight[rng.random_range(0..n)] += 1;
            }
            let mut rows: Vec<u32> = (0..n as u32).filter(|&i| weight[i as usize] > 0).collect();
            let mut b = Builder {
                x,
                y,
                dim,
                k,
                g: *g,
                weight,
                features: (0..dim as u32).collect(),
                pairs: Vec::with_capacity(rows.len()),
                left: vec![0; k],
                right: vec![0; k],
                nodes: Vec::new(),
            };
            let len = rows.len();
            b.nodes.push(leaf(0));
            let mut stack = vec![(0usize, 0usize, len, 0usize)];
            while let Some((node, lo, hi, depth)) = stack.pop() {
                let part = &mut rows[lo..hi];
                let counts = b.class_counts(part);
                let majority = first_max(&counts);
                b.nodes[node] = leaf(majority);
                let pure = counts.iter().filter(|&&c| c > 0).count() <= 1;
                if pure
                    || (g.max_depth > 0 && depth >= g.max_depth)
                    || part.len() < 2 * g.min_samples_leaf.max(1)
                {
                    continue;
                }
                let Some((feature, threshold)) = b.best_split(part, &counts, rng) else {
                    continue;
                };
                let f = feature as usize;
                let (l, r): (Vec<u32>, Vec<u32>) =
                    part.iter().partition(|&&i| x[i as usize * dim + f] <= threshold);
                let mid = lo + l.len();
                part[..l.len()].copy_from_slice(&l);
                part[l.len()..].copy_from_slice(&r);
                let left = b.nodes.len();
                b.nodes.push(leaf(0));
                b.nodes.push(leaf(0));
                b.nodes[node] = Node {
                    feature,
                    threshold,
                    left_or_class: left as u32,
                };
                stack.push((left + 1, mid, hi, depth + 1));
                stack.push((left, lo, mid, depth + 1));
            }
            Tree { nodes: b.nodes }
        }

        struct Builder<'a> {
            x: &'a [f64],
            y: &'a [usize],
            dim: usize,
            k: usize,
            g: Growth,
            weight: Vec<u32>,
            features: Vec<u32>,
            pairs: Vec<(f64, u32)>,
            left: Vec<u64>,
            right: Vec<u64>,
            nodes: Vec<Node>,
        }

        impl Builder<'_> {
            fn class_counts(&self, rows: &[u32]) -> Vec<u64> {
                let mut c = vec![0u64; self.k];
                for &i in rows {
                    c[self.y[i as usize]] += u64::from(self.weight[i as usize]);
                }
                c
            }

            fn best_split(
                &mut self,
                rows: &[u32],
                counts: &[u64],
                rng: &mut ChaCha8Rng,
            ) -> Option<(u32, f64)> {
                let total: u64 = counts.iter().sum();
                let min_leaf = self.g.min_samples_leaf.max(1);
                let m = self.g.m.clamp(1, self.dim);
                let mut best: Option<(f64, u32, f64)> = None;
                for t in 0..self.dim {
                    if t >= m && best.is_some() {
                        break;
                    }
                    let j = rng.random_range(t..self.dim);
                    self.features.swap(t, j);
                    let f = self.features[t] as usize;
                    self.pairs.clear();
                    self.pairs
                        .extend(rows.iter().map(|&i| (self.x[i as usize * self.dim + f], i)));
                    self.pairs.sort_unstable_by(|a, b| a.0.total_cmp(&b.0));
                    let (first, last) = (self.pairs[0].0, self.pairs[self.pairs.len() - 1].0);
                    if first >= last {
                        continue;
                    }
                    self.left.iter_mut().for_each(|c| *c = 0);
                    self.right.copy_from_slice(counts);
                    let mut s_left = 0u64;
                    let mut s_right: u64 = counts.iter().map(|c| c * c).sum();
                    let mut n_left = 0u64;
                    for (p, &(v, i)) in self.pairs.iter().enumerate() {
                        let c = self.y[i as usize];
                        let w = u64::from(self.weight[i as usize]);
                        s_left += w * (2 * self.left[c] + w);
                        s_right -= w * (2 * self.right[c] - w);
                        self.left[c] += w;
                        self.right[c] -= w;
                        n_left += w;
                        let Some(&(next, _)) = self.pairs.get(p + 1) else {
                            break;
                        };
                        if next <= v || p + 1 < min_leaf || self.pairs.len() - (p + 1) < min_leaf {
                            continue;
                        }
                        let n_right = total - n_left;
                        let score = s_left as f64 / n_left as f64 + s_right as f64 / n_right as f64;
                        if best.is_none_or(|(b, _, _)| score > b) {
                            let mut thr = v + (next - v) / 2.0;
                            if thr >= next {
                                thr = v;
                            }
                            best = Some((score, f as u32, thr));
                        }
                    }
                }
                best.map(|(_, f, thr)| (f, thr))
            }
        }
    }

    /// Asserts that both growths give the same tree, to the bits of every threshold.
    fn assert_same_tree(x: &[f64], y: &[usize], dim: usize, k: usize, g: &Growth, seed: u64) {
        let want = reference::grow(x, y, dim, k, g, &mut tree_rng(seed, 0));
        let got = grow(x, y, dim, k, g, &mut tree_rng(seed, 0));
        assert_eq!(
            want.nodes.len(),
            got.nodes.len(),
            "node count, {g:?}, seed {seed}"
        );
        for (i, (a, b)) in want.nodes.iter().zip(&got.nodes).enumerate() {
            assert!(
                a.feature == b.feature
                    && a.left_or_class == b.left_or_class
                    && a.threshold.to_bits() == b.threshold.to_bits(),
                "node {i}: {a:?} != {b:?}, {g:?}, seed {seed}"
            );
        }
    }

    /// Rows of `dim` values drawn from `palette` (so with many duplicates),
    /// feature `dim - 1` constant, classes from the first two features and noise.
    fn palette_rows(n: usize, dim: usize, k: usize, palette: &[f64], seed: u64) -> (Vec<f64>, Vec<usize>) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut x = vec![0.0; n * dim];
        for (j, v) in x.iter_mut().enumerate() {
            *v = if j % dim == dim - 1 {
                palette[0]
            } else {
                palette[rng.random_range(0..palette.len())]
            };
        }
        let y = (0..n)
            .map(|i| {
                let s = usize::from(x[i * dim] > 0.0) + usize::from(x[i * dim + 1.min(dim - 1)] > 1.0);
                (s + usize::from(rng.random_range(0..4) == 0)) % k
            })
            .collect();
        (x, y)
    }

    #[test]
    fn ranks_grow_the_same_trees_as_sorted_values() {
        let palettes: [&[f64]; 4] = [
            &[0.0, 0.5, 1.0, 1.5, 2.0, 3.5],
            // Signed zeros (equal but distinct in total order), extremes, subnormals.
            &[
                -0.0,
                0.0,
                f64::MAX,
                -f64::MAX,
                5e-324,
                -5e-324,
                f64::MIN_POSITIVE,
                1e300,
                -1e-300,
                1.0,
            ],
            // Neighbouring floats: halfway rounds onto `next`.
            &[1.0, 1.0 + f64::EPSILON, 1.0 + 2.0 * f64::EPSILON, 2.0, -1.0],
            &[0.0, 1.0],
        ];
        let mut cases = 0;
        for (pi, palette) in palettes.iter().enumerate() {
            for &(n, dim, k) in &[
                (1, 3, 2),
                (2, 2, 2),
                (7, 4, 3),
                (60, 5, 3),
                (300, 9, 5),
                (500, 3, 1),
            ] {
                for &(m, max_depth, min_samples_leaf) in
                    &[(1, 0, 1), (2, 0, 1), (3, 4, 1), (2, 0, 3), (9, 0, 2)]
                {
                    let g = Growth {
                        m,
                        max_depth,
                        min_samples_leaf,
                    };
                    let seed = (pi * 100 + n + dim) as u64;
                    let (x, y) = palette_rows(n, dim, k, palette, seed);
                    assert_same_tree(&x, &y, dim, k, &g, seed);
                    cases += 1;
                }
            }
        }
        // More than `MASKED` distinct values with duplicates (the span
        // histogram and the counting sort), and many classes (a few at
        // each deep node).
        let wide: Vec<f64> = (0..100).map(|i| f64::from(i) * 0.37 - 9.0).collect();
        for &(n, dim, k, m) in &[(1500, 4, 3, 2), (900, 5, 17, 2), (600, 3, 2, 3)] {
            let g = Growth {
                m,
                max_depth: 0,
                min_samples_leaf: 1,
            };
            let (x, mut y) = palette_rows(n, dim, k, &wide, n as u64);
            // Classes from the first feature's value too, so that all `k` occur.
            for (i, c) in y.iter_mut().enumerate() {
                *c = (*c + (x[i * dim] * 3.0).abs() as usize) % k;
            }
            assert_same_tree(&x, &y, dim, k, &g, n as u64);
            let g3 = Growth {
                min_samples_leaf: 3,
                ..g
            };
            assert_same_tree(&x, &y, dim, k, &g3, 7);
        }
        // Continuous values: one distinct value per row (the comparison-sort path).
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let (n, dim) = (400, 6);
        let x: Vec<f64> = (0..n * dim).map(|_| rng.random_range(-3.0..3.0)).collect();
        let y: Vec<usize> = (0..n)
            .map(|i| usize::from(x[i * dim] + x[i * dim + 2] > 0.0))
            .collect();
        for m in 1..=dim {
            let g = Growth {
                m,
                max_depth: 0,
                min_samples_leaf: 1,
            };
            assert_same_tree(&x, &y, dim, 2, &g, m as u64);
        }
        // One class everywhere: a single leaf.
        let ones = vec![0usize; 50];
        let g = Growth {
            m: 2,
            max_depth: 0,
            min_samples_leaf: 1,
        };
        assert_same_tree(&x[..50 * dim], &ones, dim, 3, &g, 1);
        assert_eq!(
            grow(&x[..50 * dim], &ones, dim, 3, &g, &mut tree_rng(1, 0))
                .nodes
                .len(),
            1
        );
        assert!(cases > 100);
    }

    #[test]
    fn prepared_ranks_follow_the_total_order() {
        let x = [0.0, -0.0, 2.0, -1.0, 2.0, 0.0, f64::MAX, -0.0];
        let p = Prepared::new(&x, &[0; 8], 1, 1);
        let (rank, vals) = p.feature(0);
        assert_eq!(rank, &[2, 1, 3, 0, 3, 2, 4, 1]);
        let bits: Vec<u64> = vals.iter().map(|v| v.to_bits()).collect();
        let want: Vec<u64> = [-1.0, -0.0, 0.0, 2.0, f64::MAX]
            .iter()
            .map(|v: &f64| v.to_bits())
            .collect();
        assert_eq!(bits, want);
        for v in [
            0.0,
            -0.0,
            1.5,
            -1.5,
            f64::MAX,
            f64::MIN,
            5e-324,
            -5e-324,
            f64::INFINITY,
        ] {
            assert_eq!(from_order_key(order_key(v)).to_bits(), v.to_bits());
        }
        // Nothing to grow on: no panic, one leaf.
        let g = Growth {
            m: 1,
            max_depth: 0,
            min_samples_leaf: 1,
        };
        assert_eq!(grow(&[], &[], 3, 2, &g, &mut tree_rng(1, 0)).nodes, vec![leaf(0)]);
        assert_eq!(grow(&[], &[1, 0], 0, 2, &g, &mut tree_rng(1, 0)).nodes.len(), 1);
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(64))]
        /// Any small data set (duplicated values from a few levels or
        /// not, any class layout and settings): the same tree as the value sort.
        #[test]
        fn ranks_match_the_value_sort_on_any_data(
            n in 1usize..120,
            dim in 1usize..7,
            k in 1usize..5,
            levels in 1u32..12,
            m in 1usize..8,
            max_depth in 0usize..6,
            min_samples_leaf in 1usize..4,
            seed in 0u64..1000,
        ) {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let x: Vec<f64> = (0..n * dim)
                .map(|_| f64::from(rng.random_range(0..levels)) * 0.37 - 1.0)
                .collect();
            let y: Vec<usize> = (0..n).map(|_| rng.random_range(0..k)).collect();
            let g = Growth { m, max_depth, min_samples_leaf };
            let want = reference::grow(&x, &y, dim, k, &g, &mut tree_rng(seed, 1));
            let got = grow(&x, &y, dim, k, &g, &mut tree_rng(seed, 1));
            proptest::prop_assert_eq!(want.nodes.len(), got.nodes.len());
            for (a, b) in want.nodes.iter().zip(&got.nodes) {
                proptest::prop_assert_eq!(a.feature, b.feature);
                proptest::prop_assert_eq!(a.left_or_class, b.left_or_class);
                proptest::prop_assert_eq!(a.threshold.to_bits(), b.threshold.to_bits());
            }
        }

        /// The flat layout votes as the first version's per-tree blocked
        /// walk (kept below) and as [`Tree::predict`], on any forest and rows
        /// (some exactly on thresholds), through several chunks of walks.
        #[test]
        fn flat_votes_as_the_per_tree_walk(
            n in 1usize..80,
            rows in 0usize..150,
            dim in 1usize..6,
            k in 1usize..5,
            trees in 1usize..25,
            seed in 0u64..1000,
        ) {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let x: Vec<f64> = (0..n * dim).map(|_| rng.random_range(-2.0..2.0)).collect();
            let y: Vec<usize> = (0..n).map(|_| rng.random_range(0..k)).collect();
            let g = Growth { m: 2, max_depth: 0, min_samples_leaf: 1 };
            let p = Prepared::new(&x, &y, dim, k);
            let forest: Vec<Tree> = (0..trees).map(|t| grow_prepared(&p, &g, &mut tree_rng(seed, t))).collect();
            let mut z: Vec<f64> = (0..rows * dim).map(|_| rng.random_range(-2.5..2.5)).collect();
            for (j, v) in z.iter_mut().enumerate().filter(|(j, _)| j % 3 == 0) {
                let t = &forest[j % trees];
                let n = &t.nodes[j % t.nodes.len()];
                if n.feature != u32::MAX {
                    *v = n.threshold;
                }
            }
            let want = reference::votes(&forest, &z, dim, k);
            let mut direct = vec![0u32; rows * k];
            for (r, v) in direct.chunks_exact_mut(k).enumerate() {
                forest.iter().for_each(|t| v[t.predict(&z[r * dim..(r + 1) * dim])] += 1);
            }
            proptest::prop_assert_eq!(&want, &direct);
            let mut got = vec![0u32; rows * k];
            Flat::new(&forest, dim).vote(&z, k, &mut got);
            proptest::prop_assert_eq!(&want, &got);
        }
    }

    /// Malformed trees (which `check_shape` rejects on load) vote as the
    /// first version walked them: a split on a feature beyond the rows, a
    /// child beyond the tree, a child before its parent (a cycle), no node;
    /// and `Tree::predict_checked` gives the first version's classes.
    #[test]
    fn flat_votes_as_the_per_tree_walk_on_malformed_trees() {
        let split = |feature, threshold, left_or_class| Node {
            feature,
            threshold,
            left_or_class,
        };
        let trees = [
            vec![split(7, 0.0, 1), leaf(1), leaf(2)],
            vec![split(1, 0.0, 1), leaf(1), leaf(2)],
            vec![split(0, 0.0, 1), split(1, 0.5, 3), leaf(0), leaf(3), leaf(1)],
            // The right child (node 3) is beyond the tree.
            vec![split(0, 0.0, 1), leaf(2), split(1, 0.0, 2)],
            vec![split(0, 0.0, 2), leaf(2), leaf(1)],
            vec![split(0, 0.0, 9), leaf(1)],
            vec![split(0, 0.0, 0)],
            vec![split(0, 0.0, 1), split(1, 0.0, 0), leaf(3)],
            vec![split(0, f64::NAN, 1), leaf(0), leaf(3)],
            vec![leaf(u32::MAX as usize)],
            vec![],
        ];
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let dim = 2;
        let mut z: Vec<f64> = (0..100 * dim).map(|_| rng.random_range(-1.0..1.0)).collect();
        z[..6].copy_from_slice(&[0.0, 0.5, -0.0, f64::NAN, f64::INFINITY, -1.0]);
        for k in [1, 3, 5] {
            // Each tree alone (its class per row) and all together.
            for t in &trees {
                let forest = [Tree { nodes: t.clone() }];
                let mut got = vec![0u32; 100 * k];
                Flat::new(&forest, dim).vote(&z, k, &mut got);
                assert_eq!(got, reference::votes(&forest, &z, dim, k), "{t:?}, k {k}");
                let mut out = vec![0usize; 100];
                reference::predict_rows(&forest[0], &z, dim, &mut out);
                for (r, &c) in out.iter().enumerate() {
                    assert_eq!(forest[0].predict_checked(&z[r * dim..(r + 1) * dim], dim), c);
                }
            }
            let forest: Vec<Tree> = trees.iter().map(|t| Tree { nodes: t.clone() }).collect();
            let mut got = vec![0u32; 100 * k];
            Flat::new(&forest, dim).vote(&z, k, &mut got);
            assert_eq!(got, reference::votes(&forest, &z, dim, k), "k {k}");
        }
        // No rows, no classes, rows wider than the trees' features: no panic.
        let forest: Vec<Tree> = trees.iter().map(|t| Tree { nodes: t.clone() }).collect();
        let flat = Flat::new(&forest, dim);
        flat.vote(&[], 3, &mut []);
        flat.vote(&z, 0, &mut []);
        flat.vote(&z[..3], 3, &mut [0; 3]);
        Flat::new(&forest, 0).vote(&z, 3, &mut [0; 3]);
    }

    #[test]
    fn a_tree_separates_separable_classes_and_stops_at_max_depth() {
        // Class = (x0 > 0.5) + 2 (x1 > 0.5): two splits make it pure.
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let n = 200;
        let x: Vec<f64> = (0..n * 3).map(|_| rng.random_range(0.0..1.0)).collect();
        let y: Vec<usize> = (0..n)
            .map(|i| usize::from(x[i * 3] > 0.5) + 2 * usize::from(x[i * 3 + 1] > 0.5))
            .collect();
        let g = Growth {
            m: 3,
            max_depth: 0,
            min_samples_leaf: 1,
        };
        let t = grow(&x, &y, 3, 4, &g, &mut tree_rng(5, 0));
        let correct = (0..n)
            .filter(|&i| t.predict(&x[i * 3..i * 3 + 3]) == y[i])
            .count();
        // Out-of-bag rows may fall near a threshold; nearly all are right.
        assert!(correct >= n * 95 / 100, "{correct}/{n}");
        let stump = grow(&x, &y, 3, 4, &Growth { max_depth: 1, ..g }, &mut tree_rng(5, 0));
        assert_eq!(stump.nodes.len(), 3, "one split, two leaves");
        // Same seed, same tree.
        assert_eq!(t, grow(&x, &y, 3, 4, &g, &mut tree_rng(5, 0)));
    }

    #[test]
    fn leaves_respect_min_samples_leaf() {
        let x: Vec<f64> = (0..10).map(f64::from).collect();
        let y: Vec<usize> = (0..10).map(|i| usize::from(i == 9)).collect();
        let g = Growth {
            m: 1,
            max_depth: 0,
            min_samples_leaf: 4,
        };
        // Without bootstrap duplicates mattering: every split leaves >= 4 distinct rows a side.
        let t = grow(&x, &y, 1, 2, &g, &mut tree_rng(2, 0));
        for n in &t.nodes {
            if n.feature != u32::MAX {
                let left = x.iter().filter(|&&v| v <= n.threshold).count();
                assert!(left >= 1 && 10 - left >= 1);
            }
        }
        assert!(t.nodes.len() <= 3, "10 rows, leaves of >= 4: at most one split");
    }
}
