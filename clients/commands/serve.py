"""``vloc serve``: the API server (uvicorn) with its engine; ``--processes N`` runs N API
processes on one listening socket, for a shared engine (``VLOC_ENGINE=ray``)."""

from __future__ import annotations

import multiprocessing as mp
import signal
import socket
import time

import click

GRACEFUL_SHUTDOWN_S = 30
RESTART_DELAY_S = 1.0


@click.command("serve")
@click.option("--host", default="127.0.0.1", show_default=True, help="Address to bind.")
@click.option("--port", default=8000, show_default=True, type=click.IntRange(0, 65535))
@click.option("--workers", type=click.IntRange(1), default=None,
              help="Worker processes of the engine [default: VLOC_WORKERS, else one per core].")
@click.option("--processes", type=click.IntRange(1), default=1, show_default=True,
              help="API processes sharing the port; more than one needs VLOC_ENGINE=ray, "
                   "a shared database (VLOC_DATABASE_URL) and VLOC_REDIS_URL.")
@click.option("--log-level", default=None, help="[default: VLOC_LOG_LEVEL, else INFO]")
def serve_cmd(host: str, port: int, workers: int | None, processes: int,
              log_level: str | None) -> None:
    """Run the API server.

    Configuration comes from VLOC_* environment variables (VLOC_DATABASE_URL,
    VLOC_DATA_DIR, VLOC_WORKERS, VLOC_ADMIN_KEY, VLOC_REDIS_URL, VLOC_ENGINE,
    VLOC_RAY_ADDRESS, VLOC_MAX_*, VLOC_LOG_JSON); see docs/api.md. Without VLOC_ADMIN_KEY an
    admin key is generated on the first start and stored in DATA_DIR/admin_key (readable by
    this user only); it is never printed, and the `vloc` commands read it from there.
    Once ready, the server prints the addresses of the web viewer (/ui/) and of the API's
    documentation (/docs). Logs go to stderr: plain lines on a terminal, JSON lines
    otherwise.
    """
    from vloc.app.config import Settings

    overrides = {}
    if workers is not None:
        overrides["workers"] = workers
    if log_level is not None:
        overrides["log_level"] = log_level
    settings = Settings(**overrides)
    if processes == 1:
        _serve(overrides, host, port, None, None)
        return
    problems = [why for bad, why in (
        (settings.engine != "ray", "VLOC_ENGINE=ray (a local engine's sessions live in one "
                                   "process)"),
        (settings.embedded_database, "VLOC_DATABASE_URL (a database every process shares)"),
        (not settings.redis_url, "VLOC_REDIS_URL (poses reach streams held by any process)"),
        (settings.engine == "ray" and not settings.ray_address,
         "VLOC_RAY_ADDRESS (without it each process starts a private Ray cluster)"))
        if bad]
    if problems:
        raise click.UsageError("--processes > 1 needs " + "; ".join(problems))
    # The admin key is made once, here, rather than raced for by the processes.
    from vloc.app.config import ensure_admin_key, private_dir

    private_dir(settings.data_dir)
    ensure_admin_key(settings)
    _supervise(overrides, host, port, processes, settings.instance_name)


def _serve(overrides: dict, host: str, port: int, sock: socket.socket | None,
           instance_name: str | None) -> None:
    """One API process; on ``sock`` when given (a process of ``--processes``)."""
    import uvicorn

    from vloc.app.config import Settings
    from vloc.app.main import create_app, drain
    from vloc.app.server import DrainingServer

    if instance_name is not None:
        overrides = {**overrides, "instance_name": instance_name}
    settings = Settings(**overrides)
    app = create_app(settings, configure_logging=True)
    config = uvicorn.Config(app, host=host, port=port, log_config=None,
                            log_level=settings.log_level.lower(),
                            ws_max_size=settings.max_frame_bytes + 4096,
                            timeout_graceful_shutdown=GRACEFUL_SHUTDOWN_S)
    DrainingServer(config, drain=lambda: drain(app),
                   on_ready=None if sock is not None else _say_where).run(
        sockets=[sock] if sock is not None else None)


def _say_where(base_url: str) -> None:
    click.echo(f"vloc: ready at {base_url}\n"
               f"  web viewer  {base_url}/ui/\n"
               f"  API docs    {base_url}/docs", err=True)


def _supervise(overrides: dict, host: str, port: int, n: int, base_name: str) -> None:
    """Bind the port once, run ``n`` API processes on it, start again any that dies, and
    pass a stop (SIGTERM, Ctrl-C) on to all of them."""
    sock = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind((host, port))
    sock.listen(2048)
    sock.set_inheritable(True)
    ctx = mp.get_context("spawn")
    stopping = False

    def start(i: int) -> mp.process.BaseProcess:
        # Each process is an instance of its own: the frames it leaves queued when it stops
        # are its own to report when it starts again.
        p = ctx.Process(target=_serve, name=f"vloc-api-{i}",
                        args=(overrides, host, port, sock, f"{base_name}-{i}"))
        p.start()
        return p

    def stop(signum, frame) -> None:
        nonlocal stopping
        stopping = True
        for p in procs:
            if p.is_alive():
                p.terminate()  # SIGTERM: each drains as a single server would

    procs = [start(i) for i in range(n)]
    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    from vloc.app.server import browser_url

    base_url = browser_url(host, sock.getsockname()[1])
    click.echo(f"vloc: {n} API processes on {base_url} (viewer {base_url}/ui/, API docs "
               f"{base_url}/docs)", err=True)
    while not stopping:
        time.sleep(RESTART_DELAY_S)
        for i, p in enumerate(procs):
            if not p.is_alive() and not stopping:
                click.echo(f"vloc: API process {i} (pid {p.pid}) exited with {p.exitcode}; "
                           "starting another", err=True)
                procs[i] = start(i)
    from vloc.app.config import Settings

    drain_s = Settings(**overrides).drain_timeout_s
    for p in procs:
        p.join(drain_s + GRACEFUL_SHUTDOWN_S + 10)
        if p.is_alive():
            p.kill()
    sock.close()

