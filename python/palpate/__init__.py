"""palpate for Python: run tactile-sensing graphs, use their stages on NumPy arrays,
and write stages in Python.

Everything calls the compiled Rust core (``palpate._palpate``): ``run`` loads and
runs a graph exactly as ``palpate run`` does (same reports, same bits); the
building blocks (``izhikevich``, ``lif``, ``lowpass``, ``drive``, ``bin``,
``wss``, ``fit`` ...) build the registered stage of that type from its keys and
call it, so they are the code the graphs run, not a second implementation.
A trained baseline's ``Model`` saves to (``save``) and loads from
(``load_model``) the model file a graph's ``save_model`` / ``model_in`` use,
and pickles.

Spike events use tonic's convention: a 1-D structured array of ``EVENT_DTYPE``
(``x``, ``y`` int16 -- the taxel's column and row; ``t`` int64 microseconds;
``p`` bool) with ``sensor_size = (cols, rows, 1)``, so ``tonic.transforms``
apply directly, and tonic-format events load back with ``Spikes.from_events``.

Example::

    import palpate
    res = palpate.run("graphs/quickstart.toml")
    print(res.metrics["wss.mae_deg"])
    wss = res.estimates["wss"]            # NumPy arrays, one entry per trial
    print(wss.estimate[:5], wss.label[:5])
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import os
import pathlib
import re
import tempfile
import types
import typing
import warnings
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np

from . import _palpate
from ._palpate import ConfigError, GraphError, PalpateError, RunError

__all__ = [
    "EVENT_DTYPE",
    "ConfigError",
    "Dataset",
    "Diagnostic",
    "Estimate",
    "EstimateTable",
    "GraphError",
    "Images",
    "LiveResult",
    "Model",
    "PalpateError",
    "Result",
    "SweepResult",
    "RunError",
    "Signals",
    "Spikes",
    "apply",
    "bin",
    "check",
    "derivative",
    "drive",
    "fit",
    "grid",
    "izhikevich",
    "lif",
    "load_model",
    "lowpass",
    "normalize",
    "read_signals",
    "run",
    "run_live",
    "simulate",
    "stage",
    "stage_types",
    "wss",
]

__version__ = _palpate.version()

#: tonic's event dtype: taxel column ``x`` and row ``y`` (int16), time ``t`` in
#: microseconds (int64), polarity ``p`` (bool; palpate's spikes are all ``True``).
EVENT_DTYPE = np.dtype([("x", "<i2"), ("y", "<i2"), ("t", "<i8"), ("p", "?")])


def grid(rows: int = 4, cols: int = 4, pitch_mm: float = 3.0, taxel_mm: float = 2.0) -> dict:
    """A grid layout (the paper's 4 x 4 array, 3 mm pitch, 2 mm taxels, by default)."""
    return {"kind": "grid", "rows": rows, "cols": cols, "pitch_mm": pitch_mm, "taxel_mm": taxel_mm}


def _n_taxels(layout: dict) -> int:
    if layout.get("kind") == "grid":
        return int(layout["rows"]) * int(layout["cols"])
    return len(layout["positions_mm"])


def _meta_of(raw: dict) -> Optional[dict]:
    return raw.get("meta")


def _real(what: str, values: Any) -> np.ndarray:
    """``values`` as a float64 array. Complex values are an error: NumPy's cast
    would drop their imaginary parts with only a warning."""
    a = np.asarray(values)
    if np.iscomplexobj(a):
        raise ValueError(f"{what} must be real numbers, got {a.dtype} values")
    try:
        return np.asarray(a, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{what} must be numbers: {e}") from None


def _seed(seed: Any) -> int:
    """A run seed: an integer in [0, 2**64), as ``[run] seed`` takes (PyO3's
    own conversion said only "can't convert negative int to unsigned")."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
        raise TypeError(f"seed must be an integer, got {type(seed).__name__}")
    if not 0 <= int(seed) < 2**64:
        raise ValueError(f"seed must be an integer in [0, 2**64), got {int(seed)}")
    return int(seed)


def _count(name: str, value: Any, least: int, most: int, note: str = "") -> int:
    """A whole-number argument checked by name (PyO3's own conversion said only
    "can't convert negative int to unsigned")."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"`{name}` must be a whole number{note}, got {type(value).__name__} {value!r}")
    if int(value) < least:
        raise ValueError(f"`{name}` must be >= {least}{note}, got {int(value)}")
    if int(value) > most:
        raise ValueError(f"`{name}` must be <= {most}{note}, got {int(value)}")
    return int(value)


def _taxel_indices(values: Any) -> np.ndarray:
    """Spike taxel indices as uint32, checked: a negative, fractional or
    too-large index is an error naming the spike, where NumPy's cast would wrap
    ``-1`` to 4294967295 and cut ``1.7`` to 1 without a word."""
    a = np.asarray(values)
    if a.ndim != 1:
        raise ValueError(f"spikes: `taxel` must be 1-D (one per spike), got shape {a.shape}")
    if a.size == 0:
        return np.zeros(0, dtype=np.uint32)
    if a.dtype.kind == "f":
        bad = ~np.isfinite(a) | (a != np.floor(a))
        if bad.any():
            i = int(np.argmax(bad))
            raise ValueError(f"spikes: taxel {float(a[i])} of spike {i} is not a whole number")
    elif a.dtype.kind not in "iu":
        raise ValueError(f"spikes: `taxel` must be integer indices, got {a.dtype} values")
    bad = (a < 0) | (a > np.iinfo(np.uint32).max)
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(f"spikes: taxel {a[i]} of spike {i} is not a taxel index (0 to 2**32 - 1)")
    return a.astype(np.uint32)


# ---------------------------------------------------------------- payloads


@dataclasses.dataclass
class Signals:
    """Analog taxel signals of one trial: ``data`` is float64 ``(samples, taxels)``."""

    data: np.ndarray
    sample_rate_hz: float
    layout: dict = dataclasses.field(default_factory=grid)
    unit: str = ""
    meta: Optional[dict] = None

    def __post_init__(self) -> None:
        self.data = np.ascontiguousarray(_real("signals: `data`", self.data))
        if self.data.ndim != 2:
            raise ValueError(f"signals: `data` must be 2-D (samples, taxels), got shape {self.data.shape}")

    def to_raw(self) -> dict:
        return {
            "kind": "signals",
            "data": self.data,
            "sample_rate_hz": float(self.sample_rate_hz),
            "unit": self.unit,
            "layout": self.layout,
            "meta": self.meta,
        }

    @classmethod
    def from_raw(cls, r: dict) -> "Signals":
        return cls(r["data"], r["sample_rate_hz"], r["layout"], r.get("unit", ""), _meta_of(r))


@dataclasses.dataclass
class Spikes:
    """The spike events of one trial: ``taxel`` (uint32) and exact times ``t_ms``
    (float64), sorted by time; ``events`` gives them in tonic's convention."""

    taxel: np.ndarray
    t_ms: np.ndarray
    duration_ms: float
    layout: dict = dataclasses.field(default_factory=grid)
    meta: Optional[dict] = None

    def __post_init__(self) -> None:
        self.taxel = _taxel_indices(self.taxel)
        self.t_ms = _real("spikes: `t_ms`", self.t_ms)
        if self.t_ms.ndim != 1:
            raise ValueError(f"spikes: `t_ms` must be 1-D (one per spike), got shape {self.t_ms.shape}")
        if len(self.taxel) != len(self.t_ms):
            raise ValueError(f"spikes: {len(self.taxel)} taxels but {len(self.t_ms)} times")
        try:
            d = float(self.duration_ms)
        except (TypeError, ValueError):
            raise TypeError(f"spikes: `duration_ms` must be a number, got {type(self.duration_ms).__name__}") from None
        if not (math.isfinite(d) and d >= 0.0):
            # A negative duration was binned into a 1-frame image.
            raise ValueError(f"spikes: `duration_ms` must be a finite number of ms >= 0, got {d}")

    @property
    def sensor_size(self) -> Tuple[int, int, int]:
        """tonic's ``(width, height, polarities)``: ``(cols, rows, 1)`` for a grid,
        ``(taxels, 1, 1)`` for an explicit layout."""
        if self.layout.get("kind") == "grid":
            return (int(self.layout["cols"]), int(self.layout["rows"]), 1)
        return (_n_taxels(self.layout), 1, 1)

    @property
    def events(self) -> np.ndarray:
        """The events as a structured array of ``EVENT_DTYPE`` (``t`` rounded to whole
        microseconds, tonic's unit)."""
        cols = self.sensor_size[0]
        ev = np.empty(len(self.taxel), dtype=EVENT_DTYPE)
        if self.layout.get("kind") == "grid":
            ev["x"] = self.taxel % cols
            ev["y"] = self.taxel // cols
        else:
            ev["x"] = self.taxel
            ev["y"] = 0
        ev["t"] = np.rint(self.t_ms * 1000.0).astype(np.int64)
        ev["p"] = True
        return ev

    @classmethod
    def from_events(
        cls,
        events: np.ndarray,
        sensor_size: Optional[Sequence[int]] = None,
        duration_ms: Optional[float] = None,
        layout: Optional[dict] = None,
        meta: Optional[dict] = None,
    ) -> "Spikes":
        """Spikes from tonic-format events (fields ``x``, ``t``, optionally ``y``
        and ``p``; ``t`` in microseconds). ``sensor_size`` ``(W, H, P)`` gives the
        grid (``cols = W``, ``rows = H``) unless ``layout`` is given; the duration
        defaults to just past the last event."""
        names = events.dtype.names or ()
        if "x" not in names or "t" not in names:
            raise ValueError(f"events need fields `x` and `t` (tonic's convention), got {names}")
        if layout is None:
            if sensor_size is None:
                raise ValueError("give `sensor_size` (W, H, P) or `layout`")
            layout = grid(rows=int(sensor_size[1]), cols=int(sensor_size[0]))
        x = events["x"].astype(np.int64)
        y = events["y"].astype(np.int64) if "y" in names else np.zeros_like(x)
        if layout.get("kind") == "grid":
            cols, rows = int(layout["cols"]), int(layout["rows"])
            if len(x) and (x.min() < 0 or y.min() < 0 or x.max() >= cols or y.max() >= rows):
                raise ValueError(f"events outside the {rows} x {cols} grid (x is the column, y the row)")
            taxel = y * cols + x
        else:
            taxel = x
        t_us = events["t"]
        if len(t_us) and t_us.min() < 0:
            i = int(np.argmin(t_us))
            raise ValueError(
                f"event {i} has time t = {t_us[i]} us: event times are microseconds from the trial's start (>= 0)"
            )
        t_ms = t_us.astype(np.float64) / 1000.0
        order = np.lexsort((taxel, t_ms))
        taxel, t_ms = taxel[order], t_ms[order]
        if duration_ms is None:
            duration_ms = float(t_ms[-1]) + 0.001 if len(t_ms) else 0.001
        return cls(taxel, t_ms, float(duration_ms), layout, meta)

    def to_raw(self) -> dict:
        return {
            "kind": "spikes",
            "taxel": self.taxel,
            "t_ms": self.t_ms,
            "duration_ms": float(self.duration_ms),
            "layout": self.layout,
            "meta": self.meta,
        }

    @classmethod
    def from_raw(cls, r: dict) -> "Spikes":
        return cls(r["taxel"], r["t_ms"], r["duration_ms"], r["layout"], _meta_of(r))


@dataclasses.dataclass
class Images:
    """Spike images: ``counts`` float64 ``(frames, taxels)``; frame ``k`` covers
    ``[k * hop_ms, k * hop_ms + window_ms)``. ``frames`` reshapes a grid's
    counts to ``(frames, rows, cols)``."""

    counts: np.ndarray
    window_ms: float
    hop_ms: float
    layout: dict = dataclasses.field(default_factory=grid)
    meta: Optional[dict] = None

    def __post_init__(self) -> None:
        c = _real("images: `counts`", self.counts)
        if c.ndim == 3:
            c = c.reshape(c.shape[0], -1)
        if c.ndim != 2:
            raise ValueError(
                f"images: `counts` must be 2-D (frames, taxels) or 3-D (frames, rows, cols), got shape {c.shape}"
            )
        self.counts = np.ascontiguousarray(c)

    @property
    def frames(self) -> np.ndarray:
        if self.layout.get("kind") == "grid":
            return self.counts.reshape(-1, int(self.layout["rows"]), int(self.layout["cols"]))
        return self.counts

    def to_raw(self) -> dict:
        return {
            "kind": "images",
            "counts": self.counts,
            "window_ms": float(self.window_ms),
            "hop_ms": float(self.hop_ms),
            "layout": self.layout,
            "meta": self.meta,
        }

    @classmethod
    def from_raw(cls, r: dict) -> "Images":
        return cls(r["counts"], r["window_ms"], r["hop_ms"], r["layout"], _meta_of(r))


@dataclasses.dataclass
class Estimate:
    """An orientation estimate: ``angle_deg`` (None = "no edge"), every class's score."""

    angle_deg: Optional[float]
    class_angles: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    scores: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    class_deg: Optional[float] = None
    best_frame: Optional[int] = None
    decision_time_ms: Optional[float] = None
    meta: Optional[dict] = None
    # The estimator flags the answer as unreliable (WSS: a rival class far from
    # the best scores nearly as well; see the `wss` stage's `uncertain_margin`).
    uncertain: bool = False

    def __post_init__(self) -> None:
        self.class_angles = _real("estimate: `class_angles`", self.class_angles)
        self.scores = _real("estimate: `scores`", self.scores)
        if self.class_deg is None and self.angle_deg is not None and len(self.class_angles) == 0:
            self.class_deg = self.angle_deg

    def to_raw(self) -> dict:
        return {
            "kind": "estimate",
            "angle_deg": None if self.angle_deg is None else float(self.angle_deg),
            "class_deg": None if self.class_deg is None else float(self.class_deg),
            "class_angles": self.class_angles,
            "scores": self.scores,
            "best_frame": self.best_frame,
            "decision_time_ms": self.decision_time_ms,
            "uncertain": bool(self.uncertain),
            "meta": self.meta,
        }

    @classmethod
    def from_raw(cls, r: dict) -> "Estimate":
        return cls(
            r["angle_deg"],
            r["class_angles"],
            r["scores"],
            r["class_deg"],
            r["best_frame"],
            r["decision_time_ms"],
            _meta_of(r),
            uncertain=bool(r.get("uncertain", False)),
        )


Payload = Union[Signals, Spikes, Images, Estimate]
_KINDS = {"signals": Signals, "spikes": Spikes, "images": Images, "estimate": Estimate}


def _from_raw(r: dict) -> Payload:
    return _KINDS[r["kind"]].from_raw(r)


def _to_raw(p: Any) -> dict:
    if isinstance(p, (Signals, Spikes, Images, Estimate)):
        return p.to_raw()
    if isinstance(p, dict) and "kind" in p:
        return p
    raise TypeError(f"expected a palpate payload (Signals, Spikes, Images, Estimate), got {type(p).__name__}")


# ---------------------------------------------------------------- graphs


#: Largest graph file read (bytes), as ``palpate_core::input::MAX_TEXT_FILE_BYTES``.
_MAX_TEXT_FILE_BYTES = 64 << 20


def _graph_error(file: str, message: str) -> GraphError:
    """A ``GraphError`` raised here (not by the loader), with every attribute the
    loader's carry: ``file``, ``line``, ``stage``, ``key`` and one diagnostic."""
    text = f"{file}: error: {message}"
    e = GraphError(f"{file}: {message}")
    e.file, e.line, e.stage, e.key = file, None, None, None
    e.diagnostics = [
        {"severity": "error", "file": file, "line": None, "stage": None, "key": None, "message": message, "text": text}
    ]
    return e


def _looks_like_path(graph: str) -> bool:
    """Whether a one-line string names a graph file rather than holding TOML text:
    it names an existing file, or ends in ``.toml``, or holds no ``=`` (which
    every TOML key-value line has). A path may hold ``=`` (``sweep/lr=0.1/``)."""
    if "\n" in graph:
        return False
    return os.path.isfile(graph) or graph.rstrip().endswith(".toml") or "=" not in graph


def _graph_text(graph: Any) -> dict:
    """(text, file, stem, base_dir, hint) of a graph given as a path, TOML text or dict."""
    if isinstance(graph, dict):
        text = _palpate_toml(graph)
        return {"text": text, "file": "<dict>", "stem": "graph", "base_dir": os.getcwd(), "hint": None}
    if isinstance(graph, pathlib.PurePath) or (isinstance(graph, str) and _looks_like_path(graph)):
        path = pathlib.Path(graph)
        try:
            # Capped as the CLI caps it (64 MiB): /dev/zero or an endless pipe
            # would otherwise be read until memory ran out.
            with open(path, "rb") as f:
                raw = f.read(_MAX_TEXT_FILE_BYTES + 1)
            if len(raw) > _MAX_TEXT_FILE_BYTES:
                raise _graph_error(
                    str(graph),
                    f"cannot read the graph file: it is larger than the cap of "
                    f"{_MAX_TEXT_FILE_BYTES} bytes (or never ends)",
                )
            text = raw.decode("utf-8")
        except (OSError, UnicodeDecodeError) as e:
            raise _graph_error(str(graph), f"cannot read the graph file: {e}") from None
        return {"text": text, "file": str(graph), "stem": path.stem, "base_dir": str(path.parent), "hint": None}
    if isinstance(graph, str):
        # One line holding `=` that names no file: TOML text, said if it does
        # not parse (a mistyped path read as TOML said only "not valid TOML").
        hint = None
        if "\n" not in graph:
            hint = f"the string was read as TOML text because no file `{graph}` exists"
        return {"text": graph, "file": "<string>", "stem": "graph", "base_dir": os.getcwd(), "hint": hint}
    raise TypeError(f"a graph is a path, a TOML string or a dict, got {type(graph).__name__}")


def _palpate_toml(d: dict) -> str:
    """A dict as TOML text (tables after plain keys, as TOML requires)."""

    def value(v: Any, key: str) -> str:
        if v is None:
            raise TypeError(f"`{key}` is None: TOML has no null; leave the key out")
        if isinstance(v, (bool, np.bool_)):
            return "true" if v else "false"
        if isinstance(v, (int, np.integer)):
            # TOML's integers stop at 2**63 - 1; a seed above it is read from
            # its digits as a string.
            return str(int(v)) if -(2**63) <= int(v) < 2**63 else json.dumps(str(int(v)))
        if isinstance(v, (float, np.floating)):
            return repr(float(v))
        if isinstance(v, (str, pathlib.PurePath)):
            return json.dumps(str(v))
        if isinstance(v, (list, tuple, np.ndarray)):
            return "[" + ", ".join(value(x, f"{key}[{i}]") for i, x in enumerate(v)) + "]"
        if isinstance(v, dict):
            return "{ " + ", ".join(f"{json.dumps(k)} = {value(x, f'{key}.{k}')}" for k, x in v.items()) + " }"
        raise TypeError(f"`{key}`: cannot write a {type(v).__name__} in a graph")

    lines: List[str] = []

    def table(prefix: List[str], t: dict) -> None:
        plain = {k: v for k, v in t.items() if not isinstance(v, dict) or (prefix and prefix[0] == "stages" and len(prefix) == 2)}
        sub = {k: v for k, v in t.items() if k not in plain}
        if prefix:
            lines.append("[" + ".".join(json.dumps(p) if not p.replace("_", "").replace("-", "").isalnum() else p for p in prefix) + "]")
        for k, v in plain.items():
            lines.append(f"{json.dumps(k)} = {value(v, '.'.join(prefix + [str(k)]))}")
        for k, v in sub.items():
            table(prefix + [k], v)

    table([], d)
    return "\n".join(lines) + "\n"


@dataclasses.dataclass
class Diagnostic:
    """One problem found while loading a graph (as ``palpate check`` prints it)."""

    severity: str
    file: str
    line: Optional[int]
    stage: Optional[str]
    key: Optional[str]
    message: str
    text: str

    def __str__(self) -> str:
        return self.text


def check(graph: Any, set: Optional[Dict[str, Any]] = None) -> List[Diagnostic]:
    """Every error and warning of a graph (path, TOML string or dict), as objects
    with ``file``, ``line``, ``stage``, ``key`` and ``message``; empty when clean."""
    return [Diagnostic(**d) for d in _palpate.check(_graph_text(graph), set)]


class EstimateTable:
    """One estimator's per-trial estimates as NumPy arrays (one entry per trial,
    in trial order): ``trial_id``, ``index``, ``group``, ``label`` (true angle,
    NaN if none), ``estimate`` (NaN = "no edge"), ``class_deg``, ``scores``
    ``(trials, classes)`` over ``class_angles``, ``decision_time_ms``,
    ``best_frame`` (-1 if none)."""

    def __init__(self, name: str, raws: List[dict]):
        self.name = name
        self.items = [Estimate.from_raw(r) for r in raws]
        metas = [r["meta"] for r in raws]
        nan = float("nan")
        self.trial_id = np.array([m["trial_id"] for m in metas], dtype=object)
        self.index = np.array([m["index"] for m in metas], dtype=np.int64)
        self.group = np.array([m["group"] for m in metas], dtype=np.int64)
        self.label = np.array([nan if m["angle_deg"] is None else m["angle_deg"] for m in metas])
        self.estimate = np.array([nan if e.angle_deg is None else e.angle_deg for e in self.items])
        self.class_deg = np.array([nan if e.class_deg is None else e.class_deg for e in self.items])
        self.decision_time_ms = np.array(
            [nan if e.decision_time_ms is None else e.decision_time_ms for e in self.items]
        )
        self.best_frame = np.array([-1 if e.best_frame is None else e.best_frame for e in self.items], dtype=np.int64)
        k = max((len(e.scores) for e in self.items), default=0)
        self.class_angles = next((e.class_angles for e in self.items if len(e.scores) == k), np.zeros(0))
        self.scores = np.full((len(self.items), k), nan)
        for i, e in enumerate(self.items):
            self.scores[i, : len(e.scores)] = e.scores

    def __len__(self) -> int:
        return len(self.items)

    def records(self) -> List[dict]:
        """One dict per trial (``pandas.DataFrame(table.records())``); scores as
        ``score_<angle>`` columns."""
        out = []
        for i in range(len(self)):
            r = {
                "trial_id": self.trial_id[i],
                "index": int(self.index[i]),
                "group": int(self.group[i]),
                "label_deg": float(self.label[i]),
                "estimate_deg": float(self.estimate[i]),
                "class_deg": float(self.class_deg[i]),
                "decision_time_ms": float(self.decision_time_ms[i]),
            }
            for a, s in zip(self.class_angles, self.scores[i]):
                r[f"score_{a:g}"] = float(s)
            out.append(r)
        return out

    def to_pandas(self):  # pragma: no cover - pandas is optional
        import pandas as pd

        return pd.DataFrame(self.records())

    def __repr__(self) -> str:
        return f"EstimateTable({self.name!r}, {len(self)} trials, {len(self.class_angles)} classes)"


class Result:
    """What ``run`` returns: ``metrics`` (every sink's, by name), ``reports`` (per
    sink: ``text``, ``files``, ``metrics``), ``estimates`` (per estimator, an
    ``EstimateTable``), ``timing`` (rows of the timing table as dicts) and
    ``timing_table`` (as the CLI prints it), ``record`` (run.json's content),
    ``out_dir``."""

    def __init__(self, raw: dict):
        self.file: str = raw["file"]
        self.out_dir = pathlib.Path(raw["out_dir"])
        self.wall_s: float = raw["wall_s"]
        self.record: dict = raw["record"]
        self.reports: Dict[str, dict] = raw["reports"]
        self.metrics: Dict[str, float] = {}
        for r in self.reports.values():
            self.metrics.update(r["metrics"])
        self.timing: List[dict] = self.record["timing"]
        self.timing_table: str = raw["timing_table"]
        self.estimates: Dict[str, EstimateTable] = {
            k: EstimateTable(k, v) for k, v in raw["estimates"].items()
        }

    def report_text(self) -> str:
        """Every sink's report as the CLI prints it."""
        return "".join(f"== {k}\n{r['text']}" for k, r in self.reports.items())

    def __repr__(self) -> str:
        return f"Result({self.file!r}, metrics={self.metrics})"


class LiveResult(Result):
    """What ``run_live`` returns: as ``Result`` (``metrics``, ``reports``,
    ``estimates``: each estimator's final answer per trial, ``record``), with
    ``live``: ``trials``, ``stream_s`` (stream time fed), ``wall_s``,
    ``blocks``, ``block_us`` (each block's time through the chain: ``mean``,
    ``median``, ``p95``, ``p99``, ``max``) and ``stages`` (per stage: its time
    per block and ``share_pct`` of the chain); ``timing_table`` is the CLI's
    summary line and per-stage table."""

    def __init__(self, raw: dict):
        super().__init__(raw)
        self.live: dict = self.record["live"]

    def __repr__(self) -> str:
        return f"LiveResult({self.file!r}, metrics={self.metrics})"


class SweepResult:
    """What ``run`` returns for a graph with a ``[sweep]``: ``text`` (the sweep
    report as the CLI prints it), ``rows`` (per point: ``label``, ``series``,
    ``x`` and ``metrics`` as ``(name, mean, sd, runs)``), ``runs`` (per point
    and repeat: ``point``, ``repeat``, ``label``, ``key``, ``value``, ``seed``,
    ``out_dir`` and ``metrics`` by name), ``out_dir`` (where sweep.csv,
    sweep.json, the curves and each point's folder are)."""

    def __init__(self, raw: dict):
        self.file: str = raw["file"]
        self.out_dir = pathlib.Path(raw["out_dir"])
        self.wall_s: float = raw["wall_s"]
        self.text: str = raw["text"]
        self.rows: List[dict] = raw["rows"]
        self.runs: List[dict] = raw["runs"]

    def summary(self, metric: str) -> List[Tuple[str, float, float, int]]:
        """``(point label, mean, sd, runs)`` of one metric at every point that has it."""
        out = []
        for r in self.rows:
            for name, mean, sd, n in r["metrics"]:
                if name == metric:
                    out.append((r["label"], mean, sd, n))
        return out

    def __repr__(self) -> str:
        return f"SweepResult({self.file!r}, points={len(self.rows)}, runs={len(self.runs)})"


def run(
    graph: Any,
    set: Optional[Dict[str, Any]] = None,
    threads: Optional[int] = None,
    out: Union[str, os.PathLike, None] = None,
    progress: bool = True,
    fresh: bool = False,
) -> Union[Result, SweepResult]:
    """Runs a graph (a path, a TOML string or a dict) as ``palpate run`` does, with
    the same report files in its output folder. ``set`` overrides keys
    (``{"stages.wss.weighting": "constant"}``), ``threads`` caps the worker
    threads (default: all cores; at most 4096), ``out`` replaces ``[run] out``. The GIL is
    released while it runs; progress goes to stderr. Ctrl-C stops it at the
    next trial or fold and raises ``KeyboardInterrupt``. Raises ``GraphError``
    (with ``diagnostics``) when the graph does not load, ``RunError`` when a
    stage fails.

    A graph with a ``[sweep]`` runs every point (through the CLI's code: each
    point's folder and completion marker, then the sweep report) and returns a
    ``SweepResult``; points already complete in ``out`` from an earlier run of
    the same graph are reused unless ``fresh``."""
    if threads is not None:
        # Above the cap of 4096, the core's own message says so.
        threads = _count("threads", threads, 0, 2**63 - 1, " (0 or None: one per core)")
    raw = _palpate.run(_graph_text(graph), set, threads, None if out is None else str(out), progress, fresh)
    if "runs" in raw:
        return SweepResult(raw)
    return Result(raw)


def run_live(
    graph: Any,
    set: Optional[Dict[str, Any]] = None,
    out: Union[str, os.PathLike, None] = None,
    block: int = 1,
    on_update: Optional[Callable[[dict], None]] = None,
) -> LiveResult:
    """Streams a graph (a path, a TOML string or a dict) live, as ``palpate run
    GRAPH --live`` does: every trial of its source, ``block`` samples at a
    time, through each stage's streaming form (a ``daq`` source: frame by
    frame as the board delivers them), then the sinks on the final answers;
    the same report files, plus ``live_timing.md`` / ``.csv``. Every stage
    must stream (``check`` names those that cannot; a ``PalpateError`` lists
    them). ``on_update`` gets every estimate as it changes: a dict with
    ``trial_id``, ``stage``, ``t_ms`` (stream time), ``last`` (the trial's
    final answer) and ``estimate`` (``kind``, ``angle_deg``, ...). An exception
    it raises, or Ctrl-C (checked at each update and every 50 ms between,
    so also with nothing in contact), stops the stream (how a
    session on a board that streams forever ends): the trial under way is
    dropped, the reports and ``run.json`` (``live.stopped``) cover the trials
    finished, and the exception is raised. The GIL is released while the
    stages run."""
    block = _count("block", block, 1, 2**63 - 1, " (samples per block)")
    raw = _palpate.run_live(_graph_text(graph), set, None if out is None else str(out), block, on_update)
    return LiveResult(raw)


def stage_types() -> List[dict]:
    """Every registered stage type: ``type``, ``doc`` and ``keys`` (name, type, default, doc)."""
    return list(_palpate.stage_types())


# ---------------------------------------------------------------- scenes


@dataclasses.dataclass
class Dataset:
    """A simulated scene's or a set of recordings' trials (``simulate``,
    ``read_signals``): ``signals`` float64 ``(trials, samples, taxels)`` (NaN past
    the end of a trial shorter than the longest),
    ``labels`` (true angle per trial, degrees; NaN if none), ``trial_ids``,
    ``groups``, ``crossing_ms`` ``(trials, 2)`` (NaN if unknown),
    ``speed_mm_s`` (each trial's commanded sliding speed, which WSS builds its
    templates for), ``sample_rate_hz``, ``layout``; ``trials`` holds each trial's ``Signals``
    (with its metadata) for the building blocks."""

    signals: np.ndarray
    labels: np.ndarray
    trial_ids: List[str]
    groups: np.ndarray
    crossing_ms: np.ndarray
    speed_mm_s: np.ndarray
    sample_rate_hz: float
    layout: dict
    unit: str
    trials: List[Signals]

    def __len__(self) -> int:
        return len(self.trials)


def simulate(scene: Union[str, os.PathLike, dict], seed: int = 1, stage_id: str = "scene", **keys: Any) -> Dataset:
    """Simulates a scene (the graph's ``scene`` stage, run seed ``seed``): ``scene``
    is a scene file's path or a dict of the stage's keys; ``keys`` override it
    (e.g. ``angles=[30, 60], trials_per_angle=2``). Each trial's seed derives
    from ``seed``, ``stage_id`` and the trial's id, as in a graph: the same seed
    and the graph's stage id (default ``scene``) give the same bits as that
    graph's scene stage."""
    if isinstance(scene, dict):
        cfg = dict(scene)
    else:
        cfg = {"file": str(pathlib.Path(scene).resolve())}
    cfg.update(keys)
    return _dataset(_palpate.simulate(cfg, _seed(seed), None, _stage_id(stage_id)))


def read_signals(
    path: Union[str, os.PathLike, Sequence[Union[str, os.PathLike]]],
    labels: Union[str, os.PathLike, None] = None,
    **keys: Any,
) -> Dataset:
    """Reads recordings as a graph's ``signal_file`` stage does, into a ``Dataset``:
    ``path`` is a file, a glob pattern (``"recordings/*.csv"``) or a list of them,
    relative to the current folder; ``labels`` a label file; ``keys`` any other key
    of the stage (``sample_rate_hz``, ``layout``, ``unit``, ``columns``,
    ``segment="contact"`` with ``contact_v``/``release_v`` to cut one log of several
    palpations into trials, ...: ``palpate stages signal_file`` lists them). CSV,
    NPY, NPZ, MATLAB ``.mat`` (v5 and v7.3) and raw DAQ files; the same checks and
    errors as the stage. ``crossing_ms`` is NaN (a recording does not know when
    the edge crossed)."""
    paths = [path] if isinstance(path, (str, os.PathLike)) else list(path)
    cfg: Dict[str, Any] = {"paths": [str(p) for p in paths]}
    if labels is not None:
        cfg["labels"] = str(labels)
    cfg.update(keys)
    return _dataset(_palpate.read_source("signal_file", cfg, 1, os.getcwd(), "signals"))


def _dataset(raws: List[dict]) -> Dataset:
    """A ``Dataset`` of a source's raw trials (signals with their metadata)."""
    trials = [Signals.from_raw(r) for r in raws]
    lens = {t.data.shape[0] for t in trials}
    if len(lens) > 1:
        # Trials of different lengths: pad the stacked array with NaN at the end.
        m = max(lens)
        stack = np.full((len(trials), m, trials[0].data.shape[1]), np.nan)
        for i, t in enumerate(trials):
            stack[i, : t.data.shape[0]] = t.data
    else:
        stack = np.stack([t.data for t in trials]) if trials else np.zeros((0, 0, 0))
    nan = float("nan")
    metas = [r["meta"] for r in raws]
    return Dataset(
        signals=stack,
        labels=np.array([nan if m["angle_deg"] is None else m["angle_deg"] for m in metas]),
        trial_ids=[m["trial_id"] for m in metas],
        groups=np.array([m["group"] for m in metas], dtype=np.int64),
        crossing_ms=np.array([m["crossing_ms"] if m["crossing_ms"] else (nan, nan) for m in metas], dtype=float).reshape(-1, 2),
        speed_mm_s=np.array([nan if m.get("speed_mm_s") is None else m["speed_mm_s"] for m in metas], dtype=float),
        sample_rate_hz=trials[0].sample_rate_hz if trials else float("nan"),
        layout=trials[0].layout if trials else grid(),
        unit=trials[0].unit if trials else "",
        trials=trials,
    )


# ---------------------------------------------------------------- building blocks


def _as_list(x: Any) -> Tuple[List[Any], bool]:
    if isinstance(x, (list, tuple)):
        return list(x), True
    if isinstance(x, Dataset):
        return list(x.trials), True
    return [x], False


def _stage_id(stage_id: Any) -> str:
    if not isinstance(stage_id, str) or not stage_id:
        raise TypeError(f"`stage_id` must be a non-empty string (a graph's stage id), got {stage_id!r}")
    return stage_id


def apply(type: str, *inputs: Any, seed: int = 1, stage_id: str = "stage", **config: Any) -> Any:
    """Applies the registered stage ``type`` with keys ``config`` to payloads (one
    per input of the stage; each a payload or a list of payloads, one per
    trial). Works for every map stage (filters, drives, encoders, spike stages,
    binning) and model-based estimator (WSS); returns a payload, or a list when
    given lists. The stage's seed derives from ``seed``, its id ``stage_id``
    (default ``stage``) and each trial's id, as in a graph: give a graph's run
    seed and stage id to get that stage's bits (``apply("jitter", spikes, seed=3,
    stage_id="jit", tau_ms=5.0)`` is the graph's stage ``jit`` at seed 3). A stage
    registered with ``@palpate.stage`` is applied by its name, its keys as
    ``config``."""
    if not inputs:
        raise TypeError("apply needs at least one input payload")
    lists = [_as_list(i) for i in inputs]
    n = len(lists[0][0])
    if any(len(l) != n for l, _ in lists):
        raise ValueError("every input must hold the same number of trials")
    trials = [[_to_raw(l[i]) for l, _ in lists] for i in range(n)]
    out = [_from_raw(r) for r in _palpate.apply(type, config, trials, _seed(seed), _stage_id(stage_id))]
    return out if lists[0][1] else out[0]


def _signals(x: Any, sample_rate_hz: Optional[float]) -> Any:
    if isinstance(x, np.ndarray):
        if sample_rate_hz is None:
            raise TypeError("an array of signals needs `sample_rate_hz`")
        if x.ndim not in (2, 3):
            raise ValueError(
                f"an array of signals must be (samples, taxels) or (trials, samples, taxels), got shape {x.shape}"
            )
        if x.ndim == 3:
            return [Signals(a, sample_rate_hz, grid(), "") if x.shape[2] == 16 else Signals(a, sample_rate_hz, _line(x.shape[2])) for a in x]
        return Signals(x, sample_rate_hz, grid() if x.shape[1] == 16 else _line(x.shape[1]))
    return x


def _line(n: int) -> dict:
    # A plain array says nothing of where its taxels sit: a count other than
    # the paper's 16 is taken as one row, and said, since spatial stages
    # (``wss``, ``bin`` images) read the layout.
    warnings.warn(
        f"an array of {n} taxels (not 16) is taken as a 1 x {n} row of taxels; "
        "for another layout pass palpate.Signals(data, sample_rate_hz, palpate.grid(rows=..., cols=...))",
        stacklevel=3,
    )
    return grid(rows=1, cols=n)


def lowpass(signals: Any, sample_rate_hz: Optional[float] = None, **config: Any) -> Any:
    """The ``lowpass`` stage (Butterworth, zero phase) on signals."""
    return apply("lowpass", _signals(signals, sample_rate_hz), **config)


def normalize(signals: Any, sample_rate_hz: Optional[float] = None, **config: Any) -> Any:
    """The ``normalize`` stage on signals."""
    return apply("normalize", _signals(signals, sample_rate_hz), **config)


def derivative(signals: Any, sample_rate_hz: Optional[float] = None, **config: Any) -> Any:
    """The ``derivative`` stage on signals."""
    return apply("derivative", _signals(signals, sample_rate_hz), **config)


def drive(signals: Any, sample_rate_hz: Optional[float] = None, **config: Any) -> Any:
    """The ``drive`` stage: signals to neuron input currents (e.g. ``kind="fa_i"``)."""
    return apply("drive", _signals(signals, sample_rate_hz), **config)


def izhikevich(currents: Any, sample_rate_hz: Optional[float] = None, **config: Any) -> Any:
    """The ``izhikevich`` encoder: input currents (Signals, or an array
    ``(samples, taxels)`` / ``(trials, samples, taxels)`` with ``sample_rate_hz``)
    to Spikes."""
    return apply("izhikevich", _signals(currents, sample_rate_hz), **config)


def lif(currents: Any, sample_rate_hz: Optional[float] = None, **config: Any) -> Any:
    """The ``lif`` encoder: input currents to Spikes."""
    return apply("lif", _signals(currents, sample_rate_hz), **config)


def bin(spikes: Any, window_ms: float = 100.0, hop_ms: float = 10.0, **config: Any) -> Any:
    """The ``bin`` stage: Spikes (or tonic events with ``sensor_size`` and
    ``duration_ms`` in ``config``) to Images."""
    if isinstance(spikes, np.ndarray) and spikes.dtype.names:
        spikes = Spikes.from_events(
            spikes, config.pop("sensor_size", None), config.pop("duration_ms", None), config.pop("layout", None)
        )
    return apply("bin", spikes, window_ms=window_ms, hop_ms=hop_ms, **config)


def wss(images: Any, **config: Any) -> Any:
    """The ``wss`` estimator (weighted spatiotemporal similarity) on Images:
    an Estimate per trial."""
    return apply("wss", images, **config)


class Model:
    """A fitted estimator; ``predict`` takes a payload or a list of them.

    A trained baseline's model (``ann``, ``edbn``, ``svm``, ``random_forest``,
    ``knn``, ``logistic``) can be saved (``save``), loaded (``load_model``) and
    pickled; the file is the one a graph's ``save_model = true`` writes, so a
    model fitted in Python runs in a graph with ``model_in = "<file>"`` (and
    live), and a graph's saved fold loads here. A loaded or unpickled model
    gives the same estimates, bit for bit, as the one saved, for the same
    ``seed``."""

    def __init__(self, inner: Any, type: str):
        self._inner = inner
        self.type = type

    @property
    def seed(self) -> int:
        """The run seed it predicts with (each trial's seed derives from it, ``stage_id`` and the trial id)."""
        return int(self._inner.seed)

    @property
    def stage_id(self) -> str:
        """The stage id its per-trial seeds derive from (a graph's stage id; default ``stage``)."""
        return str(self._inner.stage_id)

    def _bytes(self, what: str) -> bytes:
        data = self._inner.saved_bytes()
        if data is None:
            raise TypeError(
                f"cannot {what} a `{self.type}` model: only trained baselines' models are files "
                "(WSS is rebuilt from its keys; a Python stage's model is its own object)"
            )
        return data

    def save(self, path: Union[str, os.PathLike]) -> pathlib.Path:
        """Writes the model file (JSON, written whole or not at all) and returns its path."""
        data = self._bytes("save")
        p = pathlib.Path(path)
        tmp = p.with_name(p.name + ".partial")
        tmp.write_bytes(data)
        os.replace(tmp, p)
        return p

    def __reduce__(self) -> Any:
        return (_model_from_bytes, (self.type, self._bytes("pickle"), self.seed, self.stage_id))

    def predict(self, x: Any) -> Any:
        items, many = _as_list(x)
        out = [Estimate.from_raw(r) for r in self._inner.predict([_to_raw(i) for i in items])]
        return out if many else out[0]

    def predict_angles(self, x: Any) -> np.ndarray:
        """The estimated angles (NaN = "no edge") of a list of payloads."""
        items, _ = _as_list(x)
        return np.array([np.nan if e.angle_deg is None else e.angle_deg for e in self.predict(items)])


def load_model(path: Union[str, os.PathLike], seed: int = 1, stage_id: str = "stage") -> Model:
    """Loads a model file written by ``Model.save`` or by a graph's ``save_model =
    true`` (``<out>/<stage id>.fold<f>.model.json``), checked as a graph's
    ``model_in`` checks it; ``seed`` is the run seed it predicts with and
    ``stage_id`` the stage id its per-trial seeds derive from: a graph's run seed
    and the id of its ``model_in`` stage give that graph's bits."""
    p = pathlib.Path(path).resolve()
    try:
        with open(p, "rb") as f:
            head = f.read(4096)
    except OSError as e:
        raise ValueError(f"{p}: cannot read the model file: {e}") from None
    # The file's second field (serde keeps the struct's order): reading it from
    # the head spares parsing a k-NN model's tens of MB twice.
    m = re.search(rb'"stage_type"\s*:\s*"([A-Za-z0-9_-]+)"', head)
    if m is None:
        raise ValueError(f"{p}: not a palpate model file (no `stage_type` near its start)")
    type = m.group(1).decode()
    return Model(_palpate.fit(type, {"model_in": str(p)}, [], _seed(seed), _stage_id(stage_id)), type)


def _model_from_bytes(type: str, data: bytes, seed: int, stage_id: str = "stage") -> Model:
    """A model from its file's bytes (unpickling)."""
    with tempfile.TemporaryDirectory(prefix="palpate-model-") as d:
        p = pathlib.Path(d) / f"{type}.model.json"
        p.write_bytes(data)
        return load_model(p, seed, stage_id)


def fit(
    type: str,
    train: Sequence[Any],
    labels: Optional[Sequence[float]] = None,
    seed: int = 1,
    stage_id: str = "stage",
    **config: Any,
) -> Model:
    """Fits the registered estimator ``type`` (``ann``, ``edbn``, ``knn``, ``svm``,
    ``wss``, or a ``@palpate.stage`` estimator by its name ...) with keys
    ``config`` on training payloads; ``labels`` are their true angles (default:
    each payload's ``meta``), one per payload. A NaN or infinite label means "no
    label", as in ``Dataset.labels``: that payload is skipped, as a graph skips
    training trials without an angle, with a warning saying how many. The fit's
    and the model's per-trial seeds derive from ``seed`` and ``stage_id`` (a
    graph's run seed and stage id give that stage's bits). Returns a ``Model``."""
    if config.get("save_model"):
        # A graph writes each fold's model beside its reports; here there is
        # no run folder, and the file went to the system's temp folder.
        raise ValueError("fit: `save_model` is for graphs; in Python, call `model.save(path)` on the fitted model")
    train = list(train)
    if labels is not None:
        labels = list(labels)
        if len(labels) != len(train):
            # Unchecked, a short list failed inside NumPy indexing and a long
            # one was cut without a word.
            raise ValueError(
                f"fit: `labels` has {len(labels)} entries but `train` has {len(train)} payloads "
                "(one label per training payload)"
            )
        try:
            labels = [float(v) for v in labels]
        except (TypeError, ValueError) as e:
            raise ValueError(f"fit: `labels` must be angles in degrees: {e}") from None
        nan = sum(1 for v in labels if math.isnan(v))
        inf = sum(1 for v in labels if math.isinf(v))
        if nan or inf:
            # Skipped silently, a NaN among the labels (a dropped row in a
            # table) shrank the training set without a word; an infinite
            # one is no angle either (the trial's metadata drops it).
            said = []
            if nan:
                said.append(f"{nan} of {len(labels)} training payloads have a NaN label (no label)")
            if inf:
                said.append(f"{inf} of {len(labels)} training payloads have an infinite label (no label)")
            warnings.warn(f"fit: {'; '.join(said)} and are skipped", stacklevel=2)
    raws = []
    for i, p in enumerate(train):
        r = dict(_to_raw(p))
        meta = dict(r.get("meta") or {"trial_id": f"train{i}", "group": 0})
        if labels is not None:
            meta["angle_deg"] = labels[i]
        r["meta"] = meta
        raws.append(r)
    try:
        inner = _palpate.fit(type, config, raws, _seed(seed), _stage_id(stage_id))
    except RunError as e:
        if labels and not any(math.isfinite(v) for v in labels):
            # The estimator said only that it got no class ("got 0 ()").
            err = RunError(
                f"{e}; every one of the {len(labels)} labels given is non-finite (NaN or inf: no label), "
                "so no payload was left to fit on"
            )
            for k in ("file", "stage", "trial", "key"):
                setattr(err, k, getattr(e, k, None))
            raise err from None
        raise
    return Model(inner, type)


# ---------------------------------------------------------------- Python stages


class _KeyError(ValueError):
    """A Python stage's config key is wrong (``key`` names it)."""

    def __init__(self, key: str, message: str):
        super().__init__(message)
        self.key = key


def _stage_keys(cls: type) -> Dict[str, Any]:
    """A stage class's keys: its annotated class attributes (required when they
    have no default) and plain class attributes."""
    missing = object()
    keys: Dict[str, Any] = {}
    for klass in reversed(cls.__mro__[:-1]):
        for name in getattr(klass, "__annotations__", {}):
            if not name.startswith("_") and name != "trained":
                keys[name] = klass.__dict__.get(name, missing)
        for name, v in vars(klass).items():
            if name.startswith("_") or name == "trained" or callable(v) or isinstance(v, (staticmethod, classmethod, property)):
                continue
            keys[name] = v
    return {k: (None if v is missing else v, v is missing) for k, v in keys.items()}


def _key_types(cls: type) -> Dict[str, Any]:
    """The annotations of a stage class's keys, resolved (``from __future__
    import annotations`` makes them strings); an annotation that does not
    resolve is not checked."""
    try:
        return typing.get_type_hints(cls)
    except Exception:  # a forward reference the class's module cannot resolve
        hints: Dict[str, Any] = {}
        for klass in reversed(cls.__mro__[:-1]):
            hints.update(getattr(klass, "__annotations__", {}))
        return hints


_SIMPLE = {float: "a number", int: "a whole number", str: "a string", bool: "true or false", list: "a list", dict: "a table"}


def _check_key(stage_name: str, key: str, value: Any, hint: Any) -> Any:
    """``value`` of key ``key`` checked against its annotation ``hint`` when
    that is a plain ``float``, ``int``, ``str``, ``bool``, ``list`` or ``dict``
    (or ``Optional`` / ``List[...]`` / ``Dict[...]`` of one): a TOML string
    given for a number is an error naming the key, as for a built-in stage,
    where unchecked it reached ``process`` and failed there, or not at all.
    An integer for a ``float`` key becomes a float (TOML's ``level = 1``).
    Any other annotation is the stage's to check (in ``validate``)."""
    origin = typing.get_origin(hint)
    args = typing.get_args(hint)
    if origin is Union or origin is getattr(types, "UnionType", Union):  # Optional[X], X | None
        if value is None and type(None) in args:
            return value
        inner = [a for a in args if a is not type(None)]
        if len(inner) == 1:
            return _check_key(stage_name, key, value, inner[0])
        return value
    base = {list: list, dict: dict}.get(origin, hint)  # List[X] -> list
    if base not in _SIMPLE:
        return value
    if base is float and isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_)):
        return float(value)
    if base is int and isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_)):
        return int(value)
    if base in (str, bool, list, dict) and isinstance(value, base):
        return value
    raise _KeyError(
        key,
        f"key `{key}` of Python stage `{stage_name}` must be {_SIMPLE[base]} ({base.__name__}), "
        f"got {type(value).__name__} {value!r}",
    )


class _MapAdapter:
    def __init__(self, obj: Any):
        self.obj = obj

    def process(self, raws: List[dict], ctx: dict) -> dict:
        out = self.obj.process(*[_from_raw(r) for r in raws], ctx=ctx)
        return _to_raw(out)


class _EstimatorAdapter:
    def __init__(self, obj: Any):
        self.obj = obj
        self.trained = bool(getattr(obj, "trained", True))

    def fit(self, raws: List[dict], ctx: dict) -> "_ModelAdapter":
        model = copy.deepcopy(self.obj)  # one model per fold; folds may interleave
        items = [_from_raw(r) for r in raws]
        labels = np.array([np.nan if r["meta"]["angle_deg"] is None else r["meta"]["angle_deg"] for r in raws])
        if hasattr(model, "fit"):
            model.fit(items, labels, ctx=ctx)
        return _ModelAdapter(model)


class _ModelAdapter:
    def __init__(self, model: Any):
        self.model = model

    def predict(self, raw: dict, ctx: dict) -> dict:
        out = self.model.predict(_from_raw(raw), ctx=ctx)
        if isinstance(out, Estimate):
            return out.to_raw()
        if out is None:
            return Estimate(None).to_raw()
        return Estimate(float(out)).to_raw()


def stage(
    name: str,
    inputs: Union[str, Sequence[str]] = "signals",
    output: str = "spikes",
    max_inputs: Optional[int] = 1,
) -> Callable[[type], type]:
    """Registers a Python class as a stage usable in graphs run from Python::

        @palpate.stage("threshold", inputs="signals", output="spikes")
        class Threshold:
            level: float = 0.5                 # a config key with its default
            def process(self, signals, ctx):   # one trial -> a payload
                ...

    and in the graph::

        [stages.enc]
        type = "threshold"                     # the registered name is a stage type
        inputs = ["drive"]
        level = 0.3

    (the long form ``type = "python"``, ``stage = "threshold"``, ``config = {
    level = 0.3 }`` is the same stage). A built-in type's name is refused.

    A map (any ``output`` but ``estimates``) defines ``process(*payloads, ctx)``.
    An estimator (``output="estimates"``) defines ``fit(train, labels, ctx)``
    (``train`` a list of payloads, ``labels`` their true angles) and
    ``predict(payload, ctx)`` returning an ``Estimate``, an angle or None ("no
    edge"); ``trained = False`` makes it model-based (fit gets no trial). Keys
    are the class's annotated or plain attributes; an unknown or missing key, or
    a value that does not fit a plain annotation (see ``_check_key``), is an
    error naming it, and a class without the method its role needs is refused
    here. ``ctx`` holds ``stage_id``, ``trial_id`` and ``seed``
    (derived as for built-in stages, for reproducible randomness)."""
    kinds = [inputs] if isinstance(inputs, str) else list(inputs)
    role = "estimator" if output == "estimates" else "map"

    if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z][A-Za-z0-9_-]*", name):
        # A graph names the type in `type = "..."`; an empty or spaced name
        # registered fine and could never be used.
        raise ValueError(f"a stage name starts with a letter and holds letters, digits, `_` or `-`; got {name!r}")

    def deco(cls: type) -> type:
        keys = _stage_keys(cls)
        hints = _key_types(cls)
        method = "predict" if role == "estimator" else "process"
        if not callable(getattr(cls, method, None)):
            # Found only when the first trial reached it, as an AttributeError.
            raise TypeError(
                f"Python stage `{name}` ({role}, output {output}) needs a `{method}` method: "
                + ("`predict(self, payload, ctx)`" if role == "estimator" else "`process(self, *payloads, ctx)`")
            )

        def factory(config: dict) -> Any:
            for k in config:
                if k not in keys:
                    known = ", ".join(f"`{x}`" for x in keys) or "none"
                    raise _KeyError(k, f"unknown key `{k}` for Python stage `{name}`; its keys are {known}")
            obj = cls()
            for k, (default, required) in keys.items():
                if k in config:
                    setattr(obj, k, _check_key(name, k, config[k], hints.get(k)))
                elif required:
                    raise _KeyError(k, f"missing key `{k}` of Python stage `{name}`")
                else:
                    setattr(obj, k, copy.deepcopy(default))
            if hasattr(obj, "validate"):
                obj.validate()
            return _EstimatorAdapter(obj) if role == "estimator" else _MapAdapter(obj)

        _palpate.register_stage(name, role, kinds, output, factory, 1, max_inputs)
        cls.palpate_stage_name = name
        return cls

    return deco
