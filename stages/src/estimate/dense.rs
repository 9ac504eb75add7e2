//! Small dense kernels shared by the trained baselines: row-against-row
//! products `C = A Bᵀ` (`C[i][j] = a_i · b_j`) and squared distances
//! (`C[i][j] = ‖a_i − b_j‖²`) of row-major `f64` matrices.
//!
//! Why by hand rather than `matrixmultiply`/`gemm`: those crates pick an FMA
//! kernel at run time, so the bits of every dot product would depend on the
//! CPU, and a single-row call (a stream's frame) could differ from the batch
//! call over the same row. Here every entry is computed exactly as the
//! scalar [`dot`] / [`sq_dist`] compute it (four partial sums over chunks of
//! four, reduced as `(s0 + s1) + (s2 + s3)`, then the remainder in order, no
//! FMA), so a frame scored alone, a batch, the AVX2 and the SSE2 path all
//! give the same bits. The speed comes from register tiling: a tile of 2 rows
//! of `A` against 4 rows of `B` keeps 8 four-lane accumulators in registers
//! and loads each chunk once per tile instead of once per entry, compiled
//! with AVX2 where the CPU has it ([`crate::wide::with_avx2`]). The shapes
//! here are small (dims 16-80, tens to thousands of rows), where a blocked
//! GEMM's packing would not pay anyway.

/// Rows of `A` per tile.
const MR: usize = 2;
/// Rows of `B` per tile.
const NR: usize = 4;

/// Dot product over fixed-width chunks (vectorises) with a fixed summation
/// order, so the same bits on every run and every path.
#[inline]
pub fn dot(a: &[f64], b: &[f64]) -> f64 {
    let mut acc = [0.0f64; 4];
    let ca = a.chunks_exact(4);
    let cb = b.chunks_exact(4);
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for l in 0..4 {
            acc[l] += x[l] * y[l];
        }
    }
    let mut s = (acc[0] + acc[1]) + (acc[2] + acc[3]);
    for (x, y) in ra.iter().zip(rb) {
        s += x * y;
    }
    s
}

/// `‖a − b‖²` with four partial sums in a fixed order (same bits everywhere).
#[inline]
pub fn sq_dist(a: &[f64], b: &[f64]) -> f64 {
    let mut acc = [0.0f64; 4];
    let ca = a.chunks_exact(4);
    let cb = b.chunks_exact(4);
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for l in 0..4 {
            let d = x[l] - y[l];
            acc[l] += d * d;
        }
    }
    let mut s = (acc[0] + acc[1]) + (acc[2] + acc[3]);
    for (x, y) in ra.iter().zip(rb) {
        let d = x - y;
        s += d * d;
    }
    s
}

/// One entry's contribution: a product or a squared difference.
#[inline(always)]
fn term<const SQ: bool>(x: f64, y: f64) -> f64 {
    if SQ {
        let d = x - y;
        d * d
    } else {
        x * y
    }
}

/// The full tile: rows `a[0..MR]` against rows `b[0..NR]`, each `k` long;
/// entry `(r, c)` goes to `out[r][c]`, with the bits of [`dot`] / [`sq_dist`].
#[inline(always)]
fn tile<const SQ: bool>(a: [&[f64]; MR], b: [&[f64]; NR], k: usize) -> [[f64; NR]; MR] {
    let mut acc = [[[0.0f64; 4]; NR]; MR];
    // Zipped exact chunks: every load is a whole 4-lane vector with no
    // bounds check left in the loop, so the 8 accumulators stay in registers.
    let chunks = |x: &[f64]| -> std::slice::ChunksExact<'_, f64> { x[..k].chunks_exact(4) };
    let it = chunks(a[0])
        .zip(chunks(a[1]))
        .zip(chunks(b[0]))
        .zip(chunks(b[1]))
        .zip(chunks(b[2]))
        .zip(chunks(b[3]));
    for (((((a0, a1), b0), b1), b2), b3) in it {
        let av = [a0, a1];
        let bv = [b0, b1, b2, b3];
        for r in 0..MR {
            for c in 0..NR {
                for l in 0..4 {
                    acc[r][c][l] += term::<SQ>(av[r][l], bv[c][l]);
                }
            }
        }
    }
    let full = k / 4 * 4;
    let mut out = [[0.0f64; NR]; MR];
    for r in 0..MR {
        for c in 0..NR {
            let q = &acc[r][c];
            let mut s = (q[0] + q[1]) + (q[2] + q[3]);
            for t in full..k {
                s += term::<SQ>(a[r][t], b[c][t]);
            }
            out[r][c] = s;
        }
    }
    out
}

#[inline(always)]
fn pairwise<const SQ: bool>(a: &[f64], b: &[f64], k: usize, out: &mut [f64]) {
    let k1 = k.max(1);
    let m = a.len() / k1;
    let n = b.len() / k1;
    debug_assert_eq!(out.len(), m * n);
    fn row(x: &[f64], i: usize, k: usize) -> &[f64] {
        &x[i * k..(i + 1) * k]
    }
    let mut i = 0;
    while i + MR <= m {
        let ar: [&[f64]; MR] = std::array::from_fn(|r| row(a, i + r, k));
        let mut j = 0;
        while j + NR <= n {
            let br: [&[f64]; NR] = std::array::from_fn(|c| row(b, j + c, k));
            let t = tile::<SQ>(ar, br, k);
            for (r, tr) in t.iter().enumerate() {
                out[(i + r) * n + j..(i + r) * n + j + NR].copy_from_slice(tr);
            }
            j += NR;
        }
        for j in j..n {
            for (r, a_r) in ar.iter().enumerate() {
                out[(i + r) * n + j] = single::<SQ>(a_r, row(b, j, k));
            }
        }
        i += MR;
    }
    for i in i..m {
        for j in 0..n {
            out[i * n + j] = single::<SQ>(row(a, i, k), row(b, j, k));
        }
    }
}

#[inline(always)]
fn single<const SQ: bool>(x: &[f64], y: &[f64]) -> f64 {
    if SQ {
        sq_dist(x, y)
    } else {
        dot(x, y)
    }
}

/// `out[i·n + j] = dot(a_i, b_j)` for the `m = a.len()/k` rows of `a` and the
/// `n = b.len()/k` rows of `b` (both row-major, `k` wide): the same bits as
/// [`dot`] entry by entry.
pub fn gemm_nt(a: &[f64], b: &[f64], k: usize, out: &mut [f64]) {
    crate::wide::with_avx2(|| pairwise::<false>(a, b, k, out));
}

/// `out[i·n + j] = sq_dist(a_i, b_j)`, as [`gemm_nt`]: the same bits as
/// [`sq_dist`] entry by entry.
pub fn sq_dists(a: &[f64], b: &[f64], k: usize, out: &mut [f64]) {
    crate::wide::with_avx2(|| pairwise::<true>(a, b, k, out));
}

/// Adds `bias[j]` to every row of `out` (`bias.len()` wide) and applies `f` to each entry.
pub fn add_bias_map(out: &mut [f64], bias: &[f64], f: impl Fn(f64) -> f64) {
    for row in out.chunks_exact_mut(bias.len().max(1)) {
        row.iter_mut().zip(bias).for_each(|(o, b)| *o = f(*o + b));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn tiles_match_the_scalar_kernels_bit_for_bit() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        // Shapes that exercise full tiles, ragged edges and a k remainder.
        for (m, n, k) in [
            (5, 9, 7),
            (2, 4, 8),
            (1, 1, 3),
            (7, 13, 80),
            (4, 3, 16),
            (3, 0, 5),
        ] {
            let a: Vec<f64> = (0..m * k).map(|_| rng.random_range(-3.0..3.0)).collect();
            let b: Vec<f64> = (0..n * k).map(|_| rng.random_range(-3.0..3.0)).collect();
            let mut g = vec![f64::NAN; m * n];
            let mut d = vec![f64::NAN; m * n];
            gemm_nt(&a, &b, k, &mut g);
            sq_dists(&a, &b, k, &mut d);
            let base = crate::wide::baseline_only(|| {
                let mut g2 = vec![0.0; m * n];
                gemm_nt(&a, &b, k, &mut g2);
                g2
            });
            for i in 0..m {
                for j in 0..n {
                    let (x, y) = (&a[i * k..(i + 1) * k], &b[j * k..(j + 1) * k]);
                    assert_eq!(
                        g[i * n + j].to_bits(),
                        dot(x, y).to_bits(),
                        "dot {m}x{n}x{k} ({i},{j})"
                    );
                    assert_eq!(d[i * n + j].to_bits(), sq_dist(x, y).to_bits(), "dist ({i},{j})");
                    assert_eq!(base[i * n + j].to_bits(), g[i * n + j].to_bits());
                }
            }
        }
    }
}
