"""What one running application holds: settings, database, engine, fan-out, runtime."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from sqlalchemy import Engine
from sqlalchemy.orm import Session, sessionmaker

from vloc.app.config import Settings
from vloc.app.metrics import Metrics

if TYPE_CHECKING:
    from vloc.app.engine import Engine
    from vloc.app.jobs.service import BuildRunner
    from vloc.app.sessions.runtime import SessionRuntime
    from vloc.app.stream.hub import LocalHub
    from vloc.app.teach.service import RouteRunner


@dataclass(eq=False)
class AppContext:
    settings: Settings
    db_engine: Engine
    db_sessions: sessionmaker[Session]
    admin_key_hash: str
    metrics: Metrics
    engine: Engine
    hub: LocalHub
    runtime: SessionRuntime
    builds: BuildRunner
    routes: RouteRunner
