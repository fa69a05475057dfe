"""The layers' import rules, read from the source: the core imports neither the engines nor
the service nor the clients; the engines do not import the service or the clients; in the
service only app/engine.py imports the engines; the migrations' revisions import none of
the repository's code.

The service's code that the engine runs is in one package, app/tasks/, which imports no web
layer, and the service hands the engine nothing else: every engine call goes through
``app.engine.run_task`` with a function of that package."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import REPO_ROOT


def _imports(path: Path) -> set[str]:
    """Every module a file imports, at any depth (inside functions too), named as in the
    repository (without the installed distribution's ``vloc.`` prefix)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.add(node.module)
    return {name.removeprefix("vloc.") for name in found}


def _offences(folder: str, forbidden: tuple[str, ...], *, allowed: tuple[str, ...] = ()):
    out = []
    for path in sorted((REPO_ROOT / folder).rglob("*.py")):
        rel = path.relative_to(REPO_ROOT).as_posix()
        if rel in allowed:
            continue
        for module in _imports(path):
            if any(module == f or module.startswith(f + ".") for f in forbidden):
                out.append(f"{rel} imports {module}")
    return out


@pytest.mark.parametrize(("folder", "forbidden", "allowed"), [
    ("workers/core", ("workers.engine", "app", "clients"), ()),
    ("workers/engine", ("app", "clients"), ()),
    ("app", ("workers.engine", "workers.core.evaluation"), ("app/engine.py",)),
    ("workers/engine", ("workers.core.evaluation",), ()),
    # a revision does what it did when it was written: it imports none of the live code
    ("migrations/versions", ("app", "workers", "clients", "migrations"), ()),
])
def test_layers_import_only_what_is_below_them(folder, forbidden, allowed):
    assert _offences(folder, forbidden, allowed=allowed) == []


def test_the_check_finds_an_offending_import(tmp_path, monkeypatch):
    bad = tmp_path / "pkg" / "mod.py"
    bad.parent.mkdir()
    bad.write_text("def f():\n    from vloc.app.db import make_engine\n")
    monkeypatch.setattr("tests.test_layers.REPO_ROOT", tmp_path)
    assert _offences("pkg", ("app",)) == ["pkg/mod.py imports app.db"]


WEB = ("fastapi", "starlette", "app.main", "app.deps", "app.server")


def _resolved_imports(path: Path) -> set[str]:
    """:func:`_imports` with the relative imports too, named from the repository root."""
    package = path.relative_to(REPO_ROOT).parent.as_posix().split("/")
    found = set(_imports(path))
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and node.level:
            base = package[:len(package) - node.level + 1]
            names = [node.module] if node.module else [a.name for a in node.names]
            found.update(".".join([*base, name]) for name in names)
    return found


def test_the_core_s_algorithms_do_not_import_its_evaluation():
    """workers/core/evaluation measures the algorithms; nothing else in the core uses it."""
    offences = [f"{p.relative_to(REPO_ROOT)} imports {m}"
                for p in sorted((REPO_ROOT / "workers" / "core").rglob("*.py"))
                if "evaluation" not in p.relative_to(REPO_ROOT).parts
                for m in sorted(_resolved_imports(p))
                if m == "workers.core.evaluation" or m.startswith("workers.core.evaluation.")]
    assert offences == []


def _web_imports(folder: str) -> list[str]:
    """Imports of the web layer: FastAPI, the app's assembly and any router."""
    out = _offences(folder, WEB)
    for path in sorted((REPO_ROOT / folder).rglob("*.py")):
        rel = path.relative_to(REPO_ROOT).as_posix()
        out += [f"{rel} imports {m}" for m in sorted(_imports(path))
                if m.startswith("app.") and m.rsplit(".", 1)[-1] == "router"]
    return out


def test_the_tasks_import_no_web_layer():
    assert _web_imports("app/tasks") == []


def test_a_worker_importing_the_tasks_loads_no_web_layer():
    """What the engine's workers import when they unpickle a task, at any depth."""
    modules = sorted("vloc." + p.relative_to(REPO_ROOT).with_suffix("").as_posix()
                     .replace("/", ".").removesuffix(".__init__")
                     for p in (REPO_ROOT / "app" / "tasks").rglob("*.py"))
    code = (f"import importlib, sys\nfor m in {modules!r}: importlib.import_module(m)\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('fastapi', "
            "'starlette') or m.endswith('.router')))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          check=True, timeout=120)
    assert done.stdout.strip() == "[]"


def _aliases(tree: ast.AST) -> dict[str, str]:
    """Each name a module's imports bind -> the dotted name it stands for (no ``vloc.``)."""
    names = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            for alias in node.names:
                names[alias.asname or alias.name] = f"{node.module}.{alias.name}"
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.asname:
                    names[alias.asname] = alias.name
    return {k: v.removeprefix("vloc.") for k, v in names.items()}


def _dotted(node: ast.expr, aliases: dict[str, str]) -> str:
    if isinstance(node, ast.Name):
        return aliases.get(node.id, f"<local>.{node.id}")
    if isinstance(node, ast.Attribute):
        return f"{_dotted(node.value, aliases)}.{node.attr}"
    return f"<{type(node).__name__}>"


def _engine_offences(folder: str, *, allowed: tuple[str, ...] = ()) -> list[str]:
    """Calls that hand the engine a function from outside app/tasks, or that reach the
    engine's ``call`` around ``run_task``."""
    out = []
    for path in sorted((REPO_ROOT / folder).rglob("*.py")):
        rel = path.relative_to(REPO_ROOT).as_posix()
        if rel in allowed:
            continue
        tree = ast.parse(path.read_text(), str(path))
        aliases = _aliases(tree)
        calls = sorted((n for n in ast.walk(tree) if isinstance(n, ast.Call)),
                       key=lambda n: (n.lineno, n.col_offset))
        for node in calls:
            func = node.func
            if (isinstance(func, ast.Attribute) and func.attr == "call"
                    and _dotted(func.value, aliases).endswith("engine")):
                out.append(f"{rel}:{node.lineno} calls the engine around run_task")
            elif _dotted(func, aliases) in ("app.engine.run_task", "<local>.run_task"):
                task = _dotted(node.args[1], aliases) if len(node.args) > 1 else "nothing"
                if not task.startswith("app.tasks."):
                    out.append(f"{rel}:{node.lineno} runs {task} on the engine")
    return out


def test_the_engine_runs_only_the_tasks_package():
    assert _engine_offences("app", allowed=("app/engine.py",)) == []


def test_the_check_finds_a_task_outside_the_tasks_package(tmp_path, monkeypatch):
    bad = tmp_path / "pkg" / "mod.py"
    bad.parent.mkdir()
    bad.write_text(
        "from vloc.app.engine import run_task\n"
        "from vloc.app.maps import service\n"
        "from vloc.app.tasks import build as tasks\n"
        "from vloc.app.tasks.images import inspect_image\n"
        "async def f(ctx):\n"
        "    await run_task(ctx.engine, tasks.pack_map, 1)\n"
        "    await run_task(ctx.engine, inspect_image, b'')\n"
        "    await run_task(ctx.engine, service.image_path, 1)\n"
        "    ctx.engine.call(tasks.pack_map, 1)\n")
    monkeypatch.setattr("tests.test_layers.REPO_ROOT", tmp_path)
    assert _engine_offences("pkg") == [
        "pkg/mod.py:8 runs app.maps.service.image_path on the engine",
        "pkg/mod.py:9 calls the engine around run_task"]
