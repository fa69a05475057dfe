"""Schemathesis against a real ``vloc serve`` process, with every check.

Starts the server on a fresh data directory (SQLite, one worker), runs ``st run`` on its
OpenAPI description with the admin key (so that the checks reach past authentication;
``ignored_auth`` tries the operations without it too), and reports the counts.

    python bench/fuzz.py --max-examples 200 --out bench/results/fuzz.txt

The test suite runs the same with a few examples per operation
(``tests/e2e/test_fuzz.py``); ``make fuzz`` runs the longer one.
"""

from __future__ import annotations

import argparse
import os
import re
import secrets
import signal
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import httpx
from _common import ROOT, write_result

CONFIG = ROOT / "bench" / "schemathesis.toml"


@dataclass
class FuzzResult:
    returncode: int
    summary: str
    """The run's closing summary (operations, test cases, failures)."""
    output: str
    seconds: float


def run_fuzz(max_examples: int, *, seed: int = 1, phases: str | None = None,
             workers: int = 1) -> FuzzResult:
    """Serve on a free port from a temporary data directory and fuzz it."""
    with tempfile.TemporaryDirectory(prefix="vloc-fuzz-") as tmp:
        key = secrets.token_urlsafe(24)
        port = _free_port()
        env = {**os.environ, "VLOC_DATA_DIR": str(Path(tmp) / "data"), "VLOC_WORKERS": "1",
               "VLOC_ADMIN_KEY": key, "VLOC_LOG_LEVEL": "WARNING"}
        env.pop("VLOC_DATABASE_URL", None)
        log = (Path(tmp) / "server.log").open("wb")
        server = subprocess.Popen(
            [sys.executable, "-m", "vloc.clients.cli", "serve", "--host", "127.0.0.1",
             "--port", str(port)], cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=log)
        try:
            base = f"http://127.0.0.1:{port}"
            _wait_ready(base, server)
            cmd = [str(Path(sys.executable).with_name("st")), "--config-file", str(CONFIG),
                   "run", f"{base}/openapi.json", "--checks", "all",
                   "--header", f"Authorization: Bearer {key}",
                   "--max-examples", str(max_examples), "--seed", str(seed),
                   "--workers", str(workers), "--no-color", "--request-timeout", "60"]
            if phases:
                cmd += ["--phases", phases]
            t0 = time.perf_counter()
            # In the temporary directory: Schemathesis keeps its caches in the working one.
            done = subprocess.run(cmd, cwd=tmp, capture_output=True, text=True,
                                  env={**os.environ, "COLUMNS": "120"})
            seconds = time.perf_counter() - t0
        finally:
            server.send_signal(signal.SIGTERM)
            try:
                server.wait(60)
            except subprocess.TimeoutExpired:
                server.kill()
            log.close()
    output = done.stdout + done.stderr
    return FuzzResult(done.returncode, _summary(output), output, seconds)


def _summary(output: str) -> str:
    """The lines of the run's summary: per-phase results, checks, test case counts."""
    start = output.rfind("SUMMARY")
    text = output[start:] if start >= 0 else output[-3000:]
    return re.sub(r"\n{3,}", "\n\n", text.strip())


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_ready(base: str, server: subprocess.Popen, timeout: float = 120.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if server.poll() is not None:
            raise RuntimeError(f"the server exited with {server.returncode}")
        try:
            if httpx.get(f"{base}/readyz", timeout=1.0).status_code == 200:
                return
        except httpx.TransportError:
            pass
        time.sleep(0.2)
    raise RuntimeError("the server did not become ready")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--max-examples", type=int, default=200)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    result = run_fuzz(args.max_examples, seed=args.seed)
    text = (f"# Schemathesis {_version()}: st run --checks all --max-examples "
            f"{args.max_examples} --seed {args.seed} (python bench/fuzz.py)\n"
            f"# exit code {result.returncode}, {result.seconds:.0f} s\n\n{result.summary}\n")
    print(result.output if result.returncode else text)
    if args.out is not None:
        write_result(args.out, text, echo=False)
    return result.returncode


def _version() -> str:
    from importlib.metadata import version

    return version("schemathesis")


if __name__ == "__main__":
    sys.exit(main())
