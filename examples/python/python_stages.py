"""Stages written in Python, run inside a TOML graph: a threshold encoder and
a nearest-centroid estimator, side by side with the built-in WSS.

    pip install ./python
    python examples/python/python_stages.py
"""

import pathlib

import numpy as np

import palpate

REPO = pathlib.Path(__file__).resolve().parents[2]


@palpate.stage("threshold_encoder", inputs="signals", output="spikes")
class ThresholdEncoder:
    """Fires every `period_ms` while a taxel's drive is at or above `level` times its largest value."""

    level: float = 0.5  # share of the trial's largest drive above which the taxel fires
    period_ms: float = 5.0  # time between spikes while above, ms

    def process(self, signals, ctx):
        x = signals.data  # (samples, taxels)
        above = x >= self.level * max(float(x.max()), 1e-12)
        step = max(1, round(self.period_ms * signals.sample_rate_hz / 1000.0))
        above[np.arange(len(x)) % step != 0] = False  # one spike per period while above
        k, taxel = np.nonzero(above)
        t_ms = k * 1000.0 / signals.sample_rate_hz
        order = np.lexsort((taxel, t_ms))
        duration_ms = x.shape[0] * 1000.0 / signals.sample_rate_hz
        return palpate.Spikes(taxel[order], t_ms[order], duration_ms, signals.layout)


@palpate.stage("nearest_centroid", inputs="images", output="estimates")
class NearestCentroid:
    """The class whose mean total spike image (summed over time) is nearest."""

    def fit(self, train, labels, ctx):
        feats = np.stack([im.counts.sum(axis=0) for im in train])
        self.classes = np.unique(labels)
        self.centroids = np.stack([feats[labels == c].mean(axis=0) for c in self.classes])

    def predict(self, images, ctx):
        f = images.counts.sum(axis=0)
        d = np.linalg.norm(self.centroids - f, axis=1)
        return palpate.Estimate(float(self.classes[np.argmin(d)]), self.classes, -d)


GRAPH = f"""
[run]
seed = 1
out = "out/python-stages"

[stages.scene]
type = "scene"
file = "{REPO / 'graphs' / 'scenes' / 'lab.toml'}"
trials_per_angle = 5

[stages.filter]
type = "lowpass"
inputs = ["scene"]
cutoff_hz = 10.0

[stages.norm]
type = "normalize"
inputs = ["filter"]
min_span = 0.1

[stages.drive]
type = "drive"
inputs = ["norm"]
kind = "fa_i"

[stages.enc]
type = "threshold_encoder"   # the name the class was registered under
inputs = ["drive"]
level = 0.3

[stages.bins]
type = "bin"
inputs = ["enc"]

[stages.wss]
type = "wss"
inputs = ["bins"]

[stages.centroid]
type = "nearest_centroid"
inputs = ["bins"]

[stages.mae]
type = "mae"
inputs = ["wss", "centroid"]
"""

if __name__ == "__main__":
    res = palpate.run(GRAPH)
    print(res.report_text())
