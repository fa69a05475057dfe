"""Schemathesis, every check, a few examples per operation, against a real server process:
no server error, and every response as the OpenAPI description states it."""

from __future__ import annotations

import sys

from tests.conftest import REPO_ROOT

sys.path.insert(0, str(REPO_ROOT / "bench"))

from fuzz import run_fuzz  # noqa: E402

EXAMPLES = 8
"""Per operation and phase; the whole run takes well under a minute."""


def test_schemathesis_finds_nothing():
    result = run_fuzz(EXAMPLES, seed=7)
    assert result.returncode == 0, result.output[-8000:]
    assert "passed" in result.summary and "failures" not in result.summary.lower()
