"""Alembic migrations of the vloc database (see :mod:`app.migrate` to run them)."""
