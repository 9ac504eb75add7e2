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
//! The counting sort keeps four interleaved counts per rank (rows of one
//! rank, e.g. the many zero spike counts, then increment four counters in
//! turn rather than one, which would serialise on the store). The sweep
//! keeps `S_L` and the cross term `X = Σ_c N_c L_c`, and takes
//! `S_R = Σ_c N_c² − 2X + S_L` at the boundaries: the same integer as
//! updating `S_R` row by row.
//!
//! Nodes are stored flat in depth-first order. Prediction walks a block of
//! rows through one tree at a time ([`Tree::predict_rows`]): each step moves
//! every row of the block that is not yet on a leaf one level down,
//! branch-free (`next = left + (x[f] > threshold)`), and the rows still
//! walking are kept in a list compacted without a branch, so the load
//! latencies of the block's rows overlap instead of adding up.
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

/// Rows that [`Tree::predict_rows`] walks down a tree together.
const BLOCK: usize = 32;

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

    /// [`Self::predict`] of each row of `z` (row-major, `dim` wide) into
    /// `out` (one class per row, `out.len()` rows).
    ///
    /// The rows go down a block at a time, level by level: a step moves each
    /// row of the block that is not yet on a leaf from its node to
    /// `left + (z[feature] > threshold)`, without a branch on the row's path
    /// (the rows still walking are kept in a list compacted branch-free at
    /// every step), so the load latencies of the block's rows overlap instead
    /// of adding up. Unlike [`Self::predict`] this never panics: a row
    /// missing from `z`, a row stopped at a split on a feature beyond `dim`,
    /// and a row whose walk leaves the tree (a malformed tree, which
    /// `check_shape` rejects on load) get class `usize::MAX`.
    pub fn predict_rows(&self, z: &[f64], dim: usize, out: &mut [usize]) {
        let nodes = &self.nodes[..];
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
        spill: Vec::with_capacity(len),
        bins: vec![0; LANES * widest],
        counts: vec![0; p.k],
        left: vec![0; p.k],
    };
    let mut nodes = vec![leaf(0)];
    // Depth-first with an explicit stack: (node, rows range, depth).
    let mut stack = vec![(0usize, 0usize, len, 0usize)];
    while let Some((node, lo, hi, depth)) = stack.pop() {
        let part = &mut rows[lo..hi];
        b.class_counts(part);
        nodes[node] = leaf(first_max(&b.counts));
        let pure = b.counts.iter().filter(|&&c| c > 0).count() <= 1;
        if pure || (g.max_depth > 0 && depth >= g.max_depth) || part.len() < 2 * g.min_samples_leaf.max(1) {
            continue;
        }
        let Some((feature, threshold)) = b.best_split(part, rng) else {
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
        stack.push((left + 1, mid, hi, depth + 1));
        stack.push((left, lo, mid, depth + 1));
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

/// Interleaved counts per rank in the counting sort.
const LANES: usize = 4;

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
    /// The node's rows as `rank << 32 | row`, in ascending order.
    keys: Vec<u64>,
    /// Rows going right while partitioning.
    spill: Vec<u32>,
    /// Counting-sort bins.
    bins: Vec<u32>,
    /// The node's weighted class counts.
    counts: Vec<u64>,
    /// Weighted class counts left of the sweep.
    left: Vec<u64>,
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
    fn best_split(&mut self, rows: &[u32], rng: &mut ChaCha8Rng) -> Option<(u32, f64)> {
        let Builder {
            p,
            g,
            cw,
            features,
            ranks,
            keys,
            bins,
            counts,
            left,
            ..
        } = self;
        let dim = p.dim;
        if dim == 0 || rows.is_empty() {
            return None;
        }
        let len = rows.len();
        let total: u64 = counts.iter().sum();
        let s_all: u64 = counts.iter().map(|c| c * c).sum();
        let min_leaf = g.min_samples_leaf.max(1);
        let m = g.m.clamp(1, dim);
        let ranks = &mut ranks[..len];
        let keys = &mut keys[..len];
        let mut best: Option<(f64, u32, f64)> = None;
        for t in 0..dim {
            if t >= m && best.is_some() {
                break;
            }
            // Partial Fisher–Yates: feature t of this node's random order.
            let j = rng.random_range(t..dim);
            features.swap(t, j);
            let f = features[t] as usize;
            let (col, vals) = p.feature(f);
            let (mut lo, mut hi) = (u32::MAX, 0u32);
            // The rows in ascending order of rank: a counting sort when the
            // feature has few distinct values for the node's rows, else a
            // sort of `rank << 32 | row` keys.
            if vals.len() <= 4 * len {
                // Four interleaved counts per rank, so that runs of rows of
                // one rank (common: many zeros) are four chains, not one.
                let bins = &mut bins[..LANES * vals.len()];
                bins.iter_mut().for_each(|c| *c = 0);
                for (q, (r, &i)) in ranks.iter_mut().zip(rows).enumerate() {
                    let v = col[i as usize];
                    *r = v;
                    lo = lo.min(v);
                    hi = hi.max(v);
                    bins[LANES * v as usize + q % LANES] += 1;
                }
                if vals[lo as usize] >= vals[hi as usize] {
                    continue; // constant here
                }
                let mut at = 0;
                for c in &mut bins[LANES * lo as usize..LANES * (hi as usize + 1)] {
                    (*c, at) = (at, at + *c);
                }
                for (q, (&r, &i)) in ranks.iter().zip(rows).enumerate() {
                    let at = &mut bins[LANES * r as usize + q % LANES];
                    keys[*at as usize] = u64::from(r) << 32 | u64::from(i);
                    *at += 1;
                }
            } else {
                for (key, &i) in keys.iter_mut().zip(rows) {
                    let v = col[i as usize];
                    lo = lo.min(v);
                    hi = hi.max(v);
                    *key = u64::from(v) << 32 | u64::from(i);
                }
                if vals[lo as usize] >= vals[hi as usize] {
                    continue; // constant here
                }
                keys.sort_unstable();
            }
            left.iter_mut().for_each(|c| *c = 0);
            // S_L = Σ L_c², and S_R = Σ (N_c − L_c)² = Σ N_c² − 2 Σ N_c L_c + S_L
            // from the cross term X = Σ N_c L_c (exact integers, so the same
            // S_R as one updated row by row).
            let mut s_left = 0u64;
            let mut cross = 0u64;
            let mut n_left = 0u64;
            for (q, &key) in keys.iter().enumerate() {
                let rw = cw[key as u32 as usize];
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
                let (v, next) = (vals[r], vals[next_r]);
                if next <= v || q + 1 < min_leaf || len - (q + 1) < min_leaf {
                    continue;
                }
                let n_right = total - n_left;
                let s_right = s_all + s_left - 2 * cross;
                let score = s_left as f64 / n_left as f64 + s_right as f64 / n_right as f64;
                if best.is_none_or(|(b, _, _)| score > b) {
                    let mut thr = v + (next - v) / 2.0;
                    if thr >= next {
                        thr = v; // halfway rounded up to `next`: split at v itself
                    }
                    best = Some((score, f as u32, thr));
                }
            }
        }
        best.map(|(_, f, thr)| (f, thr))
    }

    /// Puts the rows of `rows` with `x[feature] <= threshold` first, both
    /// sides in their order; returns how many go left.
    fn partition(&mut self, rows: &mut [u32], feature: usize, threshold: f64) -> usize {
        let (col, vals) = self.p.feature(feature);
        self.spill.clear();
        let mut l = 0;
        for q in 0..rows.len() {
            let i = rows[q];
            if vals[col[i as usize] as usize] <= threshold {
                rows[l] = i;
                l += 1;
            } else {
                self.spill.push(i);
            }
        }
        rows[l..].copy_from_slice(&self.spill);
        l
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The first version's growth, kept as the reference the ranks must
    /// match: per node and drawn feature, the `(value, row)` pairs sorted by
    /// `f64::total_cmp` and swept.
    mod reference {
        use super::super::{first_max, leaf, Growth, Node, Tree};
        use rand::Rng;
        use rand_chacha::ChaCha8Rng;

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

        /// Blocked prediction gives each row the class [`Tree::predict`] gives it.
        #[test]
        fn predict_rows_equals_predict(
            n in 1usize..80,
            rows in 0usize..70,
            dim in 1usize..6,
            k in 1usize..5,
            seed in 0u64..1000,
        ) {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let x: Vec<f64> = (0..n * dim).map(|_| rng.random_range(-2.0..2.0)).collect();
            let y: Vec<usize> = (0..n).map(|_| rng.random_range(0..k)).collect();
            let g = Growth { m: 2, max_depth: 0, min_samples_leaf: 1 };
            let t = grow(&x, &y, dim, k, &g, &mut tree_rng(seed, 0));
            // New rows, some exactly on the thresholds.
            let mut z: Vec<f64> = (0..rows * dim).map(|_| rng.random_range(-2.5..2.5)).collect();
            for (j, v) in z.iter_mut().enumerate().filter(|(j, _)| j % 3 == 0) {
                let n = &t.nodes[j % t.nodes.len()];
                if n.feature != u32::MAX {
                    *v = n.threshold;
                }
            }
            let mut got = vec![0usize; rows];
            t.predict_rows(&z, dim, &mut got);
            for (i, &c) in got.iter().enumerate() {
                proptest::prop_assert_eq!(c, t.predict(&z[i * dim..(i + 1) * dim]));
            }
        }
    }

    #[test]
    fn predict_rows_never_panics_on_a_malformed_tree() {
        let t = Tree {
            nodes: vec![
                Node {
                    feature: 7,
                    threshold: 0.0,
                    left_or_class: 1,
                },
                leaf(1),
                leaf(2),
            ],
        };
        let mut out = [0usize; 3];
        // Feature 7 is beyond the rows: the walk stops there; row 3 is missing.
        t.predict_rows(&[1.0, 2.0, 3.0, 4.0], 2, &mut out);
        assert_eq!(out, [usize::MAX; 3]);
        // Without that split, rows 1 and 2 get their leaves, row 3 still none.
        let mut ok = t.clone();
        ok.nodes[0].feature = 1;
        ok.predict_rows(&[1.0, 2.0, 3.0, -4.0], 2, &mut out);
        assert_eq!(out, [2, 1, usize::MAX]);
        let cycle = Tree {
            nodes: vec![Node {
                feature: 0,
                threshold: 0.0,
                left_or_class: 0,
            }],
        };
        cycle.predict_rows(&[-1.0], 1, &mut out[..1]);
        assert_eq!(out[0], usize::MAX);
        Tree { nodes: vec![] }.predict_rows(&[1.0], 1, &mut out[..1]);
        assert_eq!(out[0], usize::MAX);
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
