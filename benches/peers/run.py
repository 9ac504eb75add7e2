#!/usr/bin/env python3
"""Peer comparison, Python side: Brian2 and scikit-learn on the exact
inputs palpate exported (`cargo run --release --example peers -- --out WORK`).

    python benches/peers/run.py --work benches/peers/work

Reads WORK/encoder/* and WORK/baselines/*, runs

* Brian2: the same Izhikevich neuron (same a, b, c, d, v_peak, dt, initial state,
  zero-order-hold input through a TimedArray at the drive's 1 kHz), in palpate's
  two schemes: `euler` with Brian2's own `method='euler'`, and palpate's default
  `izhikevich` half-step scheme written as the group's update code (see
  README.md for why not an ExplicitStateUpdater), on the codegen targets
  `numpy`, `cython` and `cpp_standalone`. Each configuration runs in its own
  subprocess with a fresh code cache: one cold run (code generation and
  compilation), then `--repeats` timed runs on fresh networks. The figure compared
  is Brian2's own simulation-loop time (`device._last_run_time`, which excludes
  code generation and compilation); setup time is reported separately.
* scikit-learn: MLPClassifier (same hidden size, tanh, Adam, learning rate, batch
  size, L2, epochs and early stopping on the same validation trials) for ANN (S)
  and ANN (ST); BernoulliRBM(60) -> BernoulliRBM(30) -> LogisticRegression for
  the EDBN, all on one thread, on the same training and test arrays.

prints a table (workload, palpate time, peer time, palpate/peer, speed-up =
peer/palpate, agreement), and writes WORK/results.json and the Markdown section
benches/peers/RESULTS-peers.md.
"""

import argparse
import copy
import json
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent


# ---------------------------------------------------------------------------
# Brian2 (each configuration runs in a subprocess: `run.py _brian ...`)
# ---------------------------------------------------------------------------

EULER_EQS = """
dv/dt = (0.04*v**2 + 5*v + 140 - u + I_in(t, i))/ms : 1
du/dt = a*(b*v - u)/ms : 1
"""

# palpate's `izhikevich` scheme (stages/src/encode/izhikevich.rs) as a Brian2
# user would write it: v takes two half-steps of dt/2 with the same u and I (the
# second from v clamped to v_peak, so a spike is caught at the half-step),
# then u a full step with the new v. Brian2's threshold `v >= v_peak` and reset
# act on the step's end, as palpate's do. (palpate also holds v at v_peak when
# the first half crossed; here a2 >= v_peak then anyway unless u > 326 + I.
# palpate's floor on v, c - 1000 mV, never acts on this input and is left out.)
HALF_STEP_CODE = """
I_now = I_in(t, i)
a1 = v + h*(0.04*v**2 + 5*v + 140 - u + I_now)
m = clip(a1, -1e300, v_peak)
x = clip(m + h*(0.04*m**2 + 5*m + 140 - u + I_now), -1e300, v_peak)
u = u + dt_step*a*(b*x - u)
v = x
"""

# The `exact` mode: palpate's arithmetic operation for operation, one binary
# operation per statement, so that Brian2's sympy rewriting (which reorders
# sums, e.g. `140 + ((-u + 0.04 v^2) + 5 v) + I`) cannot change the rounding,
# compiled without -ffast-math and with -ffp-contract=off (no fused
# multiply-add). It shows whether any remaining difference is the scheme or
# only floating-point rounding.
EXACT_FIRST = """
I_now = I_in(t, i)
q1 = 0.04*v
q2 = q1 + 5.0
q3 = q2*v
q4 = q3 + 140.0
q5 = q4 - u
q6 = q5 + I_now
q7 = h*q6
a1 = v + q7
"""
EXACT_EULER = EXACT_FIRST + """
r1 = b*v
r2 = r1 - u
r3 = adt*r2
u = u + r3
v = clip(a1, -1e300, v_peak)
"""
EXACT_HALF = EXACT_FIRST + """
m = clip(a1, -1e300, v_peak)
s1 = 0.04*m
s2 = s1 + 5.0
s3 = s2*m
s4 = s3 + 140.0
s5 = s4 - u
s6 = s5 + I_now
s7 = h*s6
a2 = m + s7
hit = int(a1 >= v_peak)
miss = 1 - hit
lo1 = v_peak*hit
lo2 = -1e300*miss
lo = lo1 + lo2
x = clip(a2, lo, v_peak)
r1 = b*x
r2 = r1 - u
r3 = adt*r2
u = u + r3
v = x
"""
EXACT_FLAGS = ["-w", "-O3", "-march=native", "-std=c++11", "-ffp-contract=off"]


def brian_worker(target, scheme, mode, repeats, work, cache):
    """Runs one Brian2 configuration; prints one JSON line."""
    import brian2 as b2

    b2.BrianLogger.log_level_warn()
    meta = json.loads((work / "encoder" / "encoder.json").read_text())
    cur = np.load(work / "encoder" / "currents.npy")  # [taxel][sample]
    n_taxels, n_samples = cur.shape
    fs = meta["sample_rate_hz"]
    dt_ms = meta["dt_ms"]
    duration = meta["duration_ms"] * b2.ms
    p = meta["params"]
    values = np.ascontiguousarray(cur.T)  # TimedArray wants [time][neuron]
    shutil.rmtree(cache, ignore_errors=True)
    cache.mkdir(parents=True)
    standalone = target == "cpp_standalone"
    if mode == "exact":
        b2.prefs.codegen.cpp.extra_compile_args_gcc = EXACT_FLAGS
        b2.prefs.codegen.loop_invariant_optimisations = False
    if standalone:
        b2.set_device("cpp_standalone", directory=str(cache / "project"), build_on_run=True)
        b2.prefs.devices.cpp_standalone.openmp_threads = 0
    else:
        b2.prefs.codegen.target = target
        b2.prefs.codegen.runtime.cython.cache_dir = str(cache / "cython")

    def build():
        b2.start_scope()
        b2.defaultclock.dt = dt_ms * b2.ms
        I_in = b2.TimedArray(values, dt=1000.0 / fs * b2.ms)
        ns = dict(a=p["a"], b=p["b"], c=p["c"], d=p["d"], v_peak=p["v_peak"], I_in=I_in)
        ns.update(h=(dt_ms if scheme == "euler" else 0.5 * dt_ms), dt_step=dt_ms, adt=p["a"] * dt_ms)
        if scheme == "euler" and mode == "natural":
            g = b2.NeuronGroup(
                n_taxels,
                EULER_EQS,
                threshold="v >= v_peak",
                reset="v = c; u += d",
                method="euler",
                namespace=ns,
            )
        else:
            g = b2.NeuronGroup(
                n_taxels,
                "v : 1\nu : 1",
                threshold="v >= v_peak",
                reset="v = c; u += d",
                namespace=ns,
            )
            code = {
                ("izhikevich", "natural"): HALF_STEP_CODE,
                ("izhikevich", "exact"): EXACT_HALF,
                ("euler", "exact"): EXACT_EULER,
            }[(scheme, mode)]
            g.run_regularly(code, when="groups")
        g.v = meta["v0"]
        g.u = meta["u0"]
        mon = b2.SpikeMonitor(g)
        net = b2.Network(g, mon)
        return net, mon

    runs = []
    net = mon = None
    if standalone:
        # One build (code generation + g++), then the compiled binary re-run.
        net, mon = build()
        w0 = time.perf_counter()
        net.run(duration)
        cold_total = time.perf_counter() - w0
        dev = b2.get_device()
        cold = {"total_s": cold_total, "sim_s": dev._last_run_time}
        cold["setup_s"] = cold_total - cold["sim_s"]
        for _ in range(repeats):
            w0, c0 = time.perf_counter(), os.times()
            dev.run()
            total, c1 = time.perf_counter() - w0, os.times()
            # CPU of the binary (start, load arrays, simulate, write results).
            cpu = (c1.children_user - c0.children_user) + (c1.children_system - c0.children_system)
            runs.append({"total_s": total, "sim_s": dev._last_run_time, "process_cpu_s": cpu})
    else:
        for k in range(repeats + 1):
            net, mon = build()
            w0, c0 = time.perf_counter(), time.process_time()
            net.run(duration)
            total, cpu = time.perf_counter() - w0, time.process_time() - c0
            sim = b2.get_device()._last_run_time
            r = {"total_s": total, "sim_s": sim, "setup_s": total - sim, "process_cpu_s": cpu}
            if k == 0:
                cold = r
            else:
                runs.append(r)
    i = np.asarray(mon.i[:], dtype=int)
    t = np.asarray(mon.t[:] / b2.ms, dtype=float)
    counts = np.bincount(i, minlength=n_taxels)
    sims = sorted(r["sim_s"] for r in runs)
    out = {
        "target": target,
        "scheme": scheme,
        "mode": mode,
        "brian2": b2.__version__,
        "cold": cold,
        "runs": runs,
        "sim_s_median": sims[len(sims) // 2],
        "sim_s_min": sims[0],
        "counts": counts.tolist(),
        "spikes": int(i.size),
        "spike_i": i.tolist(),
        "spike_t_ms": t.tolist(),
    }
    print("BRIAN_JSON " + json.dumps(out))


def run_brian(target, scheme, mode, repeats, work, timeout):
    cache = work / "brian-cache" / f"{target}-{scheme}-{mode}"
    cmd = [sys.executable, str(Path(__file__).resolve()), "_brian", target, scheme, mode, str(repeats), str(work), str(cache)]
    try:
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"target": target, "scheme": scheme, "mode": mode, "error": f"timed out after {timeout} s"}
    for line in res.stdout.splitlines():
        if line.startswith("BRIAN_JSON "):
            return json.loads(line[len("BRIAN_JSON ") :])
    tail = (res.stderr or res.stdout).strip().splitlines()[-8:]
    return {"target": target, "scheme": scheme, "mode": mode, "error": " | ".join(tail)}


def spike_agreement(meta, scheme, work, br):
    """Per-taxel counts and, where the counts agree, the spike-time offsets."""
    pal = np.load(work / "encoder" / f"spikes_{scheme}.npy").reshape(-1, 2)
    pc = np.asarray(meta["palpate"][scheme]["counts"])
    bc = np.asarray(br["counts"])
    same = int((pc == bc).sum())
    bi, bt = np.asarray(br["spike_i"]), np.asarray(br["spike_t_ms"])
    offs = []
    for k in range(len(pc)):
        if pc[k] != bc[k]:
            continue
        tp = np.sort(pal[pal[:, 0] == k, 1])
        tb = np.sort(bt[bi == k])
        offs.extend((tp - tb).tolist())
    offs = np.asarray(offs)
    dt = meta["dt_ms"]
    diff = {int(k): [int(pc[k]), int(bc[k])] for k in range(len(pc)) if pc[k] != bc[k]}
    return {
        "taxels_same_count": same,
        "n_taxels": len(pc),
        "palpate_spikes": int(pc.sum()),
        "peer_spikes": int(bc.sum()),
        "differing_taxels": diff,
        # palpate interpolates the crossing within the step; Brian2 stamps the
        # step's start, so t_palpate - t_brian lies in [0, dt] for the same spike.
        "matched": int(offs.size),
        "same_step": int(((offs >= -1e-9) & (offs <= dt + 1e-9)).sum()),
        "time_offset_ms": (
            {"min": float(offs.min()), "max": float(offs.max()), "mean": float(offs.mean())} if offs.size else None
        ),
    }


# ---------------------------------------------------------------------------
# scikit-learn
# ---------------------------------------------------------------------------


def load_baseline(d):
    ld = lambda n: np.load(d / f"{n}.npy")  # noqa: E731
    return {
        "X_train": ld("X_train"),
        "y_train": ld("y_train").astype(int),
        "trial_train": ld("trial_train").astype(int),
        "val": ld("val_train") > 0.5,
        "X_test": ld("X_test"),
        "y_test": ld("y_test").astype(int),
        "trial_test": ld("trial_test").astype(int),
        "trial_angle": ld("test_trial_angle"),
    }


def vote(proba, trial, n_trials, classes):
    """palpate's winner-take-all: each frame's winning class collects its
    output; the trial's answer is the largest total (first class on ties)."""
    totals = np.zeros((n_trials, proba.shape[1]))
    w = proba.argmax(axis=1)
    np.add.at(totals, (trial, w), proba[np.arange(len(w)), w])
    ans = np.where(totals.max(axis=1) > 0, np.asarray(classes)[totals.argmax(axis=1)], np.nan)
    return ans


def timed(repeats, f):
    """`repeats` samples of wall and thread-CPU time per call of `f`, each
    averaged over a batch of calls of at least 50 ms (as palpate_side.rs)."""
    w0 = time.perf_counter()
    out = f()
    batch = int(min(max(np.ceil(0.05 / max(time.perf_counter() - w0, 1e-6)), 1), 10000))
    wall, cpu = [], []
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.thread_time()
        for _ in range(batch):
            out = f()
        wall.append((time.perf_counter() - w0) / batch)
        cpu.append((time.thread_time() - c0) / batch)
    st = lambda xs: {"median": sorted(xs)[len(xs) // 2], "min": min(xs), "all": xs}  # noqa: E731
    return out, {"repeats": repeats, "calls_per_repeat": batch, "wall_s": st(wall), "cpu_s": st(cpu)}


def fit_mlp(cfg, data, classes_idx, seed):
    """MLPClassifier trained like palpate's `ann`: standardise on the fit
    vectors, Adam minibatches, validation loss on the same held-out trials
    after every epoch, stop after `patience` epochs without improvement, keep
    the best epoch's weights."""
    from sklearn.neural_network import MLPClassifier
    from sklearn.preprocessing import StandardScaler

    X, y, val = data["X_train"], data["y_train"], data["val"]
    Xf, yf, Xv, yv = X[~val], y[~val], X[val], y[val]
    scaler = StandardScaler().fit(Xf)
    Xf, Xv = scaler.transform(Xf), scaler.transform(Xv)
    mlp = MLPClassifier(
        hidden_layer_sizes=(cfg["hidden"],),
        activation="tanh",
        solver="adam",
        # palpate adds l2/2 |W|^2 to the batch's *mean* loss; sklearn adds
        # alpha/2 |W|^2 / batch_size, so alpha = l2 * batch_size.
        alpha=cfg["l2"] * cfg["batch_size"],
        batch_size=cfg["batch_size"],
        learning_rate_init=cfg["learning_rate"],
        beta_1=0.9,
        beta_2=0.999,
        epsilon=1e-8,
        shuffle=True,
        random_state=seed,
    )
    best = (np.inf, None, 0)
    since = 0
    epochs = 0
    for epoch in range(cfg["max_epochs"]):
        mlp.partial_fit(Xf, yf, classes=classes_idx)
        epochs += 1
        if len(yv):
            p = mlp.predict_proba(Xv)
            col = np.searchsorted(mlp.classes_, yv)
            watched = -np.mean(np.log(np.maximum(p[np.arange(len(yv)), col], 1e-300)))
        else:
            watched = mlp.loss_
        if not np.isfinite(watched):
            break
        if not np.isfinite(best[0]) or watched < best[0] - 1e-9 * max(abs(best[0]), 1.0):
            best = (watched, (copy.deepcopy(mlp.coefs_), copy.deepcopy(mlp.intercepts_)), epoch)
            since = 0
        else:
            since += 1
            if len(yv) and since >= max(cfg["patience"], 1):
                break
    if best[1] is not None:
        mlp.coefs_, mlp.intercepts_ = best[1]
    return {"model": mlp, "scaler": scaler, "epochs": epochs, "best_epoch": best[2]}


def predict_mlp(m, X):
    return m["model"].predict_proba(m["scaler"].transform(X))


def fit_dbn(cfg, data, classes_idx, seed):
    """The usual scikit-learn DBN-like pipeline: BernoulliRBM layers (PCD, one
    Gibbs step per minibatch, mean-field activities passed up) of palpate's
    sizes, epochs, batch size and learning rate, then a LogisticRegression on
    the top layer's activities (palpate's top RBM learns the labels itself)."""
    from sklearn.linear_model import LogisticRegression
    from sklearn.neural_network import BernoulliRBM
    from sklearn.pipeline import Pipeline

    steps = [
        (
            f"rbm{k}",
            BernoulliRBM(
                n_components=n,
                learning_rate=cfg["learning_rate"],
                batch_size=cfg["batch_size"],
                n_iter=cfg["epochs"],
                random_state=seed + k,
            ),
        )
        for k, n in enumerate(cfg["layers"])
    ]
    steps.append(("logistic", LogisticRegression(max_iter=1000)))
    pipe = Pipeline(steps).fit(data["X_train"], data["y_train"])
    return {"model": pipe, "epochs": cfg["epochs"] * len(cfg["layers"])}


def predict_dbn(m, X):
    return m["model"].predict_proba(X)


def scaled(fit_model):
    """Wraps a classifier fit in palpate's standardisation (mean and
    population SD of every training vector, as `Standardizer`)."""
    from sklearn.preprocessing import StandardScaler

    def fit(cfg, data, classes_idx, seed):
        scaler = StandardScaler().fit(data["X_train"])
        model = fit_model(cfg, scaler.transform(data["X_train"]), data["y_train"], len(classes_idx), seed)
        return {"model": model, "scaler": scaler, "epochs": None}

    return fit


def fit_svc(cfg, X, y, k, seed):
    """SVC as palpate's `svm`: RBF, one-vs-one (libsvm), same C, gamma
    (0 = 1/dim, sklearn's "scale" on standardised features) and tolerance."""
    from sklearn.svm import SVC

    gamma = cfg["gamma"] if cfg["gamma"] > 0 else 1.0 / X.shape[1]
    return SVC(C=cfg["c"], kernel="rbf", gamma=gamma, tol=cfg["tol"], decision_function_shape="ovr").fit(X, y)


def predict_svc(m, X):
    """sklearn's one-vs-one votes plus its confidence tie-breaker (its "ovr"
    decision function), scaled as palpate's: votes / (K - 1), clipped at 0."""
    d = m["model"].decision_function(m["scaler"].transform(X))
    k = d.shape[1]
    return np.maximum(d / (k - 1), 0.0)


def fit_forest(cfg, X, y, k, seed):
    """RandomForestClassifier as palpate's `random_forest`: same tree count,
    sqrt(dim) features per split unless `m` is set, bootstrap, Gini, leaf size
    and depth; one thread."""
    from sklearn.ensemble import RandomForestClassifier

    return RandomForestClassifier(
        n_estimators=cfg["n_trees"],
        max_features=cfg["m"] if cfg["m"] > 0 else "sqrt",
        max_depth=cfg["max_depth"] if cfg["max_depth"] > 0 else None,
        min_samples_leaf=cfg["min_samples_leaf"],
        bootstrap=True,
        n_jobs=1,
        random_state=seed,
    ).fit(X, y)


def predict_forest(m, X):
    """One vote (score 1) for the predicted class, as palpate's forest."""
    p = m["model"].predict(m["scaler"].transform(X))
    out = np.zeros((len(p), len(m["model"].classes_)))
    out[np.arange(len(p)), np.searchsorted(m["model"].classes_, p)] = 1.0
    return out


def fit_knn(cfg, X, y, k, seed):
    from sklearn.neighbors import KNeighborsClassifier

    return KNeighborsClassifier(n_neighbors=min(cfg["k"], len(y)), weights=cfg["weight"], n_jobs=1).fit(X, y)


def fit_logistic(cfg, X, y, k, seed):
    """Multinomial L-BFGS logistic regression; palpate minimises the summed
    log loss + alpha/2 |W|^2 (intercepts unpenalised, stopping at tol = 1e-4
    on the mean objective's gradient, as here), sklearn C * summed loss +
    1/2 |W|^2, so C = 1 / alpha."""
    from sklearn.linear_model import LogisticRegression

    return LogisticRegression(C=1.0 / cfg["alpha"], max_iter=1000).fit(X, y)


def predict_proba_scaled(m, X):
    return m["model"].predict_proba(m["scaler"].transform(X))


PEERS = {
    "ann": (fit_mlp, predict_mlp, "sklearn MLPClassifier"),
    "edbn": (fit_dbn, predict_dbn, "sklearn RBM+RBM+LogReg"),
    "svm": (scaled(fit_svc), predict_svc, "sklearn SVC"),
    "random_forest": (scaled(fit_forest), predict_forest, "sklearn RandomForestClassifier"),
    "knn": (scaled(fit_knn), predict_proba_scaled, "sklearn KNeighborsClassifier"),
    "logistic": (scaled(fit_logistic), predict_proba_scaled, "sklearn LogisticRegression"),
}


def run_baselines(work, seed, repeats):
    from threadpoolctl import threadpool_limits

    import sklearn

    meta = json.loads((work / "baselines" / "baselines.json").read_text())
    results = {}
    # palpate fits one fold on one thread; so does the peer.
    with threadpool_limits(limits=1):
        for mid, m in meta["models"].items():
            data = load_baseline(work / "baselines" / mid)
            classes = m["classes_deg"]
            classes_idx = np.arange(len(classes))
            cfg = m["config"]
            fit, pred, peer = PEERS[m["kind"]]
            model, fit_t = timed(7, lambda: fit(cfg, data, classes_idx, seed))
            n_trials = len(data["trial_angle"])

            def predict_all():
                p = pred(model, data["X_test"])
                return p, vote(p, data["trial_test"], n_trials, classes)

            (proba, answers), pred_t = timed(repeats, predict_all)
            frame_acc = float((proba.argmax(axis=1) == data["y_test"]).mean())
            err = np.abs(answers - data["trial_angle"])
            pal_ans = np.array([np.nan if a is None else a for a in m["palpate"]["trial_answers_deg"]])
            results[mid] = {
                "peer": peer,
                "sklearn": sklearn.__version__,
                "fit_time": fit_t,
                "predict_time": pred_t,
                "epochs_run": model["epochs"],
                "best_epoch": model.get("best_epoch"),
                "frame_accuracy": frame_acc,
                "mae_deg": float(np.mean(err)),
                "trial_answers_deg": answers.tolist(),
                "trials_same_answer": int((answers == pal_ans).sum()),
                "n_trials": n_trials,
            }
    return meta, results


def merged_time(a, b):
    """Two timings of one call (`timed`'s dicts, or palpate_side.rs's) as
    one: every sample of both, their minimum and median."""
    def batches(t):
        c = t["calls_per_repeat"]
        return c if isinstance(c, list) else [c]

    out = {"repeats": a["repeats"] + b["repeats"], "calls_per_repeat": batches(a) + batches(b)}
    for key in ["wall_s", "cpu_s"]:
        xs = (a.get(key) or {}).get("all", []) + (b.get(key) or {}).get("all", [])
        xs = [x for x in xs if x is not None]
        out[key] = {"median": sorted(xs)[len(xs) // 2], "min": min(xs), "all": xs} if xs else None
    return out


def retime_palpate(work, bmeta, r):
    """palpate's baseline side again (the example, every baseline, no
    encoder), into work/rounds/r<r>/: the same export, timed anew."""
    ids = ",".join(bmeta["models"].keys())
    out = work / "rounds" / f"r{r}"
    cmd = ["cargo", "run", "--quiet", "--release", "--example", "peers", "--", "--out", str(out), "--seed", str(bmeta["source"]["seed"]), "--only", ids]
    subprocess.run(cmd, check=True, cwd=HERE.parent.parent)
    return json.loads((out / "baselines" / "baselines.json").read_text())


def merge_palpate_round(bmeta, again, r):
    """Adds round `r`'s palpate times to `bmeta`. The round must have
    fitted the same models: the same per-trial answers and frame accuracy
    (palpate is deterministic), else the comparison would mix two models."""
    for mid, m in bmeta["models"].items():
        pm, qm = m["palpate"], again["models"][mid]["palpate"]
        if pm["trial_answers_deg"] != qm["trial_answers_deg"] or pm["frame_accuracy"] != qm["frame_accuracy"]:
            raise SystemExit(f"{mid}: palpate's round {r} answered differently from round 1 (a nondeterministic fit?)")
        for phase in ["fit_time", "predict_time"]:
            pm[phase] = merged_time(pm[phase], qm[phase])


def merge_sklearn_round(bres, again, r):
    """Adds round `r`'s scikit-learn times to `bres` (the first round's
    answers stay; a peer whose answers moved between rounds is noted)."""
    for mid, res in bres.items():
        q = again[mid]
        for phase in ["fit_time", "predict_time"]:
            res[phase] = merged_time(res[phase], q[phase])
        if q["trial_answers_deg"] != res["trial_answers_deg"]:
            res.setdefault("notes", []).append(f"round {r} answered differently from round 1")


# ---------------------------------------------------------------------------
# Report
# ---------------------------------------------------------------------------


def fmt_t(s):
    if s is None or not np.isfinite(s):
        return "-"
    if s >= 1:
        return f"{s:.2f} s"
    if s >= 1e-3:
        return f"{s * 1e3:.2f} ms"
    return f"{s * 1e6:.0f} us"


def machine():
    cpu = "?"
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"cpu": cpu, "cores": os.cpu_count(), "python": platform.python_version(), "platform": platform.platform()}


def main():
    if len(sys.argv) > 1 and sys.argv[1] == "_brian":
        _, _, target, scheme, mode, repeats, work, cache = sys.argv
        brian_worker(target, scheme, mode, int(repeats), Path(work), Path(cache))
        return
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, default=HERE / "work", help="palpate's export (--out of the example)")
    ap.add_argument("--targets", default="numpy,cython,cpp_standalone", help="Brian2 codegen targets")
    ap.add_argument("--repeats", type=int, default=3, help="timed runs per Brian2 configuration (sklearn: fits 7, predictions max(this, 5) samples)")
    ap.add_argument("--modes", default="natural,exact", help="Brian2 code: natural and/or exact (see README)")
    ap.add_argument("--timeout", type=float, default=900, help="seconds per Brian2 configuration")
    ap.add_argument("--skip-encoder", action="store_true")
    ap.add_argument("--skip-baselines", action="store_true")
    ap.add_argument("--md", type=Path, default=HERE / "RESULTS-peers.md", help="Markdown section to write")
    ap.add_argument("--command", default=None, help="the command line to record in the Markdown")
    ap.add_argument(
        "--rounds",
        type=int,
        default=2,
        help="baseline timing rounds, the sides alternated (palpate, scikit-learn, palpate, ...); each side's figure is its best over every round",
    )
    args = ap.parse_args()
    if args.rounds < 1:
        ap.error(f"--rounds must be at least 1, not {args.rounds}")
    work = args.work.resolve()
    load_start = os.getloadavg()
    t_start = time.time()
    rows = []  # (workload, palpate s, peer name, peer s, agreement)
    report = {"machine": machine(), "load_start": load_start, "work": str(work)}

    if not args.skip_encoder:
        meta = json.loads((work / "encoder" / "encoder.json").read_text())
        report["encoder"] = {"meta": {k: v for k, v in meta.items() if k != "palpate"}, "palpate": meta["palpate"], "brian2": []}
        for scheme in ["izhikevich", "euler"]:
            pal = meta["palpate"][scheme]["time"]["wall_s"]["min"]
            pal_cpu = (meta["palpate"][scheme]["time"].get("cpu_s") or {}).get("min")
            for target in args.targets.split(","):
                for mode in args.modes.split(","):
                    label = f"Brian2 {target}" + (" (exact FP)" if mode == "exact" else "")
                    print(f"{label}, {scheme} scheme ...", flush=True)
                    br = run_brian(target, scheme, mode, args.repeats, work, args.timeout)
                    if "error" in br:
                        print(f"  failed: {br['error']}")
                        report["encoder"]["brian2"].append(br)
                        rows.append((f"encoder 16x40 s, {scheme} scheme", pal, label, None, br["error"][:80]))
                        continue
                    ag = spike_agreement(meta, scheme, work, br)
                    br = {k: v for k, v in br.items() if k not in ("spike_i", "spike_t_ms")}
                    br["agreement"] = ag
                    br["palpate_wall_s"] = pal
                    br["palpate_cpu_s"] = pal_cpu
                    report["encoder"]["brian2"].append(br)
                    off = ag["time_offset_ms"]
                    agree = (
                        f"counts equal on {ag['taxels_same_count']}/{ag['n_taxels']} taxels "
                        f"({ag['palpate_spikes']} vs {ag['peer_spikes']} spikes)"
                    )
                    if off:
                        agree += f"; {ag['same_step']}/{ag['matched']} matched spikes in the same step"
                    print(f"  sim {fmt_t(br['sim_s_min'])} best, {fmt_t(br['sim_s_median'])} median (cold setup {fmt_t(br['cold'].get('setup_s'))}); {agree}")
                    rows.append((f"encoder 16x40 s, {scheme} scheme", pal, label, br["sim_s_min"], agree))

    if not args.skip_baselines:
        bmeta, bres = run_baselines(work, 1, max(args.repeats, 5))
        for r in range(2, args.rounds + 1):
            print(f"baselines, round {r} of {args.rounds}: palpate, then scikit-learn ...", flush=True)
            again = retime_palpate(work, bmeta, r)
            merge_palpate_round(bmeta, again, r)
            _, bres_r = run_baselines(work, 1, max(args.repeats, 5))
            merge_sklearn_round(bres, bres_r, r)
        report["baselines"] = {"meta": bmeta, "sklearn": bres, "rounds": args.rounds}
        names = {"ann_s": "ANN (S)", "ann_st": "ANN (ST)", "edbn": "EDBN", "svm": "SVM", "random_forest": "random forest", "knn": "k-NN", "logistic": "logistic"}
        for mid, r in bres.items():
            pm = bmeta["models"][mid]["palpate"]
            for phase in ["fit", "predict"]:
                agree = (
                    f"frame acc {pm['frame_accuracy']:.3f} vs {r['frame_accuracy']:.3f}; "
                    f"MAE {pm['mae_deg']:.2f} vs {r['mae_deg']:.2f} deg; "
                    f"{r['trials_same_answer']}/{r['n_trials']} trials same answer"
                )
                if phase == "fit" and r["epochs_run"] is not None:
                    agree += f"; epochs {pm['epochs_run']} vs {r['epochs_run']}"
                n = bmeta["models"][mid]["n_train" if phase == "fit" else "n_test"]
                rows.append(
                    (
                        f"{names.get(mid, mid)} {phase} ({n} x {bmeta['models'][mid]['dim']})",
                        pm[f"{phase}_time"]["wall_s"]["min"],
                        r["peer"],
                        r[f"{phase}_time"]["wall_s"]["min"],
                        agree,
                    )
                )
                print(f"{mid} {phase}: palpate {fmt_t(rows[-1][1])}, {r['peer']} {fmt_t(rows[-1][3])}; {agree}")

    load_end = os.getloadavg()
    report["load_end"] = load_end
    report["elapsed_s"] = time.time() - t_start
    report["rows"] = [
        {"workload": w, "palpate_s": p, "peer": n, "peer_s": q, "ratio": (p / q if q else None), "speedup": (q / p if q else None), "agreement": a}
        for (w, p, n, q, a) in rows
    ]
    (work / "results.json").write_text(json.dumps(report, indent=1))

    head = "| workload | palpate | peer | peer time | palpate/peer | speed-up | agreement |"
    lines = [head, "|---|---|---|---|---|---|---|"]
    for w, p, n, q, a in rows:
        ratio = f"{p / q:.4f}" if q else "-"
        speed = f"{q / p:.0f}x" if q and q / p >= 10 else (f"{q / p:.2f}x" if q else "-")
        lines.append(f"| {w} | {fmt_t(p)} | {n} | {fmt_t(q)} | {ratio} | {speed} | {a} |")
    table = "\n".join(lines)
    print()
    print(table)
    # The target: the encoder >= 100x faster than Brian2 on 16 taxels x
    # 40 s with the same spike counts (palpate's default scheme, Brian2 as a
    # user writes it), per codegen target.
    target_lines = []
    setup_lines = []
    for br in report.get("encoder", {}).get("brian2", []):
        if "error" in br:
            continue
        if br["mode"] == "natural":
            setup_lines.append(
                f"{br['target']} ({br['scheme']}) {fmt_t(br['cold'].get('setup_s'))}"
            )
        if br["mode"] != "natural" or br["scheme"] != report["encoder"]["meta"]["default_scheme"]:
            continue
        ag = br["agreement"]
        speed = br["sim_s_min"] / br["palpate_wall_s"]
        same = ag["taxels_same_count"] == ag["n_taxels"]
        ok = speed >= 100 and same
        target_lines.append(
            f"- vs Brian2 {br['target']}: {speed:.0f}x faster, spike counts "
            f"{'identical on every taxel' if same else 'differ on ' + str(ag['n_taxels'] - ag['taxels_same_count']) + ' taxel(s)'}"
            f" -> target {'met' if ok else 'NOT met'}"
        )
    report["target_check"] = target_lines
    (work / "results.json").write_text(json.dumps(report, indent=1))
    if target_lines:
        print("\nTarget (encoder >= 100x faster than Brian2, same spike counts, default scheme):")
        print("\n".join(target_lines))
    # Issue 17's target: every trained estimator >= 3x faster than its
    # scikit-learn counterpart for fit and for predict, at equal or better
    # accuracy (trial MAE no higher, frame accuracy no lower by more than 0.01).
    base_lines = []
    for mid, r in report.get("baselines", {}).get("sklearn", {}).items():
        pm = report["baselines"]["meta"]["models"][mid]["palpate"]
        acc_ok = pm["mae_deg"] <= r["mae_deg"] + 1e-9 and pm["frame_accuracy"] >= r["frame_accuracy"] - 0.01
        parts = []
        ok = acc_ok
        for phase in ["fit", "predict"]:
            sp = r[f"{phase}_time"]["wall_s"]["min"] / pm[f"{phase}_time"]["wall_s"]["min"]
            ok = ok and sp >= 3.0
            parts.append(f"{phase} {sp:.2f}x")
        base_lines.append(
            f"- {mid} vs {r['peer']}: {', '.join(parts)}; accuracy "
            f"{'equal or better' if acc_ok else 'WORSE'} (MAE {pm['mae_deg']:.2f} vs {r['mae_deg']:.2f} deg, "
            f"frame acc {pm['frame_accuracy']:.3f} vs {r['frame_accuracy']:.3f}) -> target {'met' if ok else 'NOT met'}"
        )
    if base_lines:
        print("\nTarget (every trained estimator >= 3x faster than scikit-learn, fit and predict, equal or better accuracy):")
        print("\n".join(base_lines))
    # A run without the encoder keeps the encoder rows of the previous
    # Markdown (they were measured by the run named there).
    kept_rows, kept_tail = [], []
    if args.skip_encoder and args.md.exists():
        old = args.md.read_text().splitlines()
        kept_rows = [l for l in old if l.startswith("| encoder")]
        # From Issue 8's verdicts to the end of the encoder's notes.
        start = next((i for i, l in enumerate(old) if l.startswith("Issue 8's target")), None)
        if start is not None:
            for l in old[start:]:
                if l.startswith(("Issue 17's target", "The encoder rows above were kept")):
                    break
                kept_tail.append(l)
        prev = next((l for l in old if l.startswith("Produced by")), "")
        again = next((l for l in old if l.startswith("The encoder rows above were kept")), None)
        if kept_tail and kept_tail[-1] != "":
            kept_tail.append("")
        if kept_rows and again:
            kept_tail += [again, ""]
        elif kept_rows and prev:
            kept_tail.append(
                "The encoder rows above were kept from the previous run (this one skipped the encoder): "
                + prev.split(" (")[0].replace("Produced by", "produced by")
                + "."
            )
            kept_tail.append("")
        if kept_rows:
            table = "\n".join(lines[:2] + kept_rows + lines[2:])
    cmd = args.command or "benches/peers/run.sh"
    mach = report["machine"]
    md = [
        "## Side by side with Brian2 and scikit-learn",
        "",
        f"Produced by `{cmd}` on {time.strftime('%Y-%m-%d %H:%M')} ({mach['cpu']}, {mach['cores']} cores, "
        f"Python {mach['python']}). Load average (1/5/15 min) {load_start[0]:.2f}/{load_start[1]:.2f}/{load_start[2]:.2f} "
        f"at the start, {load_end[0]:.2f}/{load_end[1]:.2f}/{load_end[2]:.2f} at the end. Times are the best of several samples of "
        "wall time per call (medians and CPU times are in results.json)"
        + (
            f", the baselines' over {report['baselines']['rounds']} rounds with the sides alternated (palpate, then scikit-learn, in each round)"
            if report.get("baselines", {}).get("rounds", 1) > 1
            else ""
        )
        + "; "
        "Brian2's is its simulation loop (code generation and compilation excluded, reported in results.json), "
        "palpate's the encoder kernel or the fit/predict calls on the same arrays. speed-up = peer / palpate. "
        "See benches/peers/README.md for what is measured and how fairness was handled.",
        "",
        table,
        "",
    ]
    if target_lines:
        md += [
            "Issue 8's target, the encoder at least 100x faster than Brian2 on 16 taxels x 40 s with the same "
            f"spike counts (palpate's default `{report['encoder']['meta']['default_scheme']}` scheme, Brian2 code "
            "as a user writes it):",
            "",
            *target_lines,
            "",
        ]
    if setup_lines:
        md += ["Brian2's one-off setup on the first run (code generation and compilation, not in the table): "
               + "; ".join(setup_lines) + ".", ""]
    md += kept_tail
    if base_lines:
        md += [
            "Issue 17's target, every trained estimator at least 3x faster than its scikit-learn counterpart "
            "for fit and for predict at equal or better accuracy (trial MAE no higher, frame accuracy no lower "
            "by more than 0.01), on fold 0 of the lab data set:",
            "",
            *base_lines,
            "",
        ]
    args.md.write_text("\n".join(md))
    print(f"\nwrote {work / 'results.json'} and {args.md}")


if __name__ == "__main__":
    main()
