"""The service hands the engine the functions of app/tasks and nothing else."""

from __future__ import annotations

import asyncio
from concurrent.futures import Future

import pytest

from vloc.app.engine import run_task
from vloc.app.localize.service import check_prior
from vloc.app.tasks.images import inspect_image


class _Engine:
    """Records what it was asked to run and answers at once."""

    def __init__(self) -> None:
        self.calls: list = []

    def call(self, fn, *args, **kwargs) -> Future:
        self.calls.append((fn, args, kwargs))
        done: Future = Future()
        done.set_result("ran")
        return done


def test_a_task_runs_on_the_engine():
    engine = _Engine()

    async def go():
        return await run_task(engine, inspect_image, b"jpeg", max_pixels=4)

    assert asyncio.run(go()) == "ran"
    assert engine.calls == [(inspect_image, (b"jpeg",), {"max_pixels": 4})]


def _nested():
    def inner():
        pass
    return inner


@pytest.mark.parametrize("fn", [check_prior, "vloc.app.tasks.images:inspect_image", _nested(),
                                print])
def test_anything_else_is_refused_before_it_reaches_the_engine(fn):
    engine = _Engine()
    with pytest.raises(TypeError, match="runs the functions of vloc.app.tasks only"):
        run_task(engine, fn)
    assert engine.calls == []
