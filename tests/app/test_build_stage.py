"""A build says what it is doing: its stage, and progress that moves through the packing."""

from __future__ import annotations

import uuid

from sqlalchemy import select

from tests.app.conftest import ADMIN, jpeg_files, wait_job
from vloc.app.jobs.models import BuildJob, BuildStage, JobStatus
from vloc.app.maps.models import MapImage
from vloc.app.maps.service import image_path
from vloc.app.tasks import build as tasks


def test_the_packing_reports_its_stages_to_the_job(module_client, shots, tmp_path,
                                                   monkeypatch):
    c = module_client
    ctx = c.app.state.ctx
    map_id = c.post("/v1/maps", json={"name": "stages"}, headers=ADMIN).json()["id"]
    assert c.post(f"/v1/maps/{map_id}/images", files=jpeg_files(shots[0][:5]),
                  headers=ADMIN).status_code == 201
    job = wait_job(c, c.post(f"/v1/maps/{map_id}/build", headers=ADMIN).json()["job_id"])
    assert (job["status"], job["stage"], job["progress"]) == ("done", BuildStage.DONE, 1.0)

    # packed again by hand for a job of its own: every stage of the packing reaches the
    # job's row, with the progress the bar shows at its start
    with ctx.db_sessions() as db:
        row = BuildJob(map_id=uuid.UUID(map_id), status=JobStatus.RUNNING)
        db.add(row)
        db.commit()
        job_id = str(row.id)
        files = {img.id: str(image_path(ctx.settings, img)) for img in db.scalars(
            select(MapImage).where(MapImage.map_id == uuid.UUID(map_id)))}
    seen = []
    real = tasks._set_stage

    def record(url, jid, stage):
        real(url, jid, stage)
        with ctx.db_sessions() as db:
            got = db.get(BuildJob, uuid.UUID(jid))
            seen.append((got.stage, got.progress))

    monkeypatch.setattr(tasks, "_set_stage", record)
    tasks.pack_map(ctx.settings.resolved_database_url, map_id, 50, str(tmp_path / "packed"),
                   image_files=files, job_id=job_id)
    assert seen == [(BuildStage.PACKING, 0.9), (BuildStage.GEOMETRY, 0.92),
                    (BuildStage.SAVING, 0.98)]
    # without a job, nothing is written
    seen.clear()
    tasks.pack_map(ctx.settings.resolved_database_url, map_id, 51, str(tmp_path / "again"),
                   image_files=files)
    assert seen == []
