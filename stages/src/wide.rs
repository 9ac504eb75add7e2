//! Running hot per-sample loops (the scene's effects, the filter, the
//! encoders) with 256-bit vectors where the CPU has them, and the pieces the
//! lock-step kernels share: the transposes between taxel-major trials and
//! sample-major lanes ([`gather_lanes`], [`scatter_lanes_uninit`]) and one reused
//! scratch buffer per thread ([`with_scratch`]).
//!
//! The release build targets baseline x86-64 (SSE2: two doubles per vector).
//! [`with_avx2`] runs a closure inside a function compiled with AVX2 enabled,
//! chosen once at run time, so the loops inlined into it use four lanes. The
//! function is compiled with AVX2 and FMA (the path requires both), but Rust
//! never contracts `a * b + c` on its own: only an explicit `mul_add` fuses,
//! and that rounds once on every path (the instruction here, the C
//! library's exact `fma` on the baseline). Every IEEE operation rounds the
//! same at either width, so the signals are bit-identical on every x86-64
//! machine (tested: a lab trial simulated both ways, and a trial encoded
//! both ways, give the same bits). Where the CPU
//! also has AVX-512 (F, VL, DQ) the same closure is compiled with it: the
//! same operations, with 32 vector registers instead of 16, which keeps a
//! 16-lane kernel's state out of memory.

use std::cell::Cell;

thread_local! {
    static BASELINE: Cell<bool> = const { Cell::new(false) };
    static NO_512: Cell<bool> = const { Cell::new(false) };
}

/// Runs `f` with this thread's `switch` set, then restores it.
fn with_switch<R>(switch: &'static std::thread::LocalKey<Cell<bool>>, f: impl FnOnce() -> R) -> R {
    let old = switch.with(|b| b.replace(true));
    let r = f();
    switch.with(|b| b.set(old));
    r
}

/// Runs `f` with the AVX-512 paths switched off on this thread (AVX2 stays):
/// for comparing the two on a machine that has both.
pub fn without_avx512<R>(f: impl FnOnce() -> R) -> R {
    with_switch(&NO_512, f)
}

/// Runs `f` with the AVX2 paths switched off on this thread (for comparing
/// the two paths).
pub fn baseline_only<R>(f: impl FnOnce() -> R) -> R {
    with_switch(&BASELINE, f)
}

/// True when the AVX2 path may run on this thread: the CPU has AVX2 and FMA
/// (checked once; `PALPATE_NO_AVX2` set in the environment turns it off)
/// and [`baseline_only`] is not in force.
pub fn avx2() -> bool {
    cpu_avx2() && !BASELINE.with(Cell::get)
}

/// True when the AVX-512 path may run (F, VL and DQ; `PALPATE_NO_AVX512`
/// turns it off, and [`without_avx512`] on this thread).
pub fn avx512() -> bool {
    avx2() && cpu_avx512() && !NO_512.with(Cell::get)
}

fn cpu_avx512() -> bool {
    use std::sync::OnceLock;
    static ON: OnceLock<bool> = OnceLock::new();
    *ON.get_or_init(|| {
        #[cfg(target_arch = "x86_64")]
        {
            std::env::var_os("PALPATE_NO_AVX512").is_none()
                && std::arch::is_x86_feature_detected!("avx512f")
                && std::arch::is_x86_feature_detected!("avx512vl")
                && std::arch::is_x86_feature_detected!("avx512dq")
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            false
        }
    })
}

fn cpu_avx2() -> bool {
    use std::sync::OnceLock;
    static ON: OnceLock<bool> = OnceLock::new();
    *ON.get_or_init(|| {
        #[cfg(target_arch = "x86_64")]
        {
            std::env::var_os("PALPATE_NO_AVX2").is_none()
                && std::arch::is_x86_feature_detected!("avx2")
                && std::arch::is_x86_feature_detected!("fma")
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            false
        }
    })
}

/// Runs `f`, compiled for AVX2 when [`avx2`] says so. `f` and what it calls
/// should be `#[inline]` so they are compiled inside the AVX2 function.
#[inline(always)]
pub fn with_avx2<R>(f: impl FnOnce() -> R) -> R {
    #[cfg(target_arch = "x86_64")]
    {
        #[target_feature(enable = "avx2,fma")]
        fn wide<R>(f: impl FnOnce() -> R) -> R {
            f()
        }
        #[target_feature(enable = "avx2,avx512f,avx512vl,avx512dq")]
        fn wide512<R>(f: impl FnOnce() -> R) -> R {
            f()
        }
        if avx512() {
            // SAFETY: the CPU supports these (checked at run time).
            return unsafe { wide512(f) };
        }
        if avx2() {
            // SAFETY: the CPU supports AVX2 (checked at run time above).
            return unsafe { wide(f) };
        }
    }
    f()
}

/// Rows held in lock step by the lane kernels (filter, encoders): the
/// paper's 4x4 array in one block.
pub const LANES: usize = 16;

/// Appends `rows[l][range]` to `out` sample-major (`out[..][l]`), up to
/// [`LANES`] rows, each sample clamped to `±clamp` when given; missing
/// lanes hold 0. `rows` must hold at least `range.end` samples each.
/// Returns whether every sample read was finite (neither NaN nor ±inf), so
/// that a stage need not read its input a second time to check it.
///
/// Why a kernel of its own: a transpose done one lane at a time walks the
/// sample-major buffer once per lane with 128-byte strides (16 passes
/// through a buffer larger than L2). With AVX2, 4 rows x 4 samples are
/// loaded as four vectors and transposed in registers (4 unpacks, 4 lane
/// swaps), so every byte is read once and written once, whole vectors at a
/// time. Only moves, min and max: the values are bit-exact.
pub fn gather_lanes(
    rows: &[Vec<f64>],
    range: std::ops::Range<usize>,
    out: &mut Vec<[f64; LANES]>,
    clamp: Option<f64>,
) -> bool {
    let w = rows.len().min(LANES);
    let rows = &rows[..w];
    let len = range.end.saturating_sub(range.start);
    assert!(
        rows.iter().all(|r| r.len() >= range.end),
        "gather_lanes: a row is shorter than the range"
    );
    let base = out.len();
    // Written in place of the new rows' storage, not zeroed first: the
    // zeroing was a whole extra write of each tile (the encoders' criterion
    // bench: -8 % without it).
    out.reserve(len);
    let dst = &mut out.spare_capacity_mut()[..len];
    let (done, mut finite) = transpose_in(rows, range.start, dst, clamp);
    let f = |x: f64| match clamp {
        Some(m) => x.clamp(-m, m),
        None => x,
    };
    // Lane `l` of sample `k`, written without reading (or referencing) the
    // uninitialised row.
    let put = |dst: &mut [std::mem::MaybeUninit<[f64; LANES]>], k: usize, l: usize, x: f64| {
        // SAFETY: `k < dst.len()` (the loops below) and `l < LANES`, so the
        // pointer is to lane `l` of the row `k` within `dst`.
        unsafe { dst[k].as_mut_ptr().cast::<f64>().add(l).write(x) }
    };
    // Rows not taken by the vector path, the last few samples, and the
    // missing lanes (0).
    for l in 0..LANES {
        let from = if l < done.0 { done.1 } else { 0 };
        match rows.get(l) {
            Some(row) => {
                for (k, &x) in (from..len).zip(&row[range.start + from..range.end]) {
                    finite &= x.abs() <= f64::MAX;
                    put(dst, k, l, f(x));
                }
            }
            None => (from..len).for_each(|k| put(dst, k, l, 0.0)),
        }
    }
    // SAFETY: every lane of rows `base .. base + len` is now written: lanes
    // below `done.0` of samples below `done.1` by `transpose_in`, every
    // other lane and sample by the loop above; the capacity was reserved.
    unsafe { out.set_len(base + len) };
    finite
}

/// Writes `src[..][l]` to samples `offset .. offset + src.len()` of row
/// `l` (up to [`LANES`] rows), the inverse of [`gather_lanes`], by the same
/// in-register transposes, into rows that are allocated but not yet
/// filled: every row must be empty (`len() == 0`) with capacity for
/// `offset + src.len()` samples. The caller sets each row's length once every
/// sample below it has been written (by calls covering `0..n`).
///
/// Why: an output zeroed only to be overwritten costs a whole extra write
/// of the trial (glibc's `calloc` clears reused memory: 18 % of the
/// low-pass on the quickstart, `perf`).
pub fn scatter_lanes_uninit(src: &[[f64; LANES]], rows: &mut [Vec<f64>], offset: usize) {
    let w = rows.len().min(LANES);
    let rows = &mut rows[..w];
    assert!(
        rows.iter()
            .all(|r| r.is_empty() && r.capacity() >= offset + src.len()),
        "scatter_lanes_uninit: a row is not empty or too small"
    );
    // Writes only through raw pointers within each row's capacity.
    let done = transpose_out(src, rows, offset);
    for (l, row) in rows.iter_mut().enumerate() {
        let from = if l < done.0 { done.1 } else { 0 };
        for (d, s) in row.spare_capacity_mut()[offset + from..offset + src.len()]
            .iter_mut()
            .zip(&src[from..])
        {
            d.write(s[l]);
        }
    }
}

/// The vector part of [`gather_lanes`]: `(rows, samples)` done (the first
/// `rows` rows, a multiple of 4, over the first `samples` samples, a
/// multiple of 4), or `(0, 0)` without AVX2; and whether what it read was
/// finite.
fn transpose_in(
    rows: &[Vec<f64>],
    start: usize,
    dst: &mut [std::mem::MaybeUninit<[f64; LANES]>],
    clamp: Option<f64>,
) -> ((usize, usize), bool) {
    #[cfg(target_arch = "x86_64")]
    if avx2() {
        let groups = rows.len() / 4;
        let n4 = dst.len() / 4 * 4;
        // SAFETY: AVX2 is present (checked); every row holds
        // `start + dst.len()` samples (asserted by the caller) and the
        // kernel reads rows `< 4·groups` at `start .. start + n4` and
        // writes `dst[..n4]`, lanes `< 4·groups`.
        let finite = unsafe { x86::transpose_in(rows, groups, start, n4, dst, clamp) };
        return ((4 * groups, n4), finite);
    }
    let _ = (rows, start, dst, clamp);
    ((0, 0), true)
}

/// The vector part of [`scatter_lanes_uninit`], as [`transpose_in`].
fn transpose_out(src: &[[f64; LANES]], rows: &mut [Vec<f64>], offset: usize) -> (usize, usize) {
    #[cfg(target_arch = "x86_64")]
    if avx2() {
        let groups = rows.len() / 4;
        let n4 = src.len() / 4 * 4;
        // SAFETY: AVX2 is present; rows have the capacity for `offset +
        // src.len()` samples (asserted by the caller); reads `src[..n4]`,
        // writes rows `< 4·groups` at `offset .. offset + n4` through raw
        // pointers (never reading the row).
        unsafe { x86::transpose_out(src, groups, n4, rows, offset) };
        return (4 * groups, n4);
    }
    let _ = (src, rows, offset);
    (0, 0)
}

/// The transpose of an 8 x 8 tile of `f32` (rows in, columns out): the
/// k-NN scan's tiles and the RBM trainer's weight transposes.
#[cfg(target_arch = "x86_64")]
#[inline]
#[target_feature(enable = "avx2")]
pub(crate) fn transpose8_ps(r: [std::arch::x86_64::__m256; 8]) -> [std::arch::x86_64::__m256; 8] {
    use std::arch::x86_64::*;
    let t0 = _mm256_unpacklo_ps(r[0], r[1]);
    let t1 = _mm256_unpackhi_ps(r[0], r[1]);
    let t2 = _mm256_unpacklo_ps(r[2], r[3]);
    let t3 = _mm256_unpackhi_ps(r[2], r[3]);
    let t4 = _mm256_unpacklo_ps(r[4], r[5]);
    let t5 = _mm256_unpackhi_ps(r[4], r[5]);
    let t6 = _mm256_unpacklo_ps(r[6], r[7]);
    let t7 = _mm256_unpackhi_ps(r[6], r[7]);
    let u0 = _mm256_shuffle_ps::<0x44>(t0, t2);
    let u1 = _mm256_shuffle_ps::<0xEE>(t0, t2);
    let u2 = _mm256_shuffle_ps::<0x44>(t1, t3);
    let u3 = _mm256_shuffle_ps::<0xEE>(t1, t3);
    let u4 = _mm256_shuffle_ps::<0x44>(t4, t6);
    let u5 = _mm256_shuffle_ps::<0xEE>(t4, t6);
    let u6 = _mm256_shuffle_ps::<0x44>(t5, t7);
    let u7 = _mm256_shuffle_ps::<0xEE>(t5, t7);
    [
        _mm256_permute2f128_ps::<0x20>(u0, u4),
        _mm256_permute2f128_ps::<0x20>(u1, u5),
        _mm256_permute2f128_ps::<0x20>(u2, u6),
        _mm256_permute2f128_ps::<0x20>(u3, u7),
        _mm256_permute2f128_ps::<0x31>(u0, u4),
        _mm256_permute2f128_ps::<0x31>(u1, u5),
        _mm256_permute2f128_ps::<0x31>(u2, u6),
        _mm256_permute2f128_ps::<0x31>(u3, u7),
    ]
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    use super::LANES;
    use std::arch::x86_64::*;

    /// Transposes a 4 x 4 block of doubles held as four row vectors.
    #[inline(always)]
    unsafe fn t4(r: [__m256d; 4]) -> [__m256d; 4] {
        let t0 = _mm256_unpacklo_pd(r[0], r[1]);
        let t1 = _mm256_unpackhi_pd(r[0], r[1]);
        let t2 = _mm256_unpacklo_pd(r[2], r[3]);
        let t3 = _mm256_unpackhi_pd(r[2], r[3]);
        [
            _mm256_permute2f128_pd(t0, t2, 0x20),
            _mm256_permute2f128_pd(t1, t3, 0x20),
            _mm256_permute2f128_pd(t0, t2, 0x31),
            _mm256_permute2f128_pd(t1, t3, 0x31),
        ]
    }

    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn transpose_in(
        rows: &[Vec<f64>],
        groups: usize,
        start: usize,
        n4: usize,
        dst: &mut [std::mem::MaybeUninit<[f64; LANES]>],
        clamp: Option<f64>,
    ) -> bool {
        let abs = _mm256_set1_pd(f64::from_bits(!(1u64 << 63)));
        let max = _mm256_set1_pd(f64::MAX);
        let mut bad = _mm256_setzero_pd();
        let clamped = clamp.is_some();
        let (lo, hi) = match clamp {
            Some(m) => (_mm256_set1_pd(-m), _mm256_set1_pd(m)),
            None => (_mm256_set1_pd(f64::NEG_INFINITY), _mm256_set1_pd(f64::INFINITY)),
        };
        let out = dst.as_mut_ptr() as *mut f64;
        for g in 0..groups {
            let p: [*const f64; 4] = std::array::from_fn(|k| rows[4 * g + k].as_ptr().add(start));
            let mut t = 0;
            while t < n4 {
                // x < hi ? x : hi, then x > lo ? x : lo: f64::clamp for finite x.
                let r = std::array::from_fn(|k| {
                    let x = _mm256_loadu_pd(p[k].add(t));
                    // Not (|x| <= MAX): NaN or ±inf.
                    bad = _mm256_or_pd(bad, _mm256_cmp_pd::<_CMP_NLE_UQ>(_mm256_and_pd(x, abs), max));
                    if clamped {
                        _mm256_max_pd(_mm256_min_pd(x, hi), lo)
                    } else {
                        x
                    }
                });
                let c = t4(r);
                for (j, v) in c.into_iter().enumerate() {
                    _mm256_storeu_pd(out.add((t + j) * LANES + 4 * g), v);
                }
                t += 4;
            }
        }
        _mm256_movemask_pd(bad) == 0
    }

    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn transpose_out(
        src: &[[f64; LANES]],
        groups: usize,
        n4: usize,
        rows: &mut [Vec<f64>],
        offset: usize,
    ) {
        let inp = src.as_ptr() as *const f64;
        for g in 0..groups {
            let p: [*mut f64; 4] = std::array::from_fn(|k| rows[4 * g + k].as_mut_ptr().add(offset));
            let mut t = 0;
            while t < n4 {
                let r = std::array::from_fn(|j| _mm256_loadu_pd(inp.add((t + j) * LANES + 4 * g)));
                let c = t4(r);
                for (k, v) in c.into_iter().enumerate() {
                    _mm256_storeu_pd(p[k].add(t), v);
                }
                t += 4;
            }
        }
    }
}

thread_local! {
    static SCRATCH: std::cell::RefCell<Vec<[f64; LANES]>> = const { std::cell::RefCell::new(Vec::new()) };
}

/// Largest scratch buffer kept between calls (bytes): 64 MiB is 131 s of a
/// 16-taxel trial at 4 kHz; a longer trial's buffer is freed after use.
const SCRATCH_KEEP_BYTES: usize = 64 << 20;

/// Runs `f` with this thread's sample-major scratch buffer (empty on entry).
///
/// Why: the lane kernels (filter, encoders) transpose each trial into a
/// buffer as large as the trial (2.8 MB for a 21 s lab trial); allocating it
/// afresh for every trial costs a page fault and a page clear per 4 kB,
/// about as much as the arithmetic of a simple pass. One buffer per thread,
/// reused trial after trial, keeps memory flat in the number of trials (it
/// is as large as the longest trial seen, up to `SCRATCH_KEEP_BYTES`). A
/// nested call gets a fresh buffer.
pub fn with_scratch<R>(f: impl FnOnce(&mut Vec<[f64; LANES]>) -> R) -> R {
    SCRATCH.with(|cell| match cell.try_borrow_mut() {
        Ok(mut buf) => {
            buf.clear();
            let r = f(&mut buf);
            if buf.capacity() * std::mem::size_of::<[f64; LANES]>() > SCRATCH_KEEP_BYTES {
                *buf = Vec::new();
            }
            r
        }
        Err(_) => f(&mut Vec::new()),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rows(w: usize, n: usize) -> Vec<Vec<f64>> {
        (0..w)
            .map(|l| (0..n).map(|k| (l * 1000 + k) as f64 * 0.5 - 7.0).collect())
            .collect()
    }

    /// The transposes put every sample where the lane-by-lane definition
    /// does, on both paths, for any row count (partial groups of 4, more
    /// than 16) and any length and start (partial groups of 4 samples).
    #[test]
    fn transposes_match_the_definition_on_both_paths() {
        for w in [1, 3, 4, 5, 8, 15, 16, 17] {
            for n in [0, 1, 3, 4, 7, 64, 69] {
                for start in [0, 1, 5] {
                    let r = rows(w, n + start);
                    let mut want = vec![[0.0; LANES]; n];
                    for (l, row) in r.iter().take(LANES).enumerate() {
                        for k in 0..n {
                            want[k][l] = row[start + k].clamp(-100.0, 100.0);
                        }
                    }
                    for base in [false, true] {
                        let run = || {
                            let mut out = vec![[9.0; LANES]];
                            let finite = gather_lanes(&r, start..start + n, &mut out, Some(100.0));
                            (out, finite)
                        };
                        let (out, finite) = if base { baseline_only(run) } else { run() };
                        assert!(finite);
                        assert_eq!(out[0], [9.0; LANES], "existing rows are kept");
                        assert_eq!(&out[1..], &want[..], "w {w} n {n} start {start} base {base}");
                        // Into unfilled rows, in two calls covering 0..n
                        // (the second part first, as the low-pass does).
                        let mut fresh: Vec<Vec<f64>> = (0..w).map(|_| Vec::with_capacity(n)).collect();
                        let h = n / 2;
                        let mut fill = || {
                            scatter_lanes_uninit(&out[1 + h..], &mut fresh, h);
                            scatter_lanes_uninit(&out[1..1 + h], &mut fresh, 0);
                        };
                        if base {
                            baseline_only(fill)
                        } else {
                            fill()
                        }
                        for (l, row) in fresh.iter_mut().enumerate().take(LANES) {
                            // SAFETY: the two calls wrote samples 0..n of the lanes below LANES.
                            unsafe { row.set_len(n) };
                            let want_l: Vec<f64> = want.iter().map(|s| s[l]).collect();
                            assert_eq!(*row, want_l, "uninit scatter w {w} n {n} lane {l}");
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn gather_notes_non_finite_samples_anywhere() {
        for w in [4, 6, 16] {
            for k in [0, 3, 4, 37, 38] {
                for bad in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
                    let mut r = rows(w, 39);
                    r[w - 1][k] = bad;
                    for base in [false, true] {
                        let run = || gather_lanes(&r, 0..39, &mut Vec::new(), None);
                        let finite = if base { baseline_only(run) } else { run() };
                        assert!(!finite, "w {w} k {k} {bad} base {base}");
                    }
                }
            }
        }
        let extremes = vec![vec![f64::MAX, f64::MIN, 0.0, -0.0, 5e-324]; 8];
        assert!(gather_lanes(&extremes, 0..5, &mut Vec::new(), None));
        // An unclamped gather keeps the values exactly (no min/max applied).
        let mut out = Vec::new();
        gather_lanes(&extremes, 0..5, &mut out, None);
        assert_eq!(out[0][7], f64::MAX);
        assert_eq!(out[3][0].to_bits(), (-0.0f64).to_bits());
    }

    #[test]
    fn scratch_is_empty_on_entry_and_nests() {
        with_scratch(|a| {
            assert!(a.is_empty());
            a.push([1.0; LANES]);
            with_scratch(|b| {
                assert!(b.is_empty());
                b.push([2.0; LANES]);
            });
            assert_eq!(a.len(), 1);
        });
        with_scratch(|a| assert!(a.is_empty()));
    }
}
