"""``vloc serve``: the API server (uvicorn) with its pool of worker processes."""

from __future__ import annotations

import click

GRACEFUL_SHUTDOWN_S = 30


@click.command("serve")
@click.option("--host", default="127.0.0.1", show_default=True, help="Address to bind.")
@click.option("--port", default=8000, show_default=True, type=click.IntRange(0, 65535))
@click.option("--workers", type=click.IntRange(1), default=None,
              help="Worker processes of the engine [default: VLOC_WORKERS, else one per core].")
@click.option("--log-level", default=None, help="[default: VLOC_LOG_LEVEL, else INFO]")
def serve_cmd(host: str, port: int, workers: int | None, log_level: str | None) -> None:
    """Run the API server.

    Configuration comes from VLOC_* environment variables (VLOC_DATABASE_URL,
    VLOC_DATA_DIR, VLOC_WORKERS, VLOC_ADMIN_KEY, VLOC_REDIS_URL, VLOC_MAX_*); see
    docs/api.md. Without VLOC_ADMIN_KEY an admin key is generated on the first start,
    stored in the data directory and printed once.
    """
    import uvicorn

    from app.config import Settings
    from app.main import create_app, drain
    from app.server import DrainingServer

    overrides = {}
    if workers is not None:
        overrides["workers"] = workers
    if log_level is not None:
        overrides["log_level"] = log_level
    settings = Settings(**overrides)
    app = create_app(settings, configure_logging=True)
    config = uvicorn.Config(app, host=host, port=port, log_config=None,
                            log_level=settings.log_level.lower(),
                            ws_max_size=settings.max_frame_bytes + 4096,
                            timeout_graceful_shutdown=GRACEFUL_SHUTDOWN_S)
    DrainingServer(config, drain=lambda: drain(app)).run()
