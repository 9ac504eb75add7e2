//! The inner kernels of WSS (a complex multiply-accumulate over frequency
//! bins, one taxel or a group of [`TAXEL_GROUP`] at a time, and a real dot
//! product over taxels), compiled for the baseline target and, on x86-64
//! CPUs that have them (checked once at run time), with AVX2 and FMA
//! enabled (the taxel groups also with AVX-512), which widens the vectors
//! and fuses each multiply-add. The fused and unfused results differ by
//! rounding only (~1e-16); the vector widths of the fused kernels do not
//! change a bit.

/// True when the AVX2 + FMA versions may run.
#[inline]
pub(crate) fn fast_cpu() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

#[inline(always)]
fn madd<const FMA: bool>(a: f64, b: f64, c: f64) -> f64 {
    if FMA {
        a.mul_add(b, c)
    } else {
        a * b + c
    }
}

/// `acc += x ⊙ h` over complex bins held as (re, im) slices of equal length.
#[inline(always)]
fn cmac_impl<const FMA: bool>(
    ar: &mut [f64],
    ai: &mut [f64],
    xr: &[f64],
    xi: &[f64],
    hr: &[f64],
    hi: &[f64],
) {
    let n = ar.len();
    let (ai, xr, xi, hr, hi) = (&mut ai[..n], &xr[..n], &xi[..n], &hr[..n], &hi[..n]);
    for f in 0..n {
        ar[f] = madd::<FMA>(xr[f], hr[f], madd::<FMA>(-xi[f], hi[f], ar[f]));
        ai[f] = madd::<FMA>(xr[f], hi[f], madd::<FMA>(xi[f], hr[f], ai[f]));
    }
}

#[cfg(target_arch = "x86_64")]
/// # Safety
/// The CPU must support AVX2 and FMA.
#[target_feature(enable = "avx2,fma")]
unsafe fn cmac_avx2(ar: &mut [f64], ai: &mut [f64], xr: &[f64], xi: &[f64], hr: &[f64], hi: &[f64]) {
    cmac_impl::<true>(ar, ai, xr, xi, hr, hi)
}

/// `acc += x ⊙ h` (complex, split parts); `fast` from [`fast_cpu`].
#[inline]
pub(crate) fn cmac(
    fast: bool,
    ar: &mut [f64],
    ai: &mut [f64],
    xr: &[f64],
    xi: &[f64],
    hr: &[f64],
    hi: &[f64],
) {
    #[cfg(target_arch = "x86_64")]
    if fast {
        // SAFETY: `fast` comes from `fast_cpu`, which checked that this CPU
        // supports AVX2 and FMA.
        unsafe { cmac_avx2(ar, ai, xr, xi, hr, hi) };
        return;
    }
    let _ = fast;
    cmac_impl::<false>(ar, ai, xr, xi, hr, hi)
}

/// Taxels per pass of [`cmac_group`].
pub(crate) const TAXEL_GROUP: usize = 4;

/// `acc += Σ_t x_t ⊙ h_t` over a group of [`TAXEL_GROUP`] taxels, each bin's
/// sum kept in a register across the group. Per bin the operations are
/// those of [`cmac`] called taxel after taxel (the same fused multiply-adds
/// in the same order), so the bits are too; what changes is that the
/// accumulator is loaded and stored once a group instead of once a taxel.
/// Taxel by taxel, every pass stored the accumulator and the next pass
/// loaded it back: `perf annotate` put two thirds of the kernel's samples
/// on those reloads.
#[inline(always)]
fn cmac_group_impl<const FMA: bool>(
    ar: &mut [f64],
    ai: &mut [f64],
    x: [(&[f64], &[f64]); TAXEL_GROUP],
    h: [(&[f64], &[f64]); TAXEL_GROUP],
) {
    let n = ar.len();
    let ai = &mut ai[..n];
    let x = x.map(|(r, i)| (&r[..n], &i[..n]));
    let h = h.map(|(r, i)| (&r[..n], &i[..n]));
    for f in 0..n {
        let (mut r, mut i) = (ar[f], ai[f]);
        for t in 0..TAXEL_GROUP {
            let (xr, xi) = (x[t].0[f], x[t].1[f]);
            let (hr, hi) = (h[t].0[f], h[t].1[f]);
            r = madd::<FMA>(xr, hr, madd::<FMA>(-xi, hi, r));
            i = madd::<FMA>(xr, hi, madd::<FMA>(xi, hr, i));
        }
        ar[f] = r;
        ai[f] = i;
    }
}

#[cfg(target_arch = "x86_64")]
/// # Safety
/// The CPU must support AVX2 and FMA.
#[target_feature(enable = "avx2,fma")]
unsafe fn cmac_group_avx2(
    ar: &mut [f64],
    ai: &mut [f64],
    x: [(&[f64], &[f64]); TAXEL_GROUP],
    h: [(&[f64], &[f64]); TAXEL_GROUP],
) {
    cmac_group_impl::<true>(ar, ai, x, h)
}

#[cfg(target_arch = "x86_64")]
/// # Safety
/// The CPU must support AVX-512F (and so AVX2 and FMA).
#[target_feature(enable = "avx2,fma,avx512f")]
unsafe fn cmac_group_avx512(
    ar: &mut [f64],
    ai: &mut [f64],
    x: [(&[f64], &[f64]); TAXEL_GROUP],
    h: [(&[f64], &[f64]); TAXEL_GROUP],
) {
    cmac_group_impl::<true>(ar, ai, x, h)
}

/// `acc += Σ_t x_t ⊙ h_t` over [`TAXEL_GROUP`] taxels (complex, split
/// parts), the bits of [`cmac`] taxel after taxel; `fast` from [`fast_cpu`].
#[inline]
pub(crate) fn cmac_group(
    fast: bool,
    ar: &mut [f64],
    ai: &mut [f64],
    x: [(&[f64], &[f64]); TAXEL_GROUP],
    h: [(&[f64], &[f64]); TAXEL_GROUP],
) {
    #[cfg(target_arch = "x86_64")]
    if fast {
        if crate::wide::avx512() {
            // SAFETY: `wide::avx512` checked that this CPU supports AVX-512F.
            unsafe { cmac_group_avx512(ar, ai, x, h) };
            return;
        }
        // SAFETY: `fast` comes from `fast_cpu`, which checked that this CPU
        // supports AVX2 and FMA.
        unsafe { cmac_group_avx2(ar, ai, x, h) };
        return;
    }
    let _ = fast;
    cmac_group_impl::<false>(ar, ai, x, h)
}

#[inline(always)]
fn dot_impl<const FMA: bool>(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len().min(b.len());
    let (a, b) = (&a[..n], &b[..n]);
    let mut s = [0.0; 4];
    let mut ca = a.chunks_exact(4);
    let mut cb = b.chunks_exact(4);
    for (x, y) in (&mut ca).zip(&mut cb) {
        for j in 0..4 {
            s[j] = madd::<FMA>(x[j], y[j], s[j]);
        }
    }
    let mut r = (s[0] + s[1]) + (s[2] + s[3]);
    for (x, y) in ca.remainder().iter().zip(cb.remainder()) {
        r += x * y;
    }
    r
}

/// `Σ_i <frame(m − i), template(i)>` and the same weighted by `count[m − i]`, for
/// `i < h` and active frames: the direct head of the streaming convolution.
/// `frames` is `[m][taxel]`, `tpl` is `[i][taxel]`.
#[inline(always)]
fn head_impl<const FMA: bool>(
    frames: &[f64],
    active: &[bool],
    count: &[f64],
    tpl: &[f64],
    n: usize,
    k: usize,
    h: usize,
) -> (f64, f64) {
    let (mut p, mut q) = (0.0, 0.0);
    for i in 0..h {
        let m = k - i;
        if active[m] {
            let r = dot_impl::<FMA>(&frames[m * n..(m + 1) * n], &tpl[i * n..(i + 1) * n]);
            p += r;
            q += count[m] * r;
        }
    }
    (p, q)
}

#[cfg(target_arch = "x86_64")]
/// # Safety
/// The CPU must support AVX2 and FMA.
#[target_feature(enable = "avx2,fma")]
unsafe fn head_avx2(
    frames: &[f64],
    active: &[bool],
    count: &[f64],
    tpl: &[f64],
    n: usize,
    k: usize,
    h: usize,
) -> (f64, f64) {
    head_impl::<true>(frames, active, count, tpl, n, k, h)
}

/// See [`head_impl`]; `fast` from [`fast_cpu`].
#[allow(clippy::too_many_arguments)]
#[inline]
pub(crate) fn head(
    fast: bool,
    frames: &[f64],
    active: &[bool],
    count: &[f64],
    tpl: &[f64],
    n: usize,
    k: usize,
    h: usize,
) -> (f64, f64) {
    #[cfg(target_arch = "x86_64")]
    if fast {
        // SAFETY: `fast` comes from `fast_cpu`, which checked that this CPU
        // supports AVX2 and FMA.
        return unsafe { head_avx2(frames, active, count, tpl, n, k, h) };
    }
    let _ = fast;
    head_impl::<false>(frames, active, count, tpl, n, k, h)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// A taxel group's products are the bits of the taxels one by one, on
    /// every kernel this CPU has (AVX-512, AVX2, baseline), at lengths
    /// that leave every vector remainder, with inputs spanning magnitudes.
    #[test]
    fn grouped_products_are_the_bits_of_taxel_by_taxel() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let mut draw = |len: usize| -> Vec<f64> {
            (0..len)
                .map(|_| rng.random_range(-1.0..1.0) * 10f64.powi(rng.random_range(-8..8)))
                .collect()
        };
        for len in [1, 3, 4, 7, 8, 9, 15, 16, 17, 31, 129, 1025] {
            let x: Vec<(Vec<f64>, Vec<f64>)> = (0..TAXEL_GROUP).map(|_| (draw(len), draw(len))).collect();
            let h: Vec<(Vec<f64>, Vec<f64>)> = (0..TAXEL_GROUP).map(|_| (draw(len), draw(len))).collect();
            let (ar0, ai0) = (draw(len), draw(len));
            for fast in [false, fast_cpu()] {
                for wide512 in [true, false] {
                    let run = || {
                        let (mut gr, mut gi) = (ar0.clone(), ai0.clone());
                        cmac_group(
                            fast,
                            &mut gr,
                            &mut gi,
                            std::array::from_fn(|t| (&x[t].0[..], &x[t].1[..])),
                            std::array::from_fn(|t| (&h[t].0[..], &h[t].1[..])),
                        );
                        let (mut sr, mut si) = (ar0.clone(), ai0.clone());
                        for t in 0..TAXEL_GROUP {
                            cmac(fast, &mut sr, &mut si, &x[t].0, &x[t].1, &h[t].0, &h[t].1);
                        }
                        (gr, gi, sr, si)
                    };
                    let (gr, gi, sr, si) = if wide512 {
                        run()
                    } else {
                        crate::wide::without_avx512(run)
                    };
                    let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                    assert_eq!(bits(&gr), bits(&sr), "re, len {len}, fast {fast}, 512 {wide512}");
                    assert_eq!(bits(&gi), bits(&si), "im, len {len}, fast {fast}, 512 {wide512}");
                }
            }
        }
    }
}
