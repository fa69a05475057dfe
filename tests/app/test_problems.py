"""The problem kinds are one list: the server's enumeration, its documentation in docs/api.md,
and no problem raised with a kind outside it."""

from __future__ import annotations

import re

import pytest

from tests.conftest import REPO_ROOT
from vloc.app.problems import Problem, ProblemKind


def documented_kinds() -> set[str]:
    """The kinds of the error table in docs/api.md (its second column)."""
    section = (REPO_ROOT / "docs" / "api.md").read_text().split("\n## Errors\n", 1)[1]
    rows = [line for line in section.split("\n## ", 1)[0].splitlines()
            if line.startswith("| ") and not line.startswith("| status")]
    return {kind for row in rows for kind in re.findall(r"`([a-z-]+)`", row.split("|")[2])}


def test_every_kind_is_documented_and_every_documented_kind_exists():
    assert documented_kinds() == {k.value for k in ProblemKind}


def test_a_problem_names_its_type_by_its_kind():
    problem = Problem(409, "seq 2 is not after 5", kind="stale-seq", last_seq=5)
    assert problem.kind is ProblemKind.STALE_SEQ
    assert problem.body()["type"] == "urn:vloc:problem:stale-seq"
    assert Problem(418, "tea").body()["type"] == "about:blank"


def test_a_kind_outside_the_list_is_refused():
    with pytest.raises(ValueError, match="not-a-kind"):
        Problem(400, "no", kind="not-a-kind")
