//! The two inner kernels of WSS (a complex multiply-accumulate over frequency
//! bins, and a real dot product over taxels), compiled twice: for the baseline
//! target and, on x86-64 CPUs that have them (checked once at run time), with
//! AVX2 and FMA enabled, which doubles the vector width and fuses each
//! multiply-add. Results differ between the two by rounding only (~1e-16).

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
