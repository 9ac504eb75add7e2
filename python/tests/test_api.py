"""palpate's Python API: graphs, diagnostics, scenes, building blocks, errors."""

import json
import math
import os

import numpy as np
import pytest

import palpate

from conftest import GRAPHS, REPO


def test_run_returns_estimates_metrics_and_timing(small_graph, tmp_path):
    res = palpate.run(small_graph, threads=2, progress=False)
    wss = res.estimates["wss"]
    assert len(wss) == 9
    assert wss.scores.shape == (9, 17)
    assert set(np.unique(wss.label)) == {30.0, 60.0, 90.0}
    assert np.isfinite(wss.estimate).all()
    # The metric is the mean absolute error of these very estimates.
    mae = np.mean(np.abs(wss.estimate - wss.label))
    assert res.metrics["wss.mae_deg"] == pytest.approx(mae, abs=1e-12)
    assert [r["stage"] for r in res.timing] == ["scene", "filter", "norm", "drive", "enc", "bins", "wss", "mae"]
    recs = wss.records()
    assert recs[0]["trial_id"] == wss.trial_id[0] and "score_10" in recs[0]
    # run.json: objects keyed by name.
    record = json.loads((tmp_path / "out" / "run.json").read_text())
    assert isinstance(record["metrics"], dict) and record["metrics"]["wss.mae_deg"] == res.metrics["wss.mae_deg"]
    assert isinstance(record["stages"], dict) and "wss" in record["stages"]


def test_per_class_csv_is_numeric_and_overall_row_is_separate(small_graph, tmp_path):
    palpate.run(small_graph, progress=False)
    per_class = np.genfromtxt(tmp_path / "out" / "mae.csv", delimiter=",", names=True, dtype=None, encoding="utf-8")
    assert per_class["angle_deg"].dtype.kind in "if"
    assert per_class["mae_deg"].dtype.kind in "if"  # all-zero errors parse as integers
    assert list(per_class["angle_deg"]) == [30.0, 60.0, 90.0]
    overall = (tmp_path / "out" / "mae_overall.csv").read_text().splitlines()
    assert overall[0].startswith("estimator,trials,") and overall[1].startswith("wss,9,")


def test_run_accepts_a_dict_and_set_overrides(tmp_path):
    g = {
        "run": {"seed": 3, "out": str(tmp_path / "o")},
        "stages": {
            "scene": {"type": "scene", "file": str(GRAPHS / "scenes" / "ideal.toml"), "angles": [45.0], "trials_per_angle": 2},
            "drive": {"type": "drive", "inputs": ["scene"], "kind": "fa_i"},
            "enc": {"type": "izhikevich", "inputs": ["drive"]},
            "bins": {"type": "bin", "inputs": ["enc"], "window_ms": 100.0, "hop_ms": 10.0},
            "wss": {"type": "wss", "inputs": ["bins"]},
            "mae": {"type": "mae", "inputs": ["wss"]},
        },
    }
    a = palpate.run(g, progress=False)
    b = palpate.run(g, set={"stages.wss.weighting": "one_minus_sr"}, progress=False)
    assert len(a.estimates["wss"]) == 2
    assert a.record["stages"]["wss"]["wss"]["weighting"] != b.record["stages"]["wss"]["wss"]["weighting"]
    # A graph "file" that never ends is refused at the cap, not read forever.
    if os.path.exists("/dev/zero"):
        with pytest.raises(palpate.GraphError, match="cap of 67108864 bytes"):
            palpate.run("/dev/zero", progress=False)
    # A mistyped thread count is refused at once (it used to hang starting them).
    with pytest.raises(ValueError, match="over the cap of 4096"):
        palpate.run(g, threads=10**11, progress=False)


def test_check_gives_diagnostics_with_line_stage_and_key():
    bad = """
[run]
seed = 1

[stages.scene]
type = "scene"

[stages.enc]
type = "izhikevich"
inputs = ["scene"]
dt_ms = "fast"

[stages.est]
type = "wss"
inputs = ["enc"]
sigma = 2
"""
    diags = palpate.check(bad)
    errors = [d for d in diags if d.severity == "error"]
    by_stage = {d.stage: d for d in errors}
    assert by_stage["enc"].key == "dt_ms" and by_stage["enc"].line == 11
    assert by_stage["est"].key == "sigma" and "sigma_mm" in by_stage["est"].message
    assert all(d.file == "<string>" for d in diags)
    assert palpate.check(GRAPHS / "quickstart.toml") == []


def test_graph_errors_are_exceptions_carrying_file_line_stage_key(tmp_path):
    p = tmp_path / "bad.toml"
    p.write_text('[stages.a]\ntype = "scene"\n\n[stages.b]\ntype = "mea"\ninputs = ["a"]\n')
    with pytest.raises(palpate.GraphError) as e:
        palpate.run(p, progress=False)
    err = e.value
    assert err.file == str(p) and err.line == 5 and err.stage == "b" and err.key == "type"
    assert "did you mean `mae`" in str(err)
    assert any(d["stage"] == "b" for d in err.diagnostics)
    with pytest.raises(palpate.GraphError):
        palpate.run(tmp_path / "missing.toml")


def test_simulate_matches_the_graph_scene_and_is_seeded():
    d = palpate.simulate(GRAPHS / "scenes" / "lab.toml", seed=1, angles=[30.0, 60.0], trials_per_angle=2)
    assert d.signals.ndim == 3 and d.signals.shape[0] == 4 and d.signals.shape[2] == 16
    assert list(d.labels) == [30.0, 30.0, 60.0, 60.0]
    assert list(d.speed_mm_s) == [2.0] * 4  # the scene's motion.speed_mm_s
    fast = palpate.simulate(GRAPHS / "scenes" / "lab.toml", seed=1, angles=[30.0], trials_per_angle=1, motion={"speed_mm_s": 4.0})
    assert list(fast.speed_mm_s) == [4.0]
    # Trials differ in length (the angle sets the crossing time): the stack is
    # NaN-padded at the end, and each trial's own samples are all finite.
    for k, t in enumerate(d.trials):
        n = t.data.shape[0]
        assert np.isfinite(t.data).all() and np.array_equal(d.signals[k, :n], t.data)
        assert np.isnan(d.signals[k, n:]).all()
    again = palpate.simulate(GRAPHS / "scenes" / "lab.toml", seed=1, angles=[30.0, 60.0], trials_per_angle=2)
    other = palpate.simulate(GRAPHS / "scenes" / "lab.toml", seed=2, angles=[30.0, 60.0], trials_per_angle=2)
    assert np.array_equal(d.signals, again.signals, equal_nan=True)
    assert not np.array_equal(d.signals, other.signals, equal_nan=True)


def test_read_signals_gives_the_recordings_a_graph_reads(tmp_path):
    """read_signals on the shipped recording: the CSV's samples, the label
    file's angles, the files' rate; through the building blocks, the same WSS
    answers as the recording's graph."""
    rec = REPO / "examples" / "recording"
    d = palpate.read_signals(rec / "trial*.csv", labels=rec / "labels.csv", unit="mV")
    assert d.trial_ids == ["trial01", "trial02", "trial03", "trial04"]
    assert list(d.labels) == [40.0, 60.0, 75.0, 90.0] and list(d.speed_mm_s) == [2.0] * 4
    assert d.sample_rate_hz == 100.0 and d.unit == "mV" and np.isnan(d.crossing_ms).all()
    raw = np.loadtxt(rec / "trial02.csv", delimiter=",", skiprows=1)
    assert np.array_equal(d.trials[1].data, raw[:, 1:])
    res = palpate.run(rec / "recording.toml", out=tmp_path / "graph", progress=False)
    x = palpate.lowpass(d.trials, cutoff_hz=10.0)
    x = palpate.drive(palpate.normalize(x, min_span=100.0), kind="fa_i")
    est = palpate.wss(palpate.bin(palpate.izhikevich(x, preset="fa_i"), window_ms=100.0, hop_ms=10.0))
    assert [e.angle_deg for e in est] == list(res.estimates["wss"].estimate)


def test_read_signals_cuts_one_log_into_palpations(tmp_path):
    """segment="contact": a log of two presses (4 taxels, 500 Hz) is two trials,
    each exactly its samples in contact; no contact is an error naming the file."""
    off, on = np.full((100, 4), 3.3), 1.75 + 0.01 * np.arange(4) + np.zeros((150, 4))
    log = np.vstack([off, on, off, on[:120] + 0.01, off])
    header = "taxel_0,taxel_1,taxel_2,taxel_3"
    np.savetxt(tmp_path / "log.csv", log, delimiter=",", header=header, comments="")
    grid2 = {"kind": "grid", "rows": 2, "cols": 2, "pitch_mm": 3.0, "taxel_mm": 2.0}
    d = palpate.read_signals(tmp_path / "log.csv", layout=grid2, sample_rate_hz=500.0, segment="contact")
    assert d.trial_ids == ["log-0", "log-1"]
    assert [t.data.shape for t in d.trials] == [(150, 4), (120, 4)]
    assert np.array_equal(d.trials[1].data, on[:120] + 0.01)
    with pytest.raises(palpate.PalpateError, match="found no trial"):
        palpate.read_signals(tmp_path / "log.csv", layout=grid2, sample_rate_hz=500.0, segment="contact", contact_v=1.0, release_v=1.1)
    with pytest.raises(palpate.PalpateError, match="release_v"):
        palpate.read_signals(tmp_path / "log.csv", layout=grid2, sample_rate_hz=500.0, segment="contact", release_v=2.0)


def test_building_blocks_chain_to_the_graph_result(small_graph, tmp_path):
    """filter -> normalize -> drive -> izhikevich -> bin -> wss through the
    building blocks gives exactly the graph's estimates (same code, same bits)."""
    res = palpate.run(small_graph, progress=False)
    d = palpate.simulate(GRAPHS / "scenes" / "lab.toml", seed=1, angles=[30.0, 60.0, 90.0], trials_per_angle=3)
    x = palpate.lowpass(d.trials, cutoff_hz=10.0, order=2)
    x = palpate.normalize(x, min_span=0.1)
    x = palpate.drive(x, kind="fa_i")
    spikes = palpate.izhikevich(x, preset="fa_i")
    images = palpate.bin(spikes, window_ms=100.0, hop_ms=10.0)
    est = palpate.wss(images, weighting="one_minus_sr", angles={"from": 10, "to": 90, "step": 5})
    got = np.array([e.angle_deg for e in est])
    assert np.array_equal(got, res.estimates["wss"].estimate)
    assert np.array_equal(np.stack([e.scores for e in est]), res.estimates["wss"].scores)


def test_encoders_on_plain_arrays():
    fs = 1000.0
    currents = np.zeros((2000, 16))
    currents[:, 5] = 10.0  # one taxel driven well above rheobase
    s = palpate.izhikevich(currents, sample_rate_hz=fs)
    assert isinstance(s, palpate.Spikes)
    assert len(s.taxel) > 5 and set(s.taxel.tolist()) == {5}
    assert np.all(np.diff(s.t_ms) >= 0) and s.duration_ms == pytest.approx(2000.0)
    l = palpate.lif(currents * 10, sample_rate_hz=fs)
    assert set(l.taxel.tolist()) <= {5}
    batch = palpate.izhikevich(np.stack([currents, currents]), sample_rate_hz=fs)
    assert len(batch) == 2 and np.array_equal(batch[0].t_ms, batch[1].t_ms)
    # Another taxel count: one row of taxels, said.
    with pytest.warns(UserWarning, match="1 x 17 row"):
        s = palpate.izhikevich(np.zeros((200, 17)), sample_rate_hz=fs)
    assert (s.layout["rows"], s.layout["cols"]) == (1, 17)


def test_bad_config_and_bad_arrays_raise_named_errors():
    with pytest.raises(palpate.ConfigError) as e:
        palpate.izhikevich(np.zeros((10, 16)), sample_rate_hz=1000.0, dt_ms="fast")
    assert e.value.key == "dt_ms"
    with pytest.raises(palpate.ConfigError) as e:
        palpate.apply("izhikevik", palpate.Signals(np.zeros((10, 16)), 1000.0))
    assert "did you mean" in str(e.value)
    with pytest.raises(ValueError, match="columns"):
        palpate.izhikevich(palpate.Signals(np.zeros((10, 15)), 1000.0))
    with pytest.raises(ValueError, match="outside"):
        palpate.bin(palpate.Spikes([99], [1.0], 10.0))
    with pytest.raises(ValueError, match="outside"):
        palpate.bin(palpate.Spikes([1], [float("nan")], 10.0))
    with pytest.raises(palpate.ConfigError):
        palpate.bin(palpate.Spikes([1], [1.0], 10.0), window_ms=-1.0)
    spikes = palpate.Spikes([1], [1.0], 10.0)
    with pytest.raises(ValueError, match=r"stage type `bin` takes 1 input\(s\) per trial, got 2"):
        palpate.apply("bin", spikes, spikes)  # the second was dropped unseen


@pytest.mark.parametrize(
    "taxel, match",
    [
        ([-1], "taxel -1 of spike 0 is not a taxel index"),  # NumPy's cast made it 4294967295
        ([3, 2**40], "taxel 1099511627776 of spike 1"),  # ... and this 0
        ([1.7], "taxel 1.7 of spike 0 is not a whole number"),  # ... and this 1
        ([np.nan], "not a whole number"),
        ([True], "integer indices"),
        ([[1]], "1-D"),
    ],
)
def test_spike_taxels_that_numpy_would_wrap_or_cut_are_refused(taxel, match):
    with pytest.raises(ValueError, match=match):
        palpate.Spikes(taxel, [1.0] * len(taxel), 10.0)


def test_payload_arrays_of_the_wrong_kind_or_shape_are_refused_at_construction():
    with pytest.raises(ValueError, match="2 taxels but 1 times"):
        palpate.Spikes([1, 2], [1.0], 10.0)
    with pytest.raises(ValueError, match="real numbers"):
        palpate.Signals(np.ones((10, 16)) * (1 + 1j), 1000.0)  # the cast dropped the imaginary part
    with pytest.raises(ValueError, match="real numbers"):
        palpate.Images(np.ones((3, 16), dtype=complex), 100.0, 10.0)
    with pytest.raises(ValueError, match=r"got shape \(16,\)"):
        palpate.Images(np.ones(16), 100.0, 10.0)  # was a TypeError about PyArray<T, D>
    with pytest.raises(ValueError, match=r"got shape \(10,\)"):
        palpate.lowpass(np.zeros(10), sample_rate_hz=1000.0)  # was an IndexError
    # What is right still passes: whole floats and an empty list.
    assert palpate.Spikes([3.0], [1.0], 10.0).taxel.tolist() == [3]
    assert palpate.bin(palpate.Spikes([], [], 100.0)).counts.sum() == 0
    assert palpate.Images(np.ones((2, 4, 4)), 100.0, 10.0).counts.shape == (2, 16)


def test_seeds_outside_the_run_seed_range_name_the_seed():
    for seed in (-1, 2**64):
        with pytest.raises(ValueError, match=r"seed must be an integer in \[0, 2\*\*64\)"):
            palpate.simulate(GRAPHS / "scenes" / "ideal.toml", seed=seed)
    with pytest.raises(TypeError, match="seed must be an integer"):
        palpate.apply("jitter", palpate.Spikes([1], [1.0], 10.0), seed="1")


def test_a_nan_label_is_no_label_and_fit_says_it_skipped_it():
    rng = np.random.default_rng(1)
    imgs = [palpate.Images(rng.random((10, 16)), 100.0, 10.0) for _ in range(3)]
    with pytest.warns(UserWarning, match="1 of 3 training payloads have a NaN label"):
        palpate.fit("knn", imgs, labels=[np.nan, 10.0, 20.0])
    with pytest.raises(ValueError, match="`labels` must be angles"):
        palpate.fit("knn", imgs, labels=["a", 10.0, 20.0])

def test_hostile_values_give_no_nan_and_no_panic():
    for value in (np.inf, -np.inf, np.nan, 1e300, -1e300):
        x = np.full((50, 16), value)
        try:
            s = palpate.izhikevich(x, sample_rate_hz=1000.0)
        except (ValueError, palpate.PalpateError):
            continue  # refused, with a message: fine
        assert np.isfinite(s.t_ms).all()


def test_stage_types_lists_keys_with_docs():
    types = {t["type"]: t for t in palpate.stage_types()}
    assert {"scene", "izhikevich", "lif", "bin", "wss", "ann", "python"} <= set(types)
    keys = {k["name"]: k for k in types["bin"]["keys"]}
    assert "window_ms" in keys and "ms" in keys["window_ms"]["doc"]


def test_trained_baseline_fit_predict_matches_its_graph():
    d = palpate.simulate(GRAPHS / "scenes" / "ideal.toml", seed=1, angles=[30.0, 60.0, 90.0], trials_per_angle=4)
    spikes = palpate.izhikevich(palpate.drive(d.trials, kind="fa_i"))
    images = palpate.bin(spikes, window_ms=100.0, hop_ms=10.0)
    train = [im for im, g in zip(images, d.groups) if g != 0]
    test = [im for im, g in zip(images, d.groups) if g == 0]
    model = palpate.fit("knn", train, seed=1)
    pred = model.predict_angles(test)
    assert pred.shape == (3,)
    assert np.isfinite(pred).all()
    # Refitting with the same seed gives the same model.
    assert np.array_equal(pred, palpate.fit("knn", train, seed=1).predict_angles(test))
    # One label per training payload: a list of another length is refused by
    # name, not cut short or failed inside NumPy.
    angles = [im.meta["angle_deg"] for im in train]
    assert np.array_equal(pred, palpate.fit("knn", iter(train), labels=np.array(angles), seed=1).predict_angles(test))
    for wrong in (angles[:-1], angles + [45.0]):
        with pytest.raises(ValueError, match="`labels` has .* entries but `train` has"):
            palpate.fit("knn", train, labels=wrong)


def test_a_seed_above_tomls_integers_is_accepted_from_a_dict_and_from_set():
    g = {
        "run": {"seed": 2**64 - 1},
        "stages": {
            "scene": {"type": "scene", "file": str(GRAPHS / "scenes" / "ideal.toml"), "angles": [45.0], "trials_per_angle": 1},
            "drive": {"type": "drive", "inputs": ["scene"], "kind": "fa_i"},
            "enc": {"type": "izhikevich", "inputs": ["drive"]},
            "bins": {"type": "bin", "inputs": ["enc"]},
            "wss": {"type": "wss", "inputs": ["bins"]},
            "mae": {"type": "mae", "inputs": ["wss"]},
        },
    }
    assert [d for d in palpate.check(g) if d.severity == "error"] == []
    assert [d for d in palpate.check(g, set={"run.seed": 2**63}) if d.severity == "error"] == []
    bad = palpate.check(g, set={"run.seed": -1})
    assert any("a seed is a whole number" in d.message for d in bad), bad


def test_run_live_streams_the_graph_and_times_each_stage(tmp_path):
    updates = []
    res = palpate.run_live(
        str(GRAPHS / "live.toml"),
        set={"stages.daq.angles": [60.0], "stages.daq.trials_per_angle": 1},
        out=tmp_path / "live",
        on_update=updates.append,
    )
    assert isinstance(res, palpate.LiveResult)
    wss = res.estimates["wss"]
    assert len(wss) == 1 and wss.estimate[0] == pytest.approx(60.0)
    assert res.metrics["wss.mae_deg"] == pytest.approx(0.0, abs=1e-9)
    # Every estimate as it changed, then the trial's final one: the answer.
    assert updates and all(u["stage"] == "wss" for u in updates)
    assert [u["last"] for u in updates].count(True) == 1 and updates[-1]["last"]
    assert updates[-1]["estimate"]["angle_deg"] == wss.estimate[0]
    t = [u["t_ms"] for u in updates]
    assert t == sorted(t)
    live = res.live
    assert live["trials"] == 1 and live["blocks"] == round(live["stream_s"] * 1000)
    assert [s["stage"] for s in live["stages"]] == ["filter", "norm", "drive", "enc", "bins", "wss"]
    assert sum(s["share_pct"] for s in live["stages"]) == pytest.approx(100.0)
    assert "share" in res.timing_table
    for f in ("run.json", "live_timing.md", "live_timing.csv", "mae.csv"):
        assert (tmp_path / "live" / f).exists(), f


def test_run_live_stops_at_an_exception_from_on_update_and_raises_it(tmp_path, small_graph, sigint):
    def enough(u):
        if u["last"]:
            raise ValueError("one trial is enough")

    with pytest.raises(ValueError, match="one trial is enough"):
        palpate.run_live(
            str(GRAPHS / "live.toml"),
            set={"stages.daq.angles": [30.0, 60.0], "stages.daq.trials_per_angle": 1},
            out=tmp_path / "live",
            on_update=enough,
        )
    # The stream stopped after the first trial; its record says so.
    record = json.loads((tmp_path / "live" / "run.json").read_text())
    assert record["live"]["trials"] == 1 and record["live"]["stopped"] is True
    overall = (tmp_path / "live" / "mae_overall.csv").read_text().splitlines()
    assert overall[1].startswith("wss,1,"), overall
    # Ctrl-C (here: the signal raised from the callback's thread) stops it too.
    import _thread

    with pytest.raises(KeyboardInterrupt):
        palpate.run_live(
            str(GRAPHS / "live.toml"),
            set={"stages.daq.angles": [30.0, 60.0], "stages.daq.trials_per_angle": 1},
            out=tmp_path / "live2",
            on_update=lambda u: _thread.interrupt_main(),
        )
    assert json.loads((tmp_path / "live2" / "run.json").read_text())["live"]["stopped"] is True
    # The quickstart filters zero-phase: not a live graph.
    with pytest.raises(palpate.PalpateError, match="filter.*cannot stream"):
        palpate.run_live(small_graph)
    with pytest.raises(ValueError, match="block"):
        palpate.run_live(str(GRAPHS / "live.toml"), block=0)


def test_ctrl_c_stops_a_live_session_with_nothing_in_contact(tmp_path, sigint):
    import _thread
    import threading

    # A contact threshold the board never reaches (it reads 1.75 V in
    # contact), played in real time: ~25 s of frames, no trial, no update.
    # Ctrl-C is checked between updates too, so the session stops.
    timer = threading.Timer(0.5, _thread.interrupt_main)
    timer.start()
    try:
        with pytest.raises(KeyboardInterrupt):
            palpate.run_live(
                str(GRAPHS / "live.toml"),
                set={
                    "stages.daq.angles": [60.0],
                    "stages.daq.trials_per_angle": 1,
                    "stages.daq.contact_v": 0.5,
                    "stages.daq.release_v": 0.6,
                    "stages.daq.speed": 1.0,
                },
                out=tmp_path / "live",
                on_update=lambda u: pytest.fail(f"an update with nothing in contact: {u}"),
            )
    finally:
        timer.cancel()
    record = json.loads((tmp_path / "live" / "run.json").read_text())
    assert record["live"]["stopped"] is True and record["live"]["trials"] == 0


def test_ctrl_c_interrupts_a_running_graph(tmp_path, sigint):
    import _thread
    import threading

    # The quickstart on the whole lab scene (170 trials): seconds of work.
    text = (GRAPHS / "quickstart.toml").read_text()
    text = text.replace('file = "scenes/lab.toml"', f'file = "{GRAPHS / "scenes" / "lab.toml"}"')
    text = text.replace("[run]\nseed = 1", f'[run]\nseed = 1\nout = "{tmp_path / "out"}"')
    timer = threading.Timer(0.3, _thread.interrupt_main)
    timer.start()
    try:
        with pytest.raises(KeyboardInterrupt):
            palpate.run(text, progress=False)
    finally:
        timer.cancel()
    # Stopped before its sinks: no report was written.
    assert not (tmp_path / "out" / "mae.csv").exists()


def test_a_model_saved_in_python_runs_in_a_graph_and_pickles_to_itself(tmp_path):
    """`Model.save` writes the file a graph's `model_in` reads: the graph's
    estimates are the Python model's, and a pickled or loaded model predicts
    the same bits (EDBN's stochastic inference included: the seed travels)."""
    import pickle

    d = palpate.simulate(GRAPHS / "scenes" / "ideal.toml", seed=1, angles=[30.0, 60.0, 90.0], trials_per_angle=3)
    images = palpate.bin(palpate.izhikevich(palpate.drive(d.trials, kind="fa_i")), window_ms=100.0, hop_ms=10.0)
    knn = palpate.fit("knn", images)
    path = knn.save(tmp_path / "knn.model.json")
    graph = f"""
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
type = "izhikevich"
inputs = ["drive"]
[stages.bins]
type = "bin"
inputs = ["enc"]
window_ms = 100.0
hop_ms = 10.0
[stages.knn]
type = "knn"
inputs = ["bins"]
model_in = "{path}"
[stages.mae]
type = "mae"
inputs = ["knn"]
"""
    res = palpate.run(graph, progress=False)
    mine = knn.predict(images)
    assert np.array_equal(res.estimates["knn"].scores, np.stack([e.scores for e in mine]))
    assert np.array_equal(res.estimates["knn"].estimate, knn.predict_angles(images))

    edbn = palpate.fit("edbn", images, seed=5, inference="spiking")
    scores = lambda m: np.stack([e.scores for e in m.predict(images)])
    want = scores(edbn)
    saved = edbn.save(tmp_path / "e.json")
    for other in (pickle.loads(pickle.dumps(edbn)), palpate.load_model(saved, seed=5)):
        assert other.type == "edbn" and other.seed == 5
        assert np.array_equal(scores(other), want)
    # The seed matters to spiking inference, so the check above could fail.
    assert not np.array_equal(scores(palpate.load_model(saved, seed=6)), want)

    with pytest.raises(TypeError, match="cannot pickle a `wss` model"):
        pickle.dumps(palpate.fit("wss", images))
    with pytest.raises(ValueError, match="call `model.save"):
        palpate.fit("knn", images, save_model=True)  # wrote /tmp/stage.fold0.model.json before
    with pytest.raises(ValueError, match="not a palpate model file"):
        palpate.load_model(tmp_path / "out" / "run.json")


# ---------------------------------------------------------------- QA fixes


def _filter_graph(tmp_path):
    """A small graph with a `lowpass` stage `filter` (for `set=` checks)."""
    return {
        "run": {"seed": 1, "out": str(tmp_path / "out")},
        "stages": {
            "scene": {"type": "scene", "file": str(GRAPHS / "scenes" / "ideal.toml"), "angles": [30.0, 60.0], "trials_per_angle": 1},
            "filter": {"type": "lowpass", "inputs": ["scene"], "cutoff_hz": 10.0},
            "drive": {"type": "drive", "inputs": ["filter"], "kind": "fa_i"},
            "enc": {"type": "izhikevich", "inputs": ["drive"]},
            "bins": {"type": "bin", "inputs": ["enc"]},
            "wss": {"type": "wss", "inputs": ["bins"]},
            "mae": {"type": "mae", "inputs": ["wss"], "per_class": False},
        },
    }


def test_a_graph_path_holding_an_equals_sign_is_a_path(tmp_path, monkeypatch):
    """`sweep/lr=0.1/graph.toml` was read as TOML text ("not valid TOML" in
    `<string>`); a one-line string naming no file that fails as TOML says it
    was read as TOML text."""
    monkeypatch.chdir(tmp_path)
    d = tmp_path / "sweep" / "lr=0.1"
    d.mkdir(parents=True)
    (d / "graph.toml").write_text(palpate._palpate_toml(_filter_graph(tmp_path)))
    assert [x for x in palpate.check("sweep/lr=0.1/graph.toml") if x.severity == "error"] == []
    # A file without the .toml ending, named by a string holding `=`, too.
    (d / "graph").write_text((d / "graph.toml").read_text())
    assert [x for x in palpate.check("sweep/lr=0.1/graph") if x.severity == "error"] == []
    # A .toml path that does not exist is a path (cannot read), not TOML text.
    with pytest.raises(palpate.GraphError, match="cannot read the graph file") as e:
        palpate.run("sweep/lr=0.2/graph.toml", progress=False)
    assert e.value.file == "sweep/lr=0.2/graph.toml"
    # No such file, no .toml ending, holds `=`: TOML text, and the error says so.
    diags = palpate.check("sweep/lr=0.2/graph")
    assert any("not valid TOML" in x.message and "no file `sweep/lr=0.2/graph` exists" in x.message for x in diags), diags
    with pytest.raises(palpate.GraphError, match="read as TOML text because no file"):
        palpate.run("sweep/lr=0.2/graph", progress=False)


def _stochastic_graph(tmp_path, seed):
    return f"""
[run]
seed = {seed}
out = "{tmp_path / 'out_a'}"
[stages.sim]
type = "scene"
file = "{GRAPHS / 'scenes' / 'lab.toml'}"
angles = [40.0]
trials_per_angle = 1
[stages.enc]
type = "izhikevich"
inputs = ["sim"]
[stages.jit]
type = "jitter"
inputs = ["enc"]
tau_ms = 5.0
[stages.ws]
type = "write_signals"
inputs = ["sim"]
format = "npy"
[stages.wsp]
type = "write_spikes"
inputs = ["jit"]
format = "npy"
"""


def test_building_blocks_reproduce_a_graph_stage_by_its_id(tmp_path):
    """`stage_id=` gives a building block the graph stage's seeds: simulate
    as scene `sim`, apply as stage `jit`, bit for bit at the same run seed;
    the defaults (`scene`, `stage`) keep their bits."""
    palpate.run(_stochastic_graph(tmp_path, 3), progress=False)
    sig = np.load(tmp_path / "out_a" / "ws" / "edge-40deg-r00.npy")
    ev = np.load(tmp_path / "out_a" / "wsp" / "edge-40deg-r00.npy")
    lab = GRAPHS / "scenes" / "lab.toml"
    d = palpate.simulate(lab, seed=3, stage_id="sim", angles=[40.0], trials_per_angle=1)
    assert np.array_equal(sig, d.trials[0].data)
    default = palpate.simulate(lab, seed=3, angles=[40.0], trials_per_angle=1)
    assert not np.array_equal(sig, default.trials[0].data)  # the id matters: the check above could fail
    raw = palpate._palpate.read_source("scene", {"file": str(lab), "angles": [40.0], "trials_per_angle": 1}, 3, None, "scene")
    assert np.array_equal(default.trials[0].data, raw[0]["data"])  # the default id is still `scene`
    sp = palpate.izhikevich(d.trials[0])
    j = palpate.apply("jitter", sp, seed=3, stage_id="jit", tau_ms=5.0)
    assert np.array_equal(ev["t"], j.events["t"])
    assert not np.array_equal(ev["t"], palpate.apply("jitter", sp, seed=3, tau_ms=5.0).events["t"])
    with pytest.raises(TypeError, match="stage_id"):
        palpate.apply("jitter", sp, seed=3, stage_id=3, tau_ms=5.0)


def test_fit_and_load_model_reproduce_a_graph_estimator_by_its_id(tmp_path):
    """EDBN's spiking inference: a model fitted or loaded with the graph's
    stage id predicts the graph's scores bit for bit (not so with the
    default id), and a pickled model keeps its id."""
    import pickle

    ideal = GRAPHS / "scenes" / "ideal.toml"
    d = palpate.simulate(ideal, seed=5, angles=[30.0, 60.0, 90.0], trials_per_angle=2)
    images = palpate.bin(palpate.izhikevich(palpate.drive(d.trials, kind="fa_i")), window_ms=100.0, hop_ms=10.0)
    edbn = palpate.fit("edbn", images, seed=5, stage_id="edbn", inference="spiking")
    assert edbn.stage_id == "edbn"
    path = edbn.save(tmp_path / "edbn.model.json")
    g = f"""
[run]
seed = 5
out = "{tmp_path / 'out_b'}"
[stages.scene]
type = "scene"
file = "{ideal}"
angles = [30.0, 60.0, 90.0]
trials_per_angle = 2
[stages.drive]
type = "drive"
inputs = ["scene"]
kind = "fa_i"
[stages.enc]
type = "izhikevich"
inputs = ["drive"]
[stages.bins]
type = "bin"
inputs = ["enc"]
window_ms = 100.0
hop_ms = 10.0
[stages.edbn]
type = "edbn"
inputs = ["bins"]
model_in = "{path}"
inference = "spiking"
[stages.mae]
type = "mae"
inputs = ["edbn"]
"""
    want = palpate.run(g, progress=False).estimates["edbn"].scores
    scores = lambda m: np.stack([e.scores for e in m.predict(images)])
    assert np.array_equal(want, scores(edbn))
    assert np.array_equal(want, scores(palpate.load_model(path, seed=5, stage_id="edbn")))
    assert not np.array_equal(want, scores(palpate.load_model(path, seed=5)))
    again = pickle.loads(pickle.dumps(edbn))
    assert again.stage_id == "edbn" and np.array_equal(want, scores(again))


@pytest.mark.parametrize(
    "call, kind, match",
    [
        (lambda g: palpate.check(g, set={"run.seed": 2**64}), ValueError, r"`run.seed`: seed must be an integer in \[0, 2\*\*64\)"),
        (lambda g: palpate.check(g, set={"stages.scene.trials_per_angle": 10**30}), ValueError, "`stages.scene.trials_per_angle`: 10+ is outside TOML's integers"),
        (lambda g: palpate.check(g, set={"stages.mae.per_class": None}), TypeError, "`stages.mae.per_class` is None: TOML has no null"),
        (lambda g: palpate.lowpass(np.ones((200, 16)), sample_rate_hz=100.0, cutoff_hz=float("nan")), ValueError, "key `cutoff_hz`: NaN"),
        (lambda g: palpate.simulate(GRAPHS / "scenes" / "ideal.toml", angles=[float("nan")]), ValueError, "key `angles`: NaN"),
        (lambda g: palpate.fit("knn", [], k=10**30), ValueError, "key `k`: 10+ is outside the 64-bit integers"),
        (lambda g: palpate.run(g, threads=-1), ValueError, "`threads` must be >= 0.*got -1"),
        (lambda g: palpate.run(g, threads=1.5), TypeError, "`threads` must be a whole number"),
        (lambda g: palpate.run_live(g, block=-1), ValueError, "`block` must be >= 1.*got -1"),
    ],
)
def test_values_out_of_range_raise_errors_naming_the_key(tmp_path, call, kind, match):
    """Were bare "NaN is not a finite number", OverflowError, "can't convert
    negative int to unsigned"."""
    with pytest.raises(kind, match=match):
        call(_filter_graph(tmp_path))


def test_nan_and_inf_through_set_are_diagnosed_as_in_a_dict_graph(tmp_path):
    """`set=` NaN or inf is a TOML float, checked by the stage as the same value
    in a dict graph (and `--set key=nan`) is: a diagnostic naming stage and key."""
    g = _filter_graph(tmp_path)
    for v in (float("nan"), float("inf")):
        via_set = [x for x in palpate.check(g, set={"stages.filter.cutoff_hz": v}) if x.severity == "error"]
        assert via_set and via_set[0].stage == "filter" and via_set[0].key == "cutoff_hz", via_set
        d = json.loads(json.dumps(g))
        d["stages"]["filter"]["cutoff_hz"] = v
        in_dict = [x for x in palpate.check(d) if x.severity == "error"]
        assert [x.message for x in via_set] == [x.message for x in in_dict]


def test_numpy_bools_are_bools_and_none_names_its_key(tmp_path):
    g = _filter_graph(tmp_path)
    g["stages"]["mae"]["per_class"] = np.bool_(True)
    assert [x for x in palpate.check(g) if x.severity == "error"] == []
    assert '"per_class" = true' in palpate._palpate_toml(g)  # was "cannot write a bool_ in a graph"
    g["stages"]["mae"]["per_class"] = None
    with pytest.raises(TypeError, match=r"`stages.mae.per_class` is None: TOML has no null; leave the key out"):
        palpate.check(g)
    g["stages"]["mae"]["per_class"] = False
    g["stages"]["scene"]["angles"] = [30.0, None]
    with pytest.raises(TypeError, match=r"`stages.scene.angles\[1\]` is None"):
        palpate.check(g)


def test_every_declared_exception_attribute_is_always_there(tmp_path):
    with pytest.raises(palpate.GraphError) as e:
        palpate.run(tmp_path / "no_such_graph.toml")
    err = e.value
    assert err.file == str(tmp_path / "no_such_graph.toml") and err.line is None and err.stage is None and err.key is None
    assert len(err.diagnostics) == 1 and "cannot read the graph file" in err.diagnostics[0]["message"]
    with pytest.raises(palpate.RunError) as e:
        palpate.lowpass(np.full((10, 16), np.nan), sample_rate_hz=100.0)
    assert e.value.file is None and e.value.stage == "stage" and e.value.key is None
    with pytest.raises(palpate.RunError) as e:
        palpate.fit("knn", [])
    assert e.value.file is None and e.value.trial is None
    # Built by hand, too: the class holds the defaults.
    assert palpate.GraphError("x").diagnostics == () and palpate.RunError("x").file is None
    assert palpate.ConfigError("x").key is None


def test_an_output_folder_that_is_a_file_is_refused_before_running(tmp_path):
    f = tmp_path / "not_a_dir"
    f.write_text("x")
    progress = []

    class Stop(Exception):
        pass

    g = _filter_graph(tmp_path)
    with pytest.raises(palpate.PalpateError, match="exists and is not a directory") as e:
        palpate.run(g, out=f, progress=False)
    assert not isinstance(e.value, palpate.RunError)  # refused, not failed at the sink
    with pytest.raises(palpate.PalpateError, match="exists and is not a directory"):
        palpate.run_live(g, out=f, on_update=progress.append)
    assert progress == [] and f.read_text() == "x"


def test_negative_durations_and_event_times_are_refused():
    with pytest.raises(ValueError, match="`duration_ms` must be a finite number of ms >= 0, got -5.0"):
        palpate.Spikes([], [], -5.0)
    with pytest.raises(ValueError, match="`duration_ms` must be >= 0"):
        palpate._palpate.apply("bin", {}, [[{"kind": "spikes", "taxel": np.zeros(0, np.uint32), "t_ms": np.zeros(0), "duration_ms": -5.0, "layout": palpate.grid()}]])
    ev = np.array([(0, 0, -5, True)], dtype=palpate.EVENT_DTYPE)
    with pytest.raises(ValueError, match="event 0 has time t = -5 us"):
        palpate.Spikes.from_events(ev, (3, 2, 1))
    assert palpate.bin(palpate.Spikes([], [], 0.0)).counts.sum() == 0  # an empty trial still bins


def test_core_warnings_are_python_warnings():
    """WSS's warnings came straight to stderr, out of reach of `warnings`."""
    import warnings

    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        est = palpate.wss(palpate.Images(np.zeros((5, 16)), 100.0, 10.0), stage_id="wss_no_speed")
    assert est.angle_deg is None or np.isfinite(est.angle_deg)
    msgs = [str(x.message) for x in w if issubclass(x.category, UserWarning)]
    assert any("declares no palpation speed" in m and "wss_no_speed" in m for m in msgs), msgs
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(UserWarning, match="all lie on one line"):
            palpate.wss(palpate.Images(np.zeros((5, 4)), 100.0, 10.0, palpate.grid(rows=1, cols=4)), stage_id="wss_line", speed_mm_s=2.0)


def test_a_graphs_load_warnings_are_python_warnings(tmp_path):
    g = _filter_graph(tmp_path)
    g["stages"]["bins"]["window_ms"] = 5.0  # shorter than its hop: a load warning
    g["stages"]["scene"]["trials_per_angle"] = 1
    assert any(x.severity == "warning" for x in palpate.check(g))
    with pytest.warns(UserWarning, match="bins"):
        palpate.run(g, progress=False)


def test_infinite_labels_are_no_label_and_all_non_finite_is_said():
    ims = [palpate.Images(np.random.default_rng(i).poisson(1.0, (20, 16)), 100.0, 10.0) for i in range(6)]
    with pytest.warns(UserWarning, match="2 of 6 training payloads have an infinite label"):
        palpate.fit("knn", ims, labels=[30.0, 30.0, 60.0, 60.0, np.inf, -np.inf])
    with pytest.warns(UserWarning):
        with pytest.raises(palpate.RunError, match="every one of the 6 labels given is non-finite") as e:
            palpate.fit("knn", ims, labels=[np.inf] * 3 + [np.nan] * 3)
    assert e.value.stage == "stage"
