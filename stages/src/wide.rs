//! Running hot per-sample loops (the scene's effects, the encoders) with
//! 256-bit vectors where the CPU has them.
//!
//! The release build targets baseline x86-64 (SSE2: two doubles per vector).
//! [`with_avx2`] runs a closure inside a function compiled with AVX2 enabled,
//! chosen once at run time, so the loops inlined into it use four lanes. Only
//! AVX2 is enabled, never FMA, and Rust never contracts `a * b + c` on its own:
//! every IEEE operation rounds the same at either width, so the signals are
//! bit-identical on every x86-64 machine (tested: a lab trial simulated both
//! ways, and a trial encoded both ways, give the same bits).

use std::cell::Cell;

thread_local! {
    static BASELINE: Cell<bool> = const { Cell::new(false) };
}

/// Runs `f` with the AVX2 paths switched off on this thread (for comparing
/// the two paths).
pub fn baseline_only<R>(f: impl FnOnce() -> R) -> R {
    let old = BASELINE.with(|b| b.replace(true));
    let r = f();
    BASELINE.with(|b| b.set(old));
    r
}

/// True when the AVX2 path may run on this thread: the CPU has AVX2 (checked
/// once; `PALPATE_NO_AVX2` set in the environment turns it off) and
/// [`baseline_only`] is not in force.
pub fn avx2() -> bool {
    cpu_avx2() && !BASELINE.with(Cell::get)
}

fn cpu_avx2() -> bool {
    use std::sync::OnceLock;
    static ON: OnceLock<bool> = OnceLock::new();
    *ON.get_or_init(|| {
        #[cfg(target_arch = "x86_64")]
        {
            std::env::var_os("PALPATE_NO_AVX2").is_none() && std::arch::is_x86_feature_detected!("avx2")
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
        #[target_feature(enable = "avx2")]
        fn wide<R>(f: impl FnOnce() -> R) -> R {
            f()
        }
        if avx2() {
            // SAFETY: the CPU supports AVX2 (checked at run time above).
            return unsafe { wide(f) };
        }
    }
    f()
}
