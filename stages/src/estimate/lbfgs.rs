//! Limited-memory BFGS (Nocedal 1980; Nocedal & Wright, *Numerical
//! Optimization*, alg. 7.4/7.5) for the smooth, convex objectives of the
//! trained baselines (multinomial logistic regression).
//!
//! From `x_0`, each iteration takes the direction `d = −H g` from the
//! two-loop recursion over the last `memory` pairs `s = x_{k+1} − x_k`,
//! `y = g_{k+1} − g_k`, with the initial scaling `H_0 = (sᵀy / yᵀy) I`
//! (the first step is `−g / ‖g‖`, as scipy's L-BFGS-B), then a backtracking
//! line search for the Armijo condition `f(x + t d) ≤ f(x) + c₁ t gᵀd`
//! (`c₁ = 1e-4`, halving `t` from 1, at most `max_line_search` halvings). A
//! pair is kept only when `sᵀy > ε‖y‖²` so `H` stays positive definite.
//!
//! Stopping follows scipy's `L-BFGS-B` as scikit-learn calls it: the largest
//! gradient component at most `gtol`, or a relative decrease
//! `(f_k − f_{k+1}) / max(|f_k|, |f_{k+1}|, 1) ≤ ftol`, or `max_iter` iterations.
//!
//! Why by hand: the `argmin` crate would bring a framework of traits and
//! dependencies for these ~100 lines, and smartcore's solver (used before)
//! evaluated the objective through its generic array traits ~30x slower
//! than scikit-learn. Everything runs in a fixed order on one thread, so a
//! fit is bit-identical run to run.

/// Settings of [`minimize`].
#[derive(Clone, Copy, Debug)]
pub struct Params {
    /// Correction pairs kept (scipy's `maxcor`).
    pub memory: usize,
    /// Stop when `max_i |g_i| ≤ gtol`.
    pub gtol: f64,
    /// Stop when the relative decrease of `f` is at most `ftol`.
    pub ftol: f64,
    /// Most iterations.
    pub max_iter: usize,
    /// Most step halvings per line search.
    pub max_line_search: usize,
}

/// What [`minimize`] found.
#[derive(Clone, Debug)]
pub struct Outcome {
    /// The last accepted point.
    pub x: Vec<f64>,
    /// `f(x)`.
    pub f: f64,
    /// Iterations taken.
    pub iterations: usize,
    /// True when `gtol` or `ftol` stopped it (not `max_iter` or a failed line search).
    pub converged: bool,
}

/// Minimises `f` from `x0`; `fg(x, g)` returns `f(x)` and writes `∇f(x)` into `g`.
pub fn minimize(x0: Vec<f64>, mut fg: impl FnMut(&[f64], &mut [f64]) -> f64, p: &Params) -> Outcome {
    let n = x0.len();
    let mut x = x0;
    let mut g = vec![0.0; n];
    let mut f = fg(&x, &mut g);
    let mut s_hist: Vec<Vec<f64>> = Vec::new();
    let mut y_hist: Vec<Vec<f64>> = Vec::new();
    let mut rho: Vec<f64> = Vec::new();
    let mut d = vec![0.0; n];
    let mut x_new = vec![0.0; n];
    let mut g_new = vec![0.0; n];
    let mut alpha = vec![0.0; p.memory.max(1)];
    let max_abs = |v: &[f64]| v.iter().fold(0.0f64, |m, x| m.max(x.abs()));
    let dotp = |a: &[f64], b: &[f64]| -> f64 { a.iter().zip(b).map(|(x, y)| x * y).sum() };
    let mut it = 0;
    while it < p.max_iter {
        if !f.is_finite() {
            break;
        }
        if max_abs(&g) <= p.gtol {
            return Outcome {
                x,
                f,
                iterations: it,
                converged: true,
            };
        }
        // Two-loop recursion: d = -H g.
        d.iter_mut().zip(&g).for_each(|(d, g)| *d = -g);
        let m = s_hist.len();
        for i in (0..m).rev() {
            alpha[i] = rho[i] * dotp(&s_hist[i], &d);
            d.iter_mut().zip(&y_hist[i]).for_each(|(d, y)| *d -= alpha[i] * y);
        }
        let gamma = if m > 0 {
            dotp(&s_hist[m - 1], &y_hist[m - 1]) / dotp(&y_hist[m - 1], &y_hist[m - 1])
        } else {
            1.0 / dotp(&g, &g).sqrt().max(f64::MIN_POSITIVE)
        };
        d.iter_mut().for_each(|d| *d *= gamma);
        for i in 0..m {
            let beta = rho[i] * dotp(&y_hist[i], &d);
            d.iter_mut()
                .zip(&s_hist[i])
                .for_each(|(d, s)| *d += (alpha[i] - beta) * s);
        }
        let mut slope = dotp(&g, &d);
        if slope >= 0.0 || !slope.is_finite() {
            // Not a descent direction (round-off): restart from steepest descent.
            s_hist.clear();
            y_hist.clear();
            rho.clear();
            let norm = dotp(&g, &g).sqrt().max(f64::MIN_POSITIVE);
            d.iter_mut().zip(&g).for_each(|(d, g)| *d = -g / norm);
            slope = dotp(&g, &d);
        }
        // Backtracking Armijo line search.
        let mut t = 1.0;
        let mut f_new = f64::INFINITY;
        let mut accepted = false;
        for _ in 0..=p.max_line_search {
            x_new
                .iter_mut()
                .zip(&x)
                .zip(&d)
                .for_each(|((xn, x), d)| *xn = x + t * d);
            f_new = fg(&x_new, &mut g_new);
            if f_new.is_finite() && f_new <= f + 1e-4 * t * slope {
                accepted = true;
                break;
            }
            t *= 0.5;
        }
        it += 1;
        if !accepted {
            break;
        }
        let s: Vec<f64> = x_new.iter().zip(&x).map(|(a, b)| a - b).collect();
        let y: Vec<f64> = g_new.iter().zip(&g).map(|(a, b)| a - b).collect();
        let sy = dotp(&s, &y);
        let yy = dotp(&y, &y);
        if sy > f64::EPSILON * yy && sy > 0.0 {
            if s_hist.len() == p.memory.max(1) {
                s_hist.remove(0);
                y_hist.remove(0);
                rho.remove(0);
            }
            s_hist.push(s);
            y_hist.push(y);
            rho.push(1.0 / sy);
        }
        let decrease = (f - f_new) / f.abs().max(f_new.abs()).max(1.0);
        std::mem::swap(&mut x, &mut x_new);
        std::mem::swap(&mut g, &mut g_new);
        f = f_new;
        if decrease <= p.ftol {
            return Outcome {
                x,
                f,
                iterations: it,
                converged: true,
            };
        }
    }
    let converged = f.is_finite() && max_abs(&g) <= p.gtol;
    Outcome {
        x,
        f,
        iterations: it,
        converged,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn finds_the_minimum_of_the_rosenbrock_function() {
        let p = Params {
            memory: 10,
            gtol: 1e-8,
            ftol: 0.0,
            max_iter: 2000,
            max_line_search: 60,
        };
        let out = minimize(
            vec![-1.2, 1.0],
            |x, g| {
                let (a, b) = (x[0], x[1]);
                g[0] = -2.0 * (1.0 - a) - 400.0 * a * (b - a * a);
                g[1] = 200.0 * (b - a * a);
                (1.0 - a).powi(2) + 100.0 * (b - a * a).powi(2)
            },
            &p,
        );
        assert!(out.converged, "{out:?}");
        assert!(
            (out.x[0] - 1.0).abs() < 1e-5 && (out.x[1] - 1.0).abs() < 1e-5,
            "{out:?}"
        );
    }

    #[test]
    fn a_quadratic_converges_in_few_iterations() {
        // f = Σ c_i (x_i - i)²: L-BFGS is exact on a quadratic within ~n steps.
        let c = [1.0, 10.0, 100.0, 3.0];
        let p = Params {
            memory: 10,
            gtol: 1e-10,
            ftol: 0.0,
            max_iter: 100,
            max_line_search: 60,
        };
        let out = minimize(
            vec![0.0; 4],
            |x, g| {
                let mut f = 0.0;
                for i in 0..4 {
                    let d = x[i] - i as f64;
                    f += c[i] * d * d;
                    g[i] = 2.0 * c[i] * d;
                }
                f
            },
            &p,
        );
        assert!(out.converged && out.iterations < 40, "{out:?}");
        for (i, x) in out.x.iter().enumerate() {
            assert!((x - i as f64).abs() < 1e-8);
        }
    }
}
