"""Stages written in Python, run inside TOML graphs."""

import numpy as np
import pytest

import palpate

from conftest import GRAPHS


@palpate.stage("test_threshold", inputs="signals", output="spikes")
class Threshold:
    level: float = 0.5  # share of the trial's largest drive above which the taxel fires
    period_ms: float = 5.0  # time between spikes while above, ms

    def process(self, signals, ctx):
        x = signals.data
        above = x >= self.level * max(float(x.max()), 1e-12)
        step = max(1, round(self.period_ms * signals.sample_rate_hz / 1000.0))
        above[np.arange(len(x)) % step != 0] = False  # one spike per period while above
        k, taxel = np.nonzero(above)
        t_ms = k * 1000.0 / signals.sample_rate_hz
        order = np.lexsort((taxel, t_ms))
        return palpate.Spikes(taxel[order], t_ms[order], x.shape[0] * 1000.0 / signals.sample_rate_hz, signals.layout)


@palpate.stage("test_centroid", inputs="images", output="estimates")
class Centroid:
    calls = 0

    def fit(self, train, labels, ctx):
        feats = np.stack([im.counts.sum(axis=0) for im in train])
        self.classes = np.unique(labels)
        self.centroids = np.stack([feats[labels == c].mean(axis=0) for c in self.classes])
        self.fold = ctx["fold"]

    def predict(self, images, ctx):
        d = np.linalg.norm(self.centroids - images.counts.sum(axis=0), axis=1)
        return palpate.Estimate(float(self.classes[np.argmin(d)]), self.classes, -d)


@palpate.stage("test_needs_key", inputs="signals", output="signals")
class NeedsKey:
    gain: float  # required: no default

    def process(self, signals, ctx):
        return palpate.Signals(signals.data * self.gain, signals.sample_rate_hz, signals.layout, signals.unit)


@palpate.stage("test_broken", inputs="signals", output="signals")
class Broken:
    def process(self, signals, ctx):
        raise RuntimeError("deliberately broken")


def graph(tmp_path, enc_cfg="config = { level = 0.3 }", extra=""):
    return f"""
[run]
seed = 1
out = "{tmp_path / 'out'}"

[stages.scene]
type = "scene"
file = "{GRAPHS / 'scenes' / 'ideal.toml'}"
angles = [30.0, 60.0, 90.0]
trials_per_angle = 3

[stages.drive]
type = "drive"
inputs = ["scene"]
kind = "fa_i"

[stages.enc]
type = "python"
stage = "test_threshold"
inputs = ["drive"]
{enc_cfg}

[stages.bins]
type = "bin"
inputs = ["enc"]
window_ms = 100.0
hop_ms = 10.0

[stages.centroid]
type = "python"
stage = "test_centroid"
inputs = ["bins"]

[stages.wss]
type = "wss"
inputs = ["bins"]

[stages.mae]
type = "mae"
inputs = ["wss", "centroid"]
{extra}
"""


def test_python_encoder_and_estimator_run_in_a_graph(tmp_path):
    res = palpate.run(graph(tmp_path), threads=2, progress=False)
    c = res.estimates["centroid"]
    assert len(c) == 9
    assert np.isfinite(c.estimate).all() and set(np.unique(c.estimate)) <= {30.0, 60.0, 90.0}
    assert "centroid.mae_deg" in res.metrics and "wss.mae_deg" in res.metrics
    # The encoder made spikes the graph binned: WSS answered every trial.
    assert np.isfinite(res.estimates["wss"].estimate).mean() > 0.5
    # Same graph, same bits, on one thread or many.
    again = palpate.run(graph(tmp_path), threads=1, progress=False)
    assert np.array_equal(again.estimates["centroid"].scores, c.scores)
    assert np.array_equal(again.estimates["wss"].scores, res.estimates["wss"].scores)


def test_python_stage_key_errors_name_the_key(tmp_path):
    with pytest.raises(palpate.GraphError) as e:
        palpate.run(graph(tmp_path, "config = { levle = 2.0 }"), progress=False)
    assert e.value.stage == "enc" and e.value.key == "config.levle"
    assert "unknown key `levle`" in str(e.value) and "`level`" in str(e.value)
    with pytest.raises(palpate.GraphError) as e:
        palpate.run(graph(tmp_path, 'stage = "nope"'), progress=False)
    with pytest.raises(palpate.GraphError) as e:
        palpate.run(graph(tmp_path).replace('stage = "test_threshold"', 'stage = "nope"'), progress=False)
    assert "no Python stage `nope`" in str(e.value) and "test_threshold" in str(e.value)
    extra = '[stages.gain]\ntype = "python"\nstage = "test_needs_key"\ninputs = ["scene"]\n'
    with pytest.raises(palpate.GraphError) as e:
        palpate.run(graph(tmp_path, extra=extra), progress=False)
    assert e.value.key == "config.gain" and "missing key `gain`" in str(e.value)


def test_a_failing_python_stage_is_a_run_error_naming_stage_and_trial(tmp_path):
    extra = (
        '[stages.bad]\ntype = "python"\nstage = "test_broken"\ninputs = ["scene"]\n'
        '[stages.sink]\ntype = "write_signals"\ninputs = ["bad"]\n'
    )
    with pytest.raises(palpate.RunError) as e:
        palpate.run(graph(tmp_path, extra=extra), progress=False)
    assert e.value.stage == "bad" and e.value.trial is not None
    assert "deliberately broken" in str(e.value)


def test_python_stage_kinds_are_checked_when_the_graph_loads(tmp_path):
    # The centroid estimator takes images: wiring signals into it is a load error.
    bad = graph(tmp_path).replace('stage = "test_centroid"\ninputs = ["bins"]', 'stage = "test_centroid"\ninputs = ["drive"]')
    diags = palpate.check(bad)
    assert any(d.stage == "centroid" and "spike images" in d.message for d in diags)


def test_a_python_stage_is_a_stage_type_of_its_own(tmp_path):
    """`type = "<registered name>"` with the class's keys beside it is the same
    stage as the long form `type = "python"`, `stage = ..., config = {...}`."""
    long = palpate.run(graph(tmp_path), progress=False)
    short_text = (
        graph(tmp_path)
        .replace('type = "python"\nstage = "test_threshold"\ninputs = ["drive"]\nconfig = { level = 0.3 }',
                 'type = "test_threshold"\ninputs = ["drive"]\nlevel = 0.3')
        .replace('type = "python"\nstage = "test_centroid"', 'type = "test_centroid"')
    )
    assert 'type = "python"' not in short_text
    short = palpate.run(short_text, progress=False)
    for est in ("centroid", "wss"):
        assert np.array_equal(short.estimates[est].scores, long.estimates[est].scores)
    with pytest.raises(palpate.GraphError) as e:
        palpate.run(short_text.replace("level = 0.3", "levle = 0.3"), progress=False)
    assert e.value.stage == "enc" and "unknown key `levle`" in str(e.value)
    # A built-in type's name cannot be taken.
    with pytest.raises(ValueError, match="built-in"):

        @palpate.stage("bin", inputs="spikes", output="images")
        class Shadow:
            def process(self, spikes, ctx):
                return spikes


def test_python_stage_keys_are_checked_against_their_annotations(tmp_path):
    # `level: float` given a string reached `process` before, where the
    # comparison failed (or, for a key only stored, nothing did).
    with pytest.raises(palpate.GraphError) as e:
        palpate.run(graph(tmp_path, 'config = { level = "high" }'), progress=False)
    assert e.value.stage == "enc" and e.value.key == "config.level"
    assert "must be a number (float), got str 'high'" in str(e.value)
    with pytest.raises(palpate.GraphError, match="must be a number"):
        palpate.run(graph(tmp_path, "config = { level = true }"), progress=False)
    # An integer for a float key is the float (TOML's `level = 1`): the same run as 1.0.
    one = palpate.run(graph(tmp_path, "config = { level = 1 }"), progress=False)
    one_f = palpate.run(graph(tmp_path, "config = { level = 1.0 }"), progress=False)
    assert np.array_equal(one.estimates["wss"].scores, one_f.estimates["wss"].scores, equal_nan=True)


def test_check_key_follows_optional_and_generic_annotations():
    from typing import List, Optional

    check = palpate._check_key
    assert check("s", "k", None, Optional[float]) is None
    assert check("s", "k", 2, Optional[float]) == 2.0 and isinstance(check("s", "k", 2, Optional[float]), float)
    assert check("s", "k", [1, 2], List[int]) == [1, 2]
    assert check("s", "k", "anything", "NotAType") == "anything"  # unresolved: the stage's to check
    for value, hint in [(2.5, int), ("x", Optional[float]), (1, str), ({"a": 1}, List[int]), (1, bool)]:
        with pytest.raises(ValueError, match="key `k` of Python stage `s` must be"):
            check("s", "k", value, hint)


def test_a_stage_without_its_method_or_with_an_unusable_name_is_refused_when_registered():
    with pytest.raises(TypeError, match="needs a `process` method"):
        @palpate.stage("test_no_process", inputs="signals", output="spikes")
        class NoProcess:
            level: float = 0.5

    with pytest.raises(TypeError, match="needs a `predict` method"):
        @palpate.stage("test_no_predict", inputs="images", output="estimates")
        class NoPredict:
            def fit(self, train, labels, ctx):
                pass

    for name in ["", "two words", "1st", "a.b"]:
        with pytest.raises(ValueError, match="a stage name starts with a letter"):
            palpate.stage(name)


def test_a_registered_stage_is_applied_and_fitted_by_its_name():
    """`apply("test_threshold", ...)` said "unknown stage type"; only the long
    form `apply("python", stage=..., config=...)` worked."""
    s = palpate.Signals(np.tile(np.linspace(0.0, 1.0, 100)[:, None], (1, 16)), 1000.0)
    short = palpate.apply("test_threshold", s, level=0.3)
    long = palpate.apply("python", s, stage="test_threshold", config={"level": 0.3})
    assert len(short.taxel) > 0
    assert np.array_equal(short.taxel, long.taxel) and np.array_equal(short.t_ms, long.t_ms)
    with pytest.raises(palpate.ConfigError, match="unknown key `levle`"):
        palpate.apply("test_threshold", s, levle=0.3)
    rng = np.random.default_rng(0)
    ims = [palpate.Images(rng.random((3, 16)) + (i % 2), 100.0, 10.0) for i in range(4)]
    m = palpate.fit("test_centroid", ims, labels=[10.0, 20.0, 10.0, 20.0])
    assert list(m.predict_angles(ims)) == [10.0, 20.0, 10.0, 20.0]


@palpate.stage("test_wrong_kind", inputs="signals", output="spikes")
class WrongKind:
    def process(self, signals, ctx):
        return signals  # declared spikes


def test_a_python_stage_returning_another_kind_than_declared_is_named(tmp_path):
    """The next stage (`bins`) failed with "expected spike events, got analog
    signals", blaming itself."""
    g = {
        "run": {"seed": 1, "out": str(tmp_path / "out")},
        "stages": {
            "scene": {"type": "scene", "file": str(GRAPHS / "scenes" / "ideal.toml"), "angles": [30.0, 60.0], "trials_per_angle": 1},
            "enc": {"type": "test_wrong_kind", "inputs": ["scene"]},
            "bins": {"type": "bin", "inputs": ["enc"]},
            "wss": {"type": "wss", "inputs": ["bins"]},
            "mae": {"type": "mae", "inputs": ["wss"]},
        },
    }
    with pytest.raises(palpate.RunError, match=r'Python stage `test_wrong_kind` declares output="spikes" .* returned signals') as e:
        palpate.run(g, progress=False)
    assert e.value.stage == "enc"
