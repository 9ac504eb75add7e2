"""Round trips NumPy <-> palpate for every payload kind; tonic and scikit-learn
interoperability; the quickstart through Python equals the CLI's reports."""

import os
import pathlib
import shutil
import subprocess
import sys

import numpy as np
import pytest

import palpate

from conftest import GRAPHS, REPO, cli_path

tonic = pytest.importorskip("tonic") if os.environ.get("PALPATE_REQUIRE_TONIC") != "1" else __import__("tonic")
import tonic.transforms as T  # noqa: E402


def _spikes(seed=0, n=200, duration_ms=1000.0):
    rng = np.random.default_rng(seed)
    taxel = rng.integers(0, 16, n)
    t = np.sort(rng.integers(0, int(duration_ms * 1000), n)) / 1000.0  # whole µs
    return palpate.Spikes(taxel, t, duration_ms)


# ------------------------------------------------------------ round trips


def test_signals_round_trip_through_a_stage_that_copies():
    data = np.random.default_rng(1).normal(size=(300, 16))
    s = palpate.Signals(data, 500.0, unit="V", meta={"trial_id": "a", "angle_deg": 45.0, "group": 2})
    # `derivative` with order 0 does not exist; a crop of the whole trial is the identity
    # for spikes, so for signals we round-trip through the raw form and the Rust checks.
    raw = s.to_raw()
    back = palpate.Signals.from_raw(raw)
    assert np.array_equal(back.data, data) and back.sample_rate_hz == 500.0
    out = palpate.lowpass(s, cutoff_hz=240.0, order=1)
    assert out.data.shape == data.shape and out.meta["trial_id"] == "a" and out.meta["angle_deg"] == 45.0


def test_spikes_round_trip_through_rust_bit_exact():
    s = _spikes()
    out = palpate.apply("jitter", s, tau_ms=0.0)
    assert np.array_equal(out.taxel, s.taxel) and np.array_equal(out.t_ms, s.t_ms)
    assert out.duration_ms == s.duration_ms


def test_images_and_estimates_round_trip():
    s = _spikes()
    im = palpate.bin(s, window_ms=100.0, hop_ms=50.0)
    assert im.frames.shape[1:] == (4, 4)
    assert im.counts.sum() == pytest.approx(
        sum(((s.t_ms >= k * 50) & (s.t_ms < k * 50 + 100)).sum() for k in range(len(im.counts)))
    )
    back = palpate.Images.from_raw(im.to_raw())
    assert np.array_equal(back.counts, im.counts)
    est = palpate.wss(im)
    raw = est.to_raw()
    again = palpate.Estimate.from_raw(raw)
    assert np.array_equal(again.scores, est.scores) and again.angle_deg == est.angle_deg


def test_events_are_tonic_structured_arrays():
    s = _spikes()
    ev = s.events
    assert ev.dtype == palpate.EVENT_DTYPE
    assert ev.dtype.names == ("x", "y", "t", "p")
    assert s.sensor_size == (4, 4, 1)
    assert np.array_equal(ev["y"] * 4 + ev["x"], s.taxel)
    assert np.array_equal(ev["t"], np.rint(s.t_ms * 1000).astype(np.int64))
    back = palpate.Spikes.from_events(ev, s.sensor_size, s.duration_ms)
    assert np.array_equal(back.taxel, s.taxel) and np.array_equal(back.t_ms, s.t_ms)


def test_write_spikes_npy_is_tonics_dtype_and_spike_file_reads_it(tmp_path):
    g = f"""
[run]
seed = 1
out = "{tmp_path / 'o'}"
[stages.scene]
type = "scene"
file = "{GRAPHS / 'scenes' / 'ideal.toml'}"
angles = [45.0]
trials_per_angle = 2
[stages.drive]
type = "drive"
inputs = ["scene"]
[stages.enc]
type = "izhikevich"
inputs = ["drive"]
[stages.out]
type = "write_spikes"
inputs = ["enc"]
format = "npy"
"""
    palpate.run(g, progress=False)
    files = sorted((tmp_path / "o" / "out").glob("*.npy"))
    assert len(files) == 2
    ev = np.load(files[0])
    assert ev.dtype == palpate.EVENT_DTYPE and len(ev) > 0
    # tonic takes it as it is.
    frames = T.ToFrame(sensor_size=(4, 4, 1), n_time_bins=3)(ev.copy())
    # tonic's time bins end before the last event's time (end exclusive).
    assert frames.shape == (3, 1, 4, 4) and len(ev) - 1 <= frames.sum() <= len(ev)
    # ... and spike_file reads it back.
    g2 = f"""
[stages.src]
type = "spike_file"
path = "{tmp_path / 'o' / 'out' / '*.npy'}"
labels = "{tmp_path / 'o' / 'out' / 'labels.toml'}"
[stages.bins]
type = "bin"
inputs = ["src"]
window_ms = 100.0
hop_ms = 10.0
[stages.sink]
type = "write_images"
inputs = ["bins"]
"""
    res = palpate.run(g2, out=tmp_path / "o2", progress=False)
    assert "sink" in res.reports


# ------------------------------------------------------------ tonic


def test_tonic_toframe_agrees_with_palpate_binning():
    s = _spikes(seed=3, n=500, duration_ms=1000.0)
    ev = s.events
    # Non-overlapping 100 ms windows over [0, 1000) ms.
    frames = T.ToFrame(sensor_size=s.sensor_size, time_window=100_000, start_time=0, end_time=1_000_000)(ev.copy())
    ours = palpate.bin(s, window_ms=100.0, hop_ms=100.0).frames
    assert frames.shape[0] == ours.shape[0] == 10
    assert np.array_equal(frames[:, 0].astype(float), ours)
    # palpate binning of tonic events (no palpate object in between).
    via_events = palpate.bin(ev, window_ms=100.0, hop_ms=100.0, sensor_size=s.sensor_size, duration_ms=1000.0).frames
    assert np.array_equal(via_events, ours)


def test_tonic_time_jitter_then_palpate_binning():
    s = _spikes(seed=4, n=300)
    jittered = T.TimeJitter(std=2000, clip_negative=True, sort_timestamps=True)(s.events.copy())
    jittered = jittered[jittered["t"] < 1_000_000]
    ours = palpate.bin(jittered, window_ms=100.0, hop_ms=100.0, sensor_size=s.sensor_size, duration_ms=1000.0)
    theirs = T.ToFrame(sensor_size=s.sensor_size, time_window=100_000, start_time=0, end_time=1_000_000)(jittered.copy())
    assert np.array_equal(theirs[:, 0].astype(float), ours.frames)
    assert ours.counts.sum() == len(jittered)


# ------------------------------------------------------------ scikit-learn


def test_sklearn_classifier_on_palpate_features():
    sklearn = pytest.importorskip("sklearn") if os.environ.get("PALPATE_REQUIRE_SKLEARN") != "1" else __import__("sklearn")
    from sklearn.linear_model import LogisticRegression

    d = palpate.simulate(GRAPHS / "scenes" / "ideal.toml", seed=1, angles=[30.0, 60.0, 90.0], trials_per_angle=6)
    images = palpate.bin(palpate.izhikevich(palpate.drive(d.trials, kind="fa_i")), window_ms=100.0, hop_ms=10.0)
    n = min(len(im.counts) for im in images)
    X = np.stack([im.counts[:n].ravel() for im in images])
    y = d.labels.astype(int)
    train, test = d.groups >= 2, d.groups < 2
    clf = LogisticRegression(max_iter=2000).fit(X[train], y[train])
    acc = (clf.predict(X[test]) == y[test]).mean()
    assert acc >= 0.5, acc  # chance is 1/3


# ------------------------------------------------------------ the CLI


def test_quickstart_through_python_equals_the_cli(tmp_path):
    cli = cli_path()
    if cli is None:
        if os.environ.get("CI"):
            pytest.fail("no palpate binary: set PALPATE_CLI or build the workspace")
        pytest.skip("no palpate binary built")
    graph = GRAPHS / "quickstart.toml"
    subprocess.run([str(cli), "run", str(graph), "--out", str(tmp_path / "cli")], check=True, capture_output=True)
    res = palpate.run(graph, out=tmp_path / "py", progress=False)
    for f in ("mae.json", "mae.csv", "mae_overall.csv", "mae.md"):
        assert (tmp_path / "cli" / f).read_bytes() == (tmp_path / "py" / f).read_bytes(), f
    import json

    cli_rec = json.loads((tmp_path / "cli" / "run.json").read_text())
    assert cli_rec["metrics"] == res.record["metrics"]
    assert cli_rec["stages"] == res.record["stages"]


def test_sweep_through_python_equals_the_cli(small_graph, tmp_path):
    """A graph with a [sweep] runs from Python through the CLI's own sweep code:
    same sweep.csv / sweep.json as `palpate run`, one run per seed, and a second
    call reuses the completed points instead of running them again."""
    cli = cli_path()
    if cli is None:
        if os.environ.get("CI"):
            pytest.fail("no palpate binary: set PALPATE_CLI or build the workspace")
        pytest.skip("no palpate binary built")
    text = small_graph + '\n[sweep]\nkey = "stages.wss.weighting"\nvalues = ["constant", "one_minus_sr"]\nrepeats = 2\nmetrics = ["wss.mae_deg"]\n'
    path = tmp_path / "sweep.toml"
    path.write_text(text)
    subprocess.run([str(cli), "run", str(path), "--out", str(tmp_path / "cli")], check=True, capture_output=True)
    res = palpate.run(path, out=tmp_path / "py", progress=False)
    assert isinstance(res, palpate.SweepResult)
    for f in ("sweep.csv", "sweep.json"):
        assert (tmp_path / "cli" / f).read_bytes() == (tmp_path / "py" / f).read_bytes(), f
    assert len(res.runs) == 4 and {r["value"] for r in res.runs} == {"constant", "one_minus_sr"}
    assert len({r["seed"] for r in res.runs}) == 2  # repeats draw different seeds
    means = dict((label, mean) for label, mean, _sd, _n in res.summary("wss.mae_deg"))
    for label in ("constant", "one_minus_sr"):
        runs = [r["metrics"]["wss.mae_deg"] for r in res.runs if r["value"] == label]
        assert means[label] == pytest.approx(sum(runs) / len(runs), abs=1e-12)
    # Resumed: the markers are reused, the answer is the same.
    marker = next((tmp_path / "py").rglob("point.json"))
    before = marker.stat().st_mtime_ns
    again = palpate.run(path, out=tmp_path / "py", progress=False)
    assert marker.stat().st_mtime_ns == before
    assert again.rows == res.rows
    # fresh=True runs every point again.
    palpate.run(path, out=tmp_path / "py", progress=False, fresh=True)
    assert marker.stat().st_mtime_ns != before


def test_set_sweep_repeats_runs_a_graph_over_seeds(small_graph, tmp_path):
    """`set={"sweep.repeats": 3}` turns a graph without a sweep into one point
    run at seeds 1, 2, 3, whose summary is the mean of the three runs."""
    res = palpate.run(small_graph, set={"sweep.repeats": 3}, out=tmp_path / "seeds", progress=False)
    assert isinstance(res, palpate.SweepResult)
    assert sorted(r["seed"] for r in res.runs) == [1, 2, 3]
    ((_label, mean, _sd, n),) = res.summary("wss.mae_deg")
    runs = [r["metrics"]["wss.mae_deg"] for r in res.runs]
    assert n == 3 and mean == pytest.approx(sum(runs) / 3, abs=1e-12)


def test_readme_example_runs_verbatim(tmp_path):
    """The README's Python example, as printed there, from a folder holding the
    repository's graphs/: it runs and its WSS answers equal the simulated labels."""
    text = (REPO / "README.md").read_text()
    start = text.index("```python", text.index("## From Python")) + len("```python")
    code = text[start : text.index("```", start)]
    env = dict(os.environ, PYTHONPATH="")
    # A folder that looks like the repository root (its graphs/) so the
    # example's relative paths hold, while its reports land in tmp_path/out.
    (tmp_path / "graphs").symlink_to(REPO / "graphs", target_is_directory=True)
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True, check=True
    ).stdout.splitlines()
    assert (tmp_path / "out" / "quickstart" / "mae.json").is_file()
    answers, labels = out[-1].split("] [")
    assert [float(a) for a in answers.strip("[]").split(",")] == [float(v) for v in labels.strip("[]").split()]
