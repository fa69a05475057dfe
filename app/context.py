"""What one running application holds: settings, database, engine, fan-out, runtime."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from sqlalchemy import Engine
from sqlalchemy.orm import Session, sessionmaker

from app.config import Settings
from app.metrics import Metrics

if TYPE_CHECKING:
    from app.engine import Engine
    from app.jobs.service import BuildRunner
    from app.routes.service import RouteRunner
    from app.sessions.runtime import SessionRuntime
    from app.stream.hub import LocalHub


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
