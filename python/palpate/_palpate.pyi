"""Type stubs of palpate's compiled module (``palpate._palpate``).

Payloads cross this boundary as "raw" dicts (``kind`` = ``signals``,
``spikes``, ``images`` or ``estimate``, NumPy arrays for the data, ``meta``
for the trial); ``palpate`` wraps them in its dataclasses.
"""

from typing import Any, Callable, Dict, List, Optional, TypedDict

class PalpateError(Exception):
    """Base class of palpate's errors."""

class GraphError(PalpateError):
    """A graph did not load (or its file could not be read). Every attribute is
    always there: None where there is none, ``diagnostics`` empty only on an
    instance built by hand."""

    file: Optional[str]
    line: Optional[int]
    stage: Optional[str]
    key: Optional[str]
    diagnostics: List["DiagnosticDict"]

class ConfigError(PalpateError):
    """A stage's config is wrong (attributes always there; None if unknown)."""

    stage: Optional[str]
    key: Optional[str]

class RunError(PalpateError):
    """A stage failed while running (attributes always there; ``file`` is None
    for a building block, which runs no graph file)."""

    file: Optional[str]
    stage: Optional[str]
    trial: Optional[str]
    key: Optional[str]

class DiagnosticDict(TypedDict):
    severity: str
    file: str
    line: Optional[int]
    stage: Optional[str]
    key: Optional[str]
    message: str
    text: str

class GraphText(TypedDict):
    text: str
    file: str
    stem: str
    base_dir: Optional[str]
    # Appended to a TOML syntax error: why the text was read as TOML (a
    # one-line string that named no file), or None.
    hint: Optional[str]

RawPayload = Dict[str, Any]

def version() -> str: ...
def check(graph: GraphText, set: Optional[Dict[str, Any]] = None) -> List[DiagnosticDict]: ...
def run(
    graph: GraphText,
    set: Optional[Dict[str, Any]] = None,
    threads: Optional[int] = None,
    out: Optional[str] = None,
    progress: bool = True,
    fresh: bool = False,
) -> Dict[str, Any]: ...
def run_live(
    graph: GraphText,
    set: Optional[Dict[str, Any]] = None,
    out: Optional[str] = None,
    block: int = 1,
    on_update: Optional[Callable[[Dict[str, Any]], None]] = None,
) -> Dict[str, Any]: ...
def stage_types() -> List[Dict[str, Any]]: ...
def apply(
    type_name: str,
    config: Dict[str, Any],
    trials: List[List[RawPayload]],
    seed: int = 1,
    stage_id: str = "stage",
    base_dir: Optional[str] = None,
) -> List[RawPayload]: ...
def fit(
    type_name: str,
    config: Dict[str, Any],
    train: List[RawPayload],
    seed: int = 1,
    stage_id: str = "stage",
) -> Model: ...
def simulate(
    config: Dict[str, Any], seed: int = 1, base_dir: Optional[str] = None, stage_id: str = "scene"
) -> List[RawPayload]: ...
def read_source(
    type_name: str,
    config: Dict[str, Any],
    seed: int = 1,
    base_dir: Optional[str] = None,
    stage_id: str = "source",
) -> List[RawPayload]: ...
def register_stage(
    name: str,
    role: str,
    inputs: List[str],
    output: str,
    factory: Callable[[Dict[str, Any]], Any],
    min_inputs: int = 1,
    max_inputs: Optional[int] = 1,
) -> None: ...
def unregister_stage(name: str) -> bool: ...

class Model:
    def predict(self, trials: List[RawPayload]) -> List[RawPayload]: ...
    def saved_bytes(self) -> Optional[bytes]: ...
    @property
    def seed(self) -> int: ...
    @property
    def stage_id(self) -> str: ...
