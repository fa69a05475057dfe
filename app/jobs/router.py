"""Job status routes (admin)."""

from __future__ import annotations

from fastapi import APIRouter, Depends

from vloc.app.deps import DbSession, require_admin
from vloc.app.jobs.models import BuildJob
from vloc.app.jobs.schemas import JobRead
from vloc.app.maps.dependencies import parse_id
from vloc.app.problems import not_found

router = APIRouter(prefix="/v1/jobs", tags=["jobs"], dependencies=[Depends(require_admin)])


@router.get("/{job_id}", response_model=JobRead)
def get_job(job_id: str, db: DbSession) -> BuildJob:
    """A build job: status, progress, counts, and the revision it made."""
    job = db.get(BuildJob, parse_id(job_id, "job"))
    if job is None:
        raise not_found("job", job_id)
    return job
