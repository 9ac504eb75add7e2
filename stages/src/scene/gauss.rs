//! Fast white Gaussian noise for the scene's `noise` effect: one standard
//! normal per taxel and sample, tens of millions per dataset.
//!
//! Two parts, both standard:
//!
//! * **Uniform bits**: eight interleaved xoshiro256++ generators (Blackman &
//!   Vigna 2018, a small generator of excellent statistical quality) stepped in
//!   lock step over structure-of-arrays state, which the compiler vectorizes;
//!   their outputs fill a buffer round-robin.
//! * **Normals**: the ziggurat of Marsaglia & Tsang (2000) with 256 layers,
//!   the algorithm (and layer constants `r`, `v`) `rand_distr`'s
//!   `StandardNormal` uses. One 64-bit draw per sample on the fast path
//!   (~98.8 % of samples): bits 0-7 pick the layer `i`, bits 12-63 a uniform
//!   `u` in [-1, 1), and `x = u X[i]` is accepted when `|x| < X[i+1]`; otherwise
//!   the wedge test `F[i+1] + (F[i] - F[i+1]) U < exp(-x²/2)`, or for the base
//!   layer a draw from the tail beyond `r` by Marsaglia's exponential method.
//!
//! Why not `rand_distr` directly: its sampler pulls one draw at a time through
//! a generic RNG, so the generator cannot run several lanes in vector
//! registers; noise was the lab scene's largest single cost (perf, `cargo
//! bench --bench scene`). The layer tables are computed
//! once from the recursion `X[i+1] = sqrt(-2 ln(v / X[i] + f(X[i])))`,
//! `f(x) = exp(-x²/2)`. Tests check moments, the CDF at many points and the
//! tail against Φ.

use rand::Rng;
use rand_chacha::ChaCha8Rng;
use std::sync::OnceLock;

/// Rightmost layer boundary of the 256-layer normal ziggurat.
const R: f64 = 3.654_152_885_361_009;
/// Area of each layer (and of the base strip with its tail).
const V: f64 = 4.928_673_233_99e-3;

struct Tables {
    x: [f64; 257],
    f: [f64; 257],
}

fn tables() -> &'static Tables {
    static T: OnceLock<Tables> = OnceLock::new();
    T.get_or_init(|| {
        let f = |x: f64| (-0.5 * x * x).exp();
        let mut x = [0.0; 257];
        x[0] = V / f(R);
        x[1] = R;
        for i in 1..255 {
            x[i + 1] = (-2.0 * (V / x[i] + f(x[i])).ln()).sqrt();
        }
        x[256] = 0.0;
        let mut fv = [0.0; 257];
        for i in 0..257 {
            fv[i] = f(x[i]);
        }
        Tables { x, f: fv }
    })
}

/// Lanes of the interleaved generator: two 256-bit groups of four, whose
/// independent dependency chains overlap.
const LANES: usize = 8;
/// Draws per refill.
const BUF: usize = 256;

/// A source of standard normal samples, seeded from a ChaCha8 stream.
pub struct GaussianSource {
    s: [[u64; LANES]; 4],
    buf: [u64; BUF],
    pos: usize,
    tab: &'static Tables,
}

impl GaussianSource {
    /// Seeds the eight generators from `rng` (an all-zero lane is redrawn: it
    /// would never leave zero).
    pub fn new(rng: &mut ChaCha8Rng) -> Self {
        let mut s = [[0u64; LANES]; 4];
        for lane in 0..LANES {
            while (0..4).all(|w| s[w][lane] == 0) {
                for w in s.iter_mut() {
                    w[lane] = rng.random();
                }
            }
        }
        GaussianSource {
            s,
            buf: [0; BUF],
            pos: BUF,
            tab: tables(),
        }
    }

    fn refill(&mut self) {
        #[cfg(target_arch = "x86_64")]
        if crate::wide::avx2() {
            // SAFETY: the CPU has AVX2 (checked at run time).
            unsafe { refill_avx2(&mut self.s, &mut self.buf) };
            self.pos = 0;
            return;
        }
        refill_portable(&mut self.s, &mut self.buf);
        self.pos = 0;
    }

    #[inline]
    fn bits(&mut self) -> u64 {
        if self.pos == BUF {
            self.refill();
        }
        let v = self.buf[self.pos];
        self.pos += 1;
        v
    }

    /// A uniform in [0, 1) with 53 random bits.
    fn uniform(&mut self) -> f64 {
        (self.bits() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// One standard normal sample.
    #[inline]
    pub fn sample(&mut self) -> f64 {
        loop {
            let bits = self.bits();
            let i = (bits & 0xff) as usize;
            // 52 bits as a double in [1, 2), mapped to [-1, 1).
            let u = 2.0 * f64::from_bits((bits >> 12) | 0x3ff0_0000_0000_0000) - 3.0;
            let x = u * self.tab.x[i];
            if x.abs() < self.tab.x[i + 1] {
                return x;
            }
            if let Some(x) = self.slow(i, u, x) {
                return x;
            }
        }
    }

    #[cold]
    fn slow(&mut self, i: usize, u: f64, x: f64) -> Option<f64> {
        if i == 0 {
            // The tail beyond r (Marsaglia 1964): exponentials until accepted.
            loop {
                let a = -(1.0 - self.uniform()).ln() / R;
                let b = -(1.0 - self.uniform()).ln();
                if 2.0 * b >= a * a {
                    return Some(if u < 0.0 { -(R + a) } else { R + a });
                }
            }
        }
        let (f0, f1) = (self.tab.f[i], self.tab.f[i + 1]);
        (f1 + (f0 - f1) * self.uniform() < (-0.5 * x * x).exp()).then_some(x)
    }

    /// Adds `sigma` times a fresh standard normal to every value: the bits
    /// of `*v += sigma * self.sample()` value by value.
    ///
    /// Why not that loop: one sample at a time is a chain of table loads
    /// and a branch per value, and noise was the largest single effect of
    /// a lab trial's simulation (`perf record`). Here the buffered draws
    /// run through the ziggurat's fast path eight at a time (`fast_run`,
    /// compiled for AVX2 where the CPU has it, see `fast_run_any`), up to
    /// the first draw it rejects; that draw and whatever its wedge or tail
    /// test consumes go through [`Self::sample`] as before. Each accepted
    /// draw is one value either way, so every value gets the same draw and
    /// the same two operations (test
    /// `batched_noise_is_the_bits_of_sample_by_sample`).
    pub fn add_scaled(&mut self, data: &mut [f64], sigma: f64) {
        let mut o = 0;
        while o < data.len() {
            if self.pos == BUF {
                self.refill();
            }
            let end = (o + (BUF - self.pos)).min(data.len());
            let (tab, bits) = (self.tab, &self.buf[self.pos..]);
            let out = &mut data[o..end];
            let took = fast_run_any(bits, tab, sigma, out);
            self.pos += took;
            o += took;
            if o < end {
                // The draw at `pos` fails the fast test: the full sampler.
                data[o] += sigma * self.sample();
                o += 1;
            }
        }
    }
}

/// [`fast_run`] compiled for AVX2 where the CPU has it, and not for
/// AVX-512 even where it has that: its table lookups become gathers, and
/// with 512-bit ones the quickstart's scene median rose on an AMD EPYC
/// with AVX-512 (`palpate run graphs/quickstart.toml --threads 1`, four
/// runs alternated with the one-sample loop: 2.27-2.38 against 2.15-2.42
/// ms, p95 7.78-8.09 against 7.42-7.67 ms), where with 256-bit ones it
/// fell (2.02-2.25 against 2.14-2.42 ms, p95 7.08-7.21 against 7.37-7.57).
#[inline]
fn fast_run_any(bits: &[u64], tab: &Tables, sigma: f64, out: &mut [f64]) -> usize {
    #[cfg(target_arch = "x86_64")]
    if crate::wide::avx2() {
        #[target_feature(enable = "avx2,fma")]
        fn avx2(bits: &[u64], tab: &Tables, sigma: f64, out: &mut [f64]) -> usize {
            fast_run(bits, tab, sigma, out)
        }
        // SAFETY: the CPU has AVX2 and FMA (checked at run time).
        return unsafe { avx2(bits, tab, sigma, out) };
    }
    fast_run(bits, tab, sigma, out)
}

/// The ziggurat's fast path of [`GaussianSource::sample`] over consecutive
/// draws `bits`, adding `sigma · x` to `out` for each accepted one, until
/// the first draw it would not accept (or the end of the shorter slice);
/// returns how many were taken. Eight draws are tested before any of
/// them is added, so a block of eight is all-or-nothing and the loop
/// vectorises; a block with a rejection is redone one draw at a time.
#[inline(always)]
fn fast_run(bits: &[u64], tab: &Tables, sigma: f64, out: &mut [f64]) -> usize {
    const W: usize = 8;
    #[inline(always)]
    fn candidate(tab: &Tables, b: u64) -> (f64, bool) {
        let i = (b & 0xff) as usize;
        let u = 2.0 * f64::from_bits((b >> 12) | 0x3ff0_0000_0000_0000) - 3.0;
        let x = u * tab.x[i];
        (x, x.abs() < tab.x[i + 1])
    }
    let n = bits.len().min(out.len());
    let (bits, out) = (&bits[..n], &mut out[..n]);
    let mut done = 0;
    for (b8, o8) in bits.chunks_exact(W).zip(out.chunks_exact_mut(W)) {
        let mut x = [0.0; W];
        let mut all = true;
        for (xl, &b) in x.iter_mut().zip(b8) {
            let (v, ok) = candidate(tab, b);
            *xl = v;
            all &= ok;
        }
        if !all {
            break;
        }
        for (o, xl) in o8.iter_mut().zip(x) {
            *o += sigma * xl;
        }
        done += W;
    }
    for (o, &b) in out[done..].iter_mut().zip(&bits[done..]) {
        let (x, ok) = candidate(tab, b);
        if !ok {
            break;
        }
        *o += sigma * x;
        done += 1;
    }
    done
}

/// The eight lanes' xoshiro256++ steps, portable.
fn refill_portable(s: &mut [[u64; LANES]; 4], buf: &mut [u64; BUF]) {
    // The state in locals so it stays in registers.
    let [mut s0, mut s1, mut s2, mut s3] = *s;
    for out in buf.chunks_exact_mut(LANES) {
        for l in 0..LANES {
            out[l] = s0[l].wrapping_add(s3[l]).rotate_left(23).wrapping_add(s0[l]);
            let t = s1[l] << 17;
            s2[l] ^= s0[l];
            s3[l] ^= s1[l];
            s1[l] ^= s2[l];
            s0[l] ^= s3[l];
            s2[l] ^= t;
            s3[l] = s3[l].rotate_left(45);
        }
    }
    *s = [s0, s1, s2, s3];
}

/// The eight lanes' xoshiro256++ steps in 256-bit registers (the same
/// integer operations as the portable loop, so the same bits).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn refill_avx2(s: &mut [[u64; LANES]; 4], buf: &mut [u64; BUF]) {
    use std::arch::x86_64::*;
    #[inline(always)]
    fn rotl<const L: i32, const R: i32>(x: __m256i) -> __m256i {
        unsafe { _mm256_or_si256(_mm256_slli_epi64::<L>(x), _mm256_srli_epi64::<R>(x)) }
    }
    // SAFETY: unaligned loads and stores of four u64 at offsets 0 and 4 of
    // eight-long arrays.
    unsafe {
        let ld = |a: &[u64; LANES], h: usize| _mm256_loadu_si256(a[4 * h..].as_ptr().cast());
        let mut st = [
            [ld(&s[0], 0), ld(&s[1], 0), ld(&s[2], 0), ld(&s[3], 0)],
            [ld(&s[0], 1), ld(&s[1], 1), ld(&s[2], 1), ld(&s[3], 1)],
        ];
        for out in buf.chunks_exact_mut(LANES) {
            for (h, [s0, s1, s2, s3]) in st.iter_mut().enumerate() {
                let o = _mm256_add_epi64(rotl::<23, 41>(_mm256_add_epi64(*s0, *s3)), *s0);
                _mm256_storeu_si256(out[4 * h..].as_mut_ptr().cast(), o);
                let t = _mm256_slli_epi64::<17>(*s1);
                *s2 = _mm256_xor_si256(*s2, *s0);
                *s3 = _mm256_xor_si256(*s3, *s1);
                *s1 = _mm256_xor_si256(*s1, *s2);
                *s0 = _mm256_xor_si256(*s0, *s3);
                *s2 = _mm256_xor_si256(*s2, t);
                *s3 = rotl::<45, 19>(*s3);
            }
        }
        for (w, dst) in s.iter_mut().enumerate() {
            for (h, group) in st.iter().enumerate() {
                _mm256_storeu_si256(dst[4 * h..].as_mut_ptr().cast(), group[w]);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    fn phi(z: f64) -> f64 {
        super::super::special::cdf(z)
    }

    #[test]
    fn tables_close_on_zero_and_match_the_published_constants() {
        let t = tables();
        // Marsaglia & Tsang's x[0] = v / f(r); the recursion reproduces the
        // published table (as in rand_distr: X[2] = 3.4492..., X[255] = 0.2152...).
        assert!((t.x[0] - 3.910_757_959_537_09).abs() < 1e-12, "{}", t.x[0]);
        assert!((t.x[2] - 3.449_278_298_560_964).abs() < 1e-12, "{}", t.x[2]);
        assert!((t.x[255] - 0.215_241_895_913_273_8).abs() < 1e-9, "{}", t.x[255]);
        assert!(t.x.windows(2).all(|w| w[0] > w[1]));
    }

    /// `add_scaled`'s blocks of eight give every value the draw and the
    /// bits that one `sample` at a time gives, across refills, rejections
    /// (wedge and tail draws consume extra bits) and calls of any length,
    /// with the generator left in the same state, on the AVX2 and the
    /// baseline builds of the fast path alike.
    #[test]
    fn batched_noise_is_the_bits_of_sample_by_sample() {
        for seed in 0..20u64 {
            let mut a = GaussianSource::new(&mut ChaCha8Rng::seed_from_u64(seed));
            let mut b = GaussianSource::new(&mut ChaCha8Rng::seed_from_u64(seed));
            let mut draw = ChaCha8Rng::seed_from_u64(1000 + seed);
            for call in 0..40 {
                let len = rand::Rng::random_range(&mut draw, 0..3000usize);
                let sigma = rand::Rng::random_range(&mut draw, -2.0..2.0);
                let init: Vec<f64> = (0..len).map(|k| (k as f64 * 0.37).sin()).collect();
                let mut fast = init.clone();
                if call % 2 == 0 {
                    a.add_scaled(&mut fast, sigma);
                } else {
                    crate::wide::baseline_only(|| a.add_scaled(&mut fast, sigma));
                }
                let mut slow = init;
                for v in slow.iter_mut() {
                    *v += sigma * b.sample();
                }
                let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                assert_eq!(bits(&fast), bits(&slow), "seed {seed}, length {len}");
            }
            assert_eq!(
                a.sample().to_bits(),
                b.sample().to_bits(),
                "seed {seed}: the states parted"
            );
        }
    }

    #[test]
    fn samples_follow_the_standard_normal() {
        let mut g = GaussianSource::new(&mut ChaCha8Rng::seed_from_u64(7));
        let n = 1_000_000;
        let xs: Vec<f64> = (0..n).map(|_| g.sample()).collect();
        assert!(xs.iter().all(|x| x.is_finite()));
        let mean = xs.iter().sum::<f64>() / n as f64;
        let var = xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n as f64;
        let kurt = xs.iter().map(|x| (x - mean).powi(4)).sum::<f64>() / n as f64 / (var * var);
        assert!(mean.abs() < 5e-3, "mean {mean}");
        assert!((var - 1.0).abs() < 5e-3, "var {var}");
        assert!((kurt - 3.0).abs() < 0.03, "kurtosis {kurt}");
        // The empirical CDF against Φ (Kolmogorov bound at 1e6 draws: ~1.4e-3
        // at the 1 % level) at points spanning the body and the tail.
        let mut sorted = xs.clone();
        sorted.sort_by(f64::total_cmp);
        for k in -40..=40 {
            let z = k as f64 * 0.1;
            let emp = sorted.partition_point(|&x| x <= z) as f64 / n as f64;
            assert!((emp - phi(z)).abs() < 1.6e-3, "z={z}: {emp} vs {}", phi(z));
        }
        // Beyond r the base layer's tail sampler is used: P(|Z| > 3.654) ≈ 2.58e-4.
        let tail = xs.iter().filter(|x| x.abs() > R).count() as f64 / n as f64;
        assert!((tail - 2.0 * (1.0 - phi(R))).abs() < 6e-5, "tail {tail}");
    }

    #[test]
    fn the_avx2_generator_matches_the_portable_one() {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            let mut g = GaussianSource::new(&mut ChaCha8Rng::seed_from_u64(11));
            let (mut s, mut buf) = (g.s, [0u64; BUF]);
            for _ in 0..3 {
                // SAFETY: AVX2 checked above.
                unsafe { refill_avx2(&mut s, &mut buf) };
                refill_portable(&mut g.s, &mut g.buf);
                assert_eq!(buf, g.buf);
                assert_eq!(s, g.s);
            }
        }
    }

    #[test]
    fn the_same_seed_gives_the_same_bits() {
        let a: Vec<f64> = {
            let mut g = GaussianSource::new(&mut ChaCha8Rng::seed_from_u64(3));
            (0..1000).map(|_| g.sample()).collect()
        };
        let mut g = GaussianSource::new(&mut ChaCha8Rng::seed_from_u64(3));
        let mut b = vec![0.0; 1000];
        g.add_scaled(&mut b, 1.0);
        assert_eq!(a, b);
    }
}
