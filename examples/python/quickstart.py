"""The quickstart from Python: run the graph, compare WSS with a scikit-learn
model on the same spike images, and plot both.

    pip install ./python matplotlib scikit-learn
    python examples/python/quickstart.py [--out out/python-quickstart]

1. runs graphs/quickstart.toml exactly as `palpate run` does (same reports in
   the output folder) and prints its MAE;
2. rebuilds the same spike images with the building blocks (the same Rust
   stages, on NumPy arrays) and trains a scikit-learn logistic regression on
   them, leave-one-repetition-out, as palpate's trained baselines are tested;
3. plots per-class MAE of both to <out>/wss_vs_sklearn.png.
"""

import argparse
import pathlib

import numpy as np

import palpate

REPO = pathlib.Path(__file__).resolve().parents[2]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/python-quickstart", help="output folder")
    ap.add_argument("--folds", type=int, default=10, help="repetitions held out in turn (<= 10)")
    ap.add_argument(
        "--trials-per-angle",
        type=int,
        default=None,
        help="trials per angle (default: the scene's 10; fewer for a quick look)",
    )
    args = ap.parse_args()
    out = pathlib.Path(args.out)

    # 1. The graph, as the CLI runs it.
    keys = {} if args.trials_per_angle is None else {"trials_per_angle": args.trials_per_angle}
    res = palpate.run(
        REPO / "graphs" / "quickstart.toml",
        out=out,
        set={f"stages.scene.{k}": v for k, v in keys.items()},
    )
    print(res.report_text())
    print(res.timing_table)
    wss = res.estimates["wss"]
    print(f"WSS: MAE {res.metrics['wss.mae_deg']:.2f} deg over {len(wss)} trials")

    # 2. The same pipeline through the building blocks, then scikit-learn.
    from sklearn.linear_model import LogisticRegression
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    d = palpate.simulate(REPO / "graphs" / "scenes" / "lab.toml", seed=1, **keys)
    # The building blocks give the graph's own images: WSS on them answers as
    # the graph did, bit for bit.
    assert d.trial_ids == list(res.estimates["wss"].trial_id), "trial order differs from the graph's"
    x = palpate.lowpass(d.trials, cutoff_hz=10.0, order=2)
    x = palpate.normalize(x, min_span=0.1)
    x = palpate.drive(x, kind="fa_i")
    images = palpate.bin(palpate.izhikevich(x, preset="fa_i"), window_ms=100.0, hop_ms=10.0)
    again = palpate.wss(images, weighting="one_minus_sr", angles={"from": 10, "to": 90, "step": 5})
    same = np.array_equal(np.stack([e.scores for e in again]), wss.scores)
    print(f"building blocks -> WSS: {'the same scores as the graph, bit for bit' if same else 'DIFFERENT scores'}")
    if not same:
        raise SystemExit("the building blocks disagree with the graph")
    n = min(len(im.counts) for im in images)
    X = np.stack([im.counts[:n].ravel() for im in images])
    y = d.labels
    pred = np.full(len(y), np.nan)
    for g in range(min(args.folds, int(d.groups.max()) + 1)):
        test = d.groups == g
        clf = make_pipeline(StandardScaler(), LogisticRegression(max_iter=3000))
        clf.fit(X[~test], y[~test].astype(int))
        pred[test] = clf.predict(X[test])
    done = ~np.isnan(pred)
    sk_err = np.abs(pred[done] - y[done])
    print(f"scikit-learn logistic regression: MAE {sk_err.mean():.2f} deg over {done.sum()} trials")

    # 3. Per-class MAE of both.
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    angles = np.unique(y)
    wss_mae = [np.mean(np.abs(wss.estimate[wss.label == a] - a)) for a in angles]
    sk_mae = [np.mean(np.abs(pred[done & (y == a)] - a)) for a in angles]
    fig, ax = plt.subplots(figsize=(8, 3.5))
    w = 1.8
    ax.bar(angles - w / 2, wss_mae, width=w, label=f"WSS (MAE {np.mean(np.abs(wss.estimate - wss.label)):.2f}°)")
    ax.bar(angles + w / 2, sk_mae, width=w, label=f"logistic regression (MAE {sk_err.mean():.2f}°)")
    ax.set_xlabel("true edge orientation (deg)")
    ax.set_ylabel("MAE (deg)")
    ax.set_xticks(angles)
    ax.legend()
    ax.set_title("quickstart scene: WSS vs a scikit-learn model on the same spike images")
    fig.tight_layout()
    out.mkdir(parents=True, exist_ok=True)
    fig.savefig(out / "wss_vs_sklearn.png", dpi=120)
    print(f"plot in {out / 'wss_vs_sklearn.png'}")


if __name__ == "__main__":
    main()
