"""docs/api.md and docs/client.md against the code: every field of a pose and every problem
type is described, and the `sh` examples of docs/api.md run, in order, as one script
against a real server."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.conftest import REPO_ROOT
from vloc.app.sessions.schemas import PoseEstimate
from vloc.clients.sdk import Pose as ClientPose

API_MD = (REPO_ROOT / "docs" / "api.md").read_text()
CLIENT_MD = (REPO_ROOT / "docs" / "client.md").read_text()
POSE_FIELDS = set(PoseEstimate.model_fields) | {"geopose"}


def _section(text: str, heading: str) -> str:
    start = text.index(heading)
    nxt = re.search(r"^#{1,3} ", text[start + len(heading):], re.M)
    return text[start:start + len(heading) + (nxt.start() if nxt else len(text))]


def _table_names(section: str) -> set[str]:
    """The backquoted names in the first column of the section's tables."""
    names = set()
    for line in section.splitlines():
        if line.startswith("| `"):
            names |= set(re.findall(r"`([a-z_]+)`", line.split("|")[1]))
    return names


def test_api_md_describes_every_pose_field():
    start = API_MD.index("What a pose says")
    table = API_MD[start:API_MD.index("A frame that was accepted but gave no estimate", start)]
    assert _table_names(table) == POSE_FIELDS


def test_client_md_describes_every_pose_attribute():
    assert _table_names(_section(CLIENT_MD, "### Poses")) == set(ClientPose.model_fields)


def test_api_md_lists_every_problem_type():
    code = "\n".join(p.read_text() for p in (REPO_ROOT / "app").rglob("*.py"))
    kinds = set(re.findall(r'kind="([a-z-]+)"', code))
    kinds |= {"duplicate-seq", "stale-seq"}  # chosen at run time
    kinds |= {f"frame-{k.replace('_', '-')}" for k in
              ("bad_image", "error", "not_stored", "worker_died", "not_open")}
    errors = _section(API_MD, "## Errors")
    listed = {k for line in errors.splitlines() if line.startswith("| ")
              for k in re.findall(r"`([a-z-]+)`", line.split("|")[2])}
    assert kinds - listed == set()


def _sh_blocks(text: str) -> list[str]:
    return re.findall(r"^```sh\n(.*?)^```", text, re.M | re.S)


def _files(folder: Path) -> None:
    """The files the examples name: geotagged map images and query frames."""
    from tests.clients.conftest import make_shots

    maps, queries = make_shots(10)
    for i, shot in enumerate(maps[:3]):
        (folder / f"IMG_{446 + i:04d}.jpg").write_bytes(shot.jpeg)
    # a PNG without EXIF: its position comes in the form fields (41.0347, -83.3057)
    grey = cv2.imdecode(np.frombuffer(maps[3].jpeg, np.uint8), cv2.IMREAD_COLOR)
    (folder / "frame.png").write_bytes(cv2.imencode(".png", grey)[1].tobytes())
    for i, shot in enumerate(queries[:3]):
        (folder / f"IMG_{516 + i:04d}.jpg").write_bytes(shot.jpeg)


@pytest.mark.skipif(sys.platform == "win32", reason="the examples are POSIX shell")
def test_the_curl_examples_run(server, tmp_path):
    for tool in ("curl", "jq", "bash"):
        if subprocess.run(["which", tool], capture_output=True).returncode:
            pytest.skip(f"{tool} is not installed")
    _files(tmp_path)
    script = "set -euo pipefail\n" \
             "curl() { command curl --fail-with-body \"$@\"; }\n" + "\n".join(_sh_blocks(API_MD))
    (tmp_path / "api.sh").write_text(script)
    env = {**os.environ, "VLOC": server.base_url}
    out = subprocess.run(["bash", str(tmp_path / "api.sh")], cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stdout[-4000:] + out.stderr[-4000:]
    for member in ('"type": *"localization"', '"state": *"active"', '"status": *"done"',
                   '"heading_source": *"(device|geometry)"', '"altitude_m": *250'):
        assert re.search(member, out.stdout), member
