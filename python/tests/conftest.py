"""Shared fixtures: the repository's paths and a small, fast scene."""

import os
import pathlib
import signal

import pytest

REPO = pathlib.Path(__file__).resolve().parents[2]
GRAPHS = REPO / "graphs"


@pytest.fixture(scope="session")
def repo() -> pathlib.Path:
    return REPO


@pytest.fixture
def sigint():
    """Python's own Ctrl-C handler for the test. A process started in the
    background by a non-interactive shell (`cmd &` in a script) inherits
    SIGINT ignored, and then Python installs no handler and
    `_thread.interrupt_main()` does nothing: the Ctrl-C tests would fail for
    how they were launched, not for what they test."""
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, old)


@pytest.fixture
def small_graph(tmp_path) -> str:
    """The quickstart's pipeline on the lab scene, cut to 3 angles x 3 trials."""
    text = (GRAPHS / "quickstart.toml").read_text()
    text = text.replace('file = "scenes/lab.toml"', f'file = "{GRAPHS / "scenes" / "lab.toml"}"\nangles = [30.0, 60.0, 90.0]\ntrials_per_angle = 3')
    text = text.replace("[run]\nseed = 1", f'[run]\nseed = 1\nout = "{tmp_path / "out"}"')
    return text


def cli_path():
    """The `palpate` binary to compare against: $PALPATE_CLI, else one the
    workspace built."""
    env = os.environ.get("PALPATE_CLI")
    if env:
        return pathlib.Path(env)
    for p in (REPO / "target" / "release" / "palpate", REPO / "target" / "debug" / "palpate"):
        if p.exists():
            return p
    return None
