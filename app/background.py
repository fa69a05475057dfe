"""Work the app runs in the background on its event loop: map builds and route builds."""

from __future__ import annotations

import asyncio
import uuid
from abc import ABC, abstractmethod


class BackgroundRunner(ABC):
    """Runs one task per id on the application's event loop and keeps it until it ends.

    Subclasses are dataclasses with a ``loop`` field (set when the application starts) and
    implement :meth:`run`, which records its own failures.
    """

    task_name = "task"
    """Prefix of the tasks' names (``<task_name>-<id>``)."""
    loop: asyncio.AbstractEventLoop | None

    def __post_init__(self) -> None:
        self._tasks: set[asyncio.Task] = set()

    def launch(self, item_id: uuid.UUID) -> None:
        """Start the work for ``item_id``; callable from any thread."""
        assert self.loop is not None, "the runner starts with the application"
        self.loop.call_soon_threadsafe(self._spawn, item_id)

    def _spawn(self, item_id: uuid.UUID) -> None:
        task = self.loop.create_task(self.run(item_id), name=f"{self.task_name}-{item_id}")
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def wait_idle(self) -> None:
        while self._tasks:
            await asyncio.gather(*list(self._tasks), return_exceptions=True)

    async def cancel_all(self) -> None:
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*list(self._tasks), return_exceptions=True)

    @abstractmethod
    async def run(self, item_id: uuid.UUID) -> None:
        """Do the work for ``item_id``, recording its outcome (failures included)."""
