"""The service's distribution installs one top-level package, ``vloc``, holding the
repository's ``app``, ``workers``, ``clients`` and ``migrations`` folders with their data, and
nothing under the generic names themselves."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest
import sqlalchemy

from tests.conftest import REPO_ROOT

FOLDERS = ("app", "workers", "clients", "migrations")


def _listed() -> set[str]:
    config = tomllib.loads((REPO_ROOT / "pyproject.toml").read_text())
    return set(config["tool"]["setuptools"]["packages"])


def test_every_package_folder_is_listed_under_vloc():
    folders = {p.parent for f in FOLDERS for p in (REPO_ROOT / f).rglob("__init__.py")}
    folders.add(REPO_ROOT / "migrations" / "versions")  # revisions: modules without __init__
    expected = {"vloc." + p.relative_to(REPO_ROOT).as_posix().replace("/", ".")
                for p in folders if "__pycache__" not in p.parts}
    assert _listed() == expected


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> tuple[Path, str]:
    """A wheel built from a copy of what the distribution is made of (setuptools leaves a
    build folder beside the sources it builds, which is not the repository's to keep)."""
    src, out = tmp_path_factory.mktemp("src"), tmp_path_factory.mktemp("wheel")
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(REPO_ROOT / name, src / name)
    for folder in FOLDERS:
        shutil.copytree(REPO_ROOT / folder, src / folder,
                        ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    done = subprocess.run([sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps",
                           "--wheel-dir", str(out), str(src)], check=True, timeout=300,
                          capture_output=True, text=True)
    (path,) = out.glob("vloc-*.whl")
    return path, done.stdout + done.stderr


@pytest.fixture(scope="module")
def wheel(built) -> Path:
    return built[0]


def test_the_build_prints_no_warning(built):
    """What ``make demo`` shows before its first line: setuptools' deprecations (a license
    table) and data folders it does not know how to treat."""
    _, output = built
    assert re.findall(r"\w*Warning: .*", output) == []


def test_the_wheel_holds_one_top_level_package_with_its_data(wheel):
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/")[0] for n in names}
    assert {t for t in tops if not t.endswith(".dist-info")} == {"vloc"}
    for needed in ("vloc/app/main.py", "vloc/app/ui/static/index.html",
                   "vloc/app/ui/static/vendor/leaflet/leaflet.js",
                   "vloc/workers/core/localisers/filtering.py", "vloc/clients/cli.py",
                   "vloc/migrations/env.py"):
        assert needed in names, needed
    assert any(n.startswith("vloc/migrations/versions/0001_") for n in names)
    entry_points = next(n for n in names if n.endswith("entry_points.txt"))
    assert "vloc = vloc.clients.cli:main" in zipfile.ZipFile(wheel).read(entry_points).decode()


def test_the_installed_package_migrates_a_database_from_its_own_files(wheel, tmp_path):
    site = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps",
                    "--target", str(site), str(wheel)], check=True, timeout=300)
    # Isolated (-I): neither the working directory nor the repository is on the path, so
    # everything below comes from the installed files. The deployment's migration step.
    script = (
        "import runpy, sys; sys.path.insert(0, sys.argv[1])\n"
        "from vloc.app import migrate\n"
        "assert migrate.__file__.startswith(sys.argv[1]), migrate.__file__\n"
        "runpy.run_module('vloc.app.migrate', run_name='__main__')\n")
    db = tmp_path / "db.sqlite3"
    done = subprocess.run([sys.executable, "-I", "-c", script, str(site)],
                          capture_output=True, text=True, timeout=120,
                          env={**os.environ, "VLOC_DATABASE_URL": f"sqlite:///{db}"})
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("database at revision 0")
    tables = sqlalchemy.inspect(sqlalchemy.create_engine(f"sqlite:///{db}")).get_table_names()
    assert {"maps", "map_images", "sessions", "routes"} <= set(tables)
