"""What the benchmark scripts share: one BLAS thread, the repository's paths, results files.

The scripts in ``bench/`` run as ``python bench/NAME.py``: ``bench/`` is then ``sys.path[0]``
and they import this module as ``_common``. Those one folder deeper (``bench/paper/``,
``bench/nav/``) put the repository on ``sys.path`` first and import it as ``bench._common``.

It imports only the standard library, so that a script can import it and call
:func:`one_thread` before anything loads numpy: the thread count of BLAS is read once, when
numpy loads, and cannot be changed through the environment afterwards.
"""

from __future__ import annotations

import os
import platform
import sys
from collections.abc import Iterable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
"""The repository's root folder."""
RESULTS = ROOT / "bench" / "results"
"""Where the benchmarks keep the results they report."""
DATASETS = ROOT.parent / "shared" / "datasets"
"""The recorded data sets (``seneca-uav``, ``lewis-uav``), beside the repository when present."""

THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
"""The environment variables that set how many threads OpenMP, OpenBLAS and MKL start."""


def one_thread(names: Iterable[str] = THREAD_VARIABLES, *, override: bool = True) -> None:
    """Pin BLAS and OpenMP to one thread, so that what a script times is one core's work.

    Call it before numpy (or anything that imports numpy) is imported: the libraries read
    these variables when they load.

    Parameters
    ----------
    names : iterable of str, optional
        The variables to set to ``"1"``; all of :data:`THREAD_VARIABLES` by default.
    override : bool, optional
        Replace a value already in the environment (the default). With ``False`` a
        variable the user has set keeps its value; only the unset ones become ``"1"``.
    """
    for name in names:
        if override:
            os.environ[name] = "1"
        else:
            os.environ.setdefault(name, "1")


def repo_on_path() -> None:
    """Put the repository's root first on ``sys.path``, where ``tests`` and ``bench`` are."""
    sys.path.insert(0, str(ROOT))


def machine_and_python() -> str:
    """The machine and the Python a result was taken with, e.g. ``x86_64, Python 3.11.9``."""
    return f"{platform.machine()}, Python {platform.python_version()}"


def write_result(path: Path, text: str, *, echo: bool = True, announce: bool = False) -> Path:
    """Write a results file as UTF-8, creating its folder, then print what was written.

    Parameters
    ----------
    path : Path
        The file to write, e.g. ``RESULTS / "core.md"``; its folder is created if missing.
    text : str
        The whole file, written as it is (no newline is added).
    echo : bool, optional
        Print ``text`` once it is written (the default).
    announce : bool, optional
        Print ``wrote PATH`` last.

    Returns
    -------
    Path
        ``path``, for a caller that goes on to write files beside it.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
    if echo:
        print(text)
    if announce:
        print(f"wrote {path}")
    return path
