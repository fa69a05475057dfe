"""What the API process and the workers say to each other (pickled over pipes).

Tasks go to a worker through its own queue, in order; outcomes come back through the
worker's own result pipe. Frames are identified by (session id, seq) end to end.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

from vloc.workers.core.estimate import Estimate
from vloc.workers.core.image import Header
from vloc.workers.core.metadata import FrameMetadata

DEFAULT_FACTORY = "vloc.workers.core.localisers:make_localiser"


@dataclass(frozen=True, slots=True)
class SessionSpec:
    """Everything a worker needs to (re)create a session's localiser.

    Attributes
    ----------
    session_id : str
    map_id, revision : str, int
        The packed map's identity; workers cache maps under this key.
    map_folder : str
        The :class:`~workers.core.mapdata.MapData` folder ("" for a localiser without map).
    mode : str
        Localiser mode, as for :func:`workers.core.localisers.make_localiser`.
    params : dict
        Normalised parameters.
    seed : int
        The session's seed: the same frames in the same order give the same estimates.
    factory : str
        ``"module:function"`` with the signature of ``make_localiser``.
    """

    session_id: str
    map_id: str
    revision: int
    map_folder: str
    mode: str
    params: dict = field(default_factory=dict)
    seed: int = 0
    factory: str = DEFAULT_FACTORY


# -- API process -> worker ------------------------------------------------------------------

@dataclass(frozen=True, slots=True)
class OpenSession:
    spec: SessionSpec
    state: bytes | None = None
    call_id: int | None = None


@dataclass(frozen=True, slots=True)
class FrameTask:
    session_id: str
    seq: int
    data: bytes
    captured_at: float | None = None
    checkpoint: bool = True
    metadata: FrameMetadata | None = None
    """The frame's sensor reports, as the API process validated them (pickled as they are:
    not validated again)."""
    header: Header | None = None
    """What the image header the API process checked says (size, EXIF orientation): not
    read again."""


@dataclass(frozen=True, slots=True)
class ControlTask:
    """``reset``, ``set_initial_pose`` (x, y or lat, lon; sigma), ``stats`` or ``move``
    (``spec``: the session's :class:`SessionSpec` on another revision of its map) on a
    session."""

    call_id: int
    session_id: str
    op: str
    kwargs: dict = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class CallTask:
    """Run ``fn`` (a module-level function, pickled by reference, or ``"module:function"``)
    with the arguments; build jobs use this."""

    call_id: int
    fn: Callable | str
    args: tuple = ()
    kwargs: dict = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class CloseSession:
    session_id: str


@dataclass(frozen=True, slots=True)
class Stop:
    pass


# -- worker -> API process ------------------------------------------------------------------

@dataclass(frozen=True, slots=True)
class Ready:
    pid: int


@dataclass(frozen=True, slots=True)
class FrameDone:
    """A frame's estimate.

    Attributes
    ----------
    estimate : Estimate
        The localiser's (:class:`workers.core.estimate.Estimate`).
    state : bytes or None
        The localiser's state after this frame (a checkpoint), when one was asked for.
    decode_ms : float
        Decoding and resizing time in the worker; the step's own time is in the estimate.
    """

    session_id: str
    seq: int
    estimate: Estimate
    state: bytes | None
    decode_ms: float
    prev_seq: int | None = None
    """The seq of the outcome its worker reported for the session just before this one (None
    for the first since the session opened there): outcomes that reach a viewer by different
    paths can be put back in order with it."""
    revision: int | None = None
    """The map revision the estimate was made on (a session following its map moves to a
    new revision between two frames)."""


@dataclass(frozen=True, slots=True)
class FrameFailed:
    """A frame that gave no estimate.

    ``kind`` is ``bad_image`` (the bytes did not decode), ``error`` (the localiser raised),
    ``not_open`` (the session is not open on the worker) or ``worker_died``. ``prev_seq`` is
    as for :class:`FrameDone` where a worker reported it, else None.
    """

    session_id: str
    seq: int
    kind: str
    reason: str
    prev_seq: int | None = None


@dataclass(frozen=True, slots=True)
class Checkpoint:
    """A session's state after a control (reset, initial pose), in order with its frames;
    or the state after frame ``seq`` whose storing was put off."""

    session_id: str
    state: bytes
    seq: int | None = None


FrameOutcome = FrameDone | FrameFailed
Outcome = FrameDone | FrameFailed | Checkpoint


@dataclass(frozen=True, slots=True)
class CallDone:
    call_id: int
    ok: bool
    value: object = None
    error_type: str = ""
    error: str = ""
    session_id: str | None = None
    state: bytes | None = None
