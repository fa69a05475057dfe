"""FastAPI's validation errors as the client wrote the request.

pydantic locates an error in the model it validated, which is not always the request the
client sent: a discriminated union adds its tag (``body.filter.params.n_particle`` for a
body ``{"params": {"n_particle": 5}}``). :func:`readable` drops those segments and, for an
unknown name, suggests the known one it most resembles.
"""

from __future__ import annotations

import difflib
import types
import typing
from typing import Any

from pydantic import BaseModel

from vloc.app.problems import ProblemKind

MISSING = {("body", "files"): ("no files in the upload (form field 'files')",
                               ProblemKind.NO_FILES)}
"""Missing fields with a problem kind of their own: location -> (detail, kind)."""


def readable(errors: list[dict], body: Any, body_types: list[Any]) -> list[dict]:
    """Each error with ``loc`` as the client wrote it, and a ``suggestion`` for an unknown
    name close to a known one (of the models in ``body_types``)."""
    names = set().union(*(_field_names(t) for t in body_types)) if body_types else set()
    out = []
    for error in errors:
        error = dict(error, loc=_as_sent(error["loc"], body))
        if error.get("type") == "extra_forbidden" and error["loc"]:
            name = str(error["loc"][-1])
            # a name that is known elsewhere (another mode's parameter) gets no suggestion
            close = difflib.get_close_matches(name, names - {name}, n=1, cutoff=0.75)
            if close and name not in names:
                error["suggestion"] = close[0]
        out.append(error)
    return out


def _as_sent(loc: list, body: Any) -> list:
    if not loc or loc[0] != "body":
        return list(loc)
    out, here = [loc[0]], body
    for i, part in enumerate(loc[1:], start=1):
        last = i == len(loc) - 1
        if isinstance(here, dict) and part not in here and not last:
            continue  # a wrapper the client never sent: the tag of a union
        out.append(part)
        if isinstance(here, dict):
            here = here.get(part)
        elif isinstance(here, list) and isinstance(part, int) and 0 <= part < len(here):
            here = here[part]
        else:
            here = None
    return out


def _field_names(annotation: Any, seen: set | None = None) -> set[str]:
    """The field names of every model reachable from ``annotation``."""
    seen = set() if seen is None else seen
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        if annotation in seen:
            return set()
        seen.add(annotation)
        names = set(annotation.model_fields)
        for field in annotation.model_fields.values():
            names |= _field_names(field.annotation, seen)
        return names
    if isinstance(annotation, types.UnionType) or typing.get_origin(annotation) is not None:
        return set().union(*(_field_names(a, seen) for a in typing.get_args(annotation)),
                           set())
    return set()
