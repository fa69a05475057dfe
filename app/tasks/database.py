"""The database connection of the tasks in a worker process, one per database URL."""

from __future__ import annotations

from functools import lru_cache

from sqlalchemy.orm import Session, sessionmaker

from vloc.app.db import make_engine, make_session_factory


@lru_cache(maxsize=8)
def sessions(database_url: str) -> sessionmaker[Session]:
    """The session factory for ``database_url``, made once per worker process."""
    return make_session_factory(make_engine(database_url))
