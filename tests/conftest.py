"""Fixtures shared by the whole test tree."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]


def shared_dir() -> Path:
    """The shared folder beside the repository, or ``$VLOC_SHARED_DIR`` when set."""
    env = os.environ.get("VLOC_SHARED_DIR")
    return Path(env) if env else REPO_ROOT / ".." / "shared"


@pytest.fixture(scope="session")
def seneca_dir() -> Path:
    """The real UAV data set ``seneca-uav``; the test is skipped where it is absent."""
    path = shared_dir() / "datasets" / "seneca-uav"
    if not (path / "images").is_dir():
        pytest.skip(f"data set seneca-uav not found at {path.resolve()} "
                    "(set VLOC_SHARED_DIR to the folder holding datasets/)")
    return path
