"""The README's two commands: ``make demo`` installs the runtime only and says one line while
it does; ``make test`` adds the dev extra (pytest, Playwright, Schemathesis, Ray) on top,
after ``make demo`` or on a fresh checkout."""

from __future__ import annotations

import re
import shutil
import subprocess

import pytest

from tests.conftest import REPO_ROOT

pytestmark = pytest.mark.skipif(shutil.which("make") is None, reason="no make here")


def _dry_run(target: str) -> str:
    """The commands ``make TARGET`` would run from scratch (nothing is run)."""
    done = subprocess.run(["make", "--dry-run", "--always-make", target], cwd=REPO_ROOT,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    return done.stdout


def _installs(commands: str) -> list[str]:
    return [line for line in commands.splitlines() if " install " in line]


def test_the_demo_installs_the_runtime_without_the_dev_extra():
    installs = _installs(_dry_run("demo"))
    assert installs and not any("[dev]" in line for line in installs)
    assert all("-c docker/requirements.lock" in line for line in installs if " -e " in line)


def test_the_tests_install_the_dev_extra_over_the_runtime():
    installs = _installs(_dry_run("test"))
    assert any("-e ." in line for line in installs)
    assert any("'.[dev]'" in line for line in installs)


def test_the_demo_setup_says_one_line_and_runs_quietly():
    text = (REPO_ROOT / "Makefile").read_text()
    recipes = {}
    for target, body in re.findall(r"^(\S[^:\n]*):[^\n]*\n((?:\t[^\n]*\n)+)", text, re.M):
        recipes[target] = body.splitlines()
    runtime = recipes["$(RUNTIME)"] + recipes["demo"]
    assert all(line.startswith("\t@") for line in runtime), runtime
    assert sum("echo" in line for line in runtime) == 1
    assert all(line.startswith("\t@$(PIP) ") for line in runtime if "install" in line)
    assert "PIP    := $(BIN)/python -m pip --quiet --quiet" in text
