"""What one running application holds: settings, database, engine, fan-out, the live
sessions, their frame intake, and the build and route runners."""

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
    from vloc.app.sessions.intake import FrameIntake
    from vloc.app.sessions.registry import SessionRegistry
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
    sessions: SessionRegistry
    intake: FrameIntake
    builds: BuildRunner
    routes: RouteRunner
