"""Where was this one image taken? A synchronous, sessionless localisation.

The route (``POST /v1/maps/{id}/localize``) checks the request and the map, then runs
:func:`vloc.app.tasks.localize.localize_image` on the least busy worker of the engine; this
module checks what the request gives of the filter's start.
"""

from __future__ import annotations

from vloc.app.problems import Problem, ProblemKind

DEFAULT_PRIOR_SIGMA_M = 25.0


def check_prior(lat: float | None, lon: float | None, sigma_m: float | None
                ) -> tuple[float, float, float] | None:
    """The prior position, or None; 422 ``bad-prior`` for half a pair or a sigma without
    a position (ranges are checked by the query parser)."""
    if lat is None and lon is None:
        if sigma_m is not None:
            raise Problem(422, "prior_sigma_m needs prior_lat and prior_lon",
                          kind=ProblemKind.BAD_PRIOR, field="prior_sigma_m")
        return None
    if lat is None or lon is None:
        missing = "prior_lat" if lat is None else "prior_lon"
        raise Problem(422, "prior_lat and prior_lon come together", kind=ProblemKind.BAD_PRIOR,
                      field=missing)
    return lat, lon, sigma_m if sigma_m is not None else DEFAULT_PRIOR_SIGMA_M
