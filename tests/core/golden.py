"""Recorded estimates of every localiser mode and configuration, for regression checks.

Each case runs one localiser over a short query sequence with a fixed seed and records every
estimate at full precision (positions, spreads, covariance, feature, next feature, status,
best image). Half way through, the localiser's state is packed and restored into a fresh
localiser of another seed, so the checkpoint format is part of what is pinned down.

SIFT, resizing and the BLAS kernels differ in their last bits from one CPU to another, and a
filter amplifies such bits, so the answers are recorded per platform: ``golden_estimates/``
beside this file holds one ``<fingerprint>.json`` for each platform (see
:func:`platform_fingerprint`) and ``params.json``, what parameter validation accepts and
refuses, which is the same everywhere. Record them with::

    .venv/bin/python -m tests.core.golden --seneca                  # after a change of behaviour
    .venv/bin/python -m tests.core.golden --seneca --add-platform   # same code, another CPU

The first records this platform's answers and removes every other platform's, which the
change has made stale; the second adds this platform's answers beside the others, and is
only right when the code is the one they were recorded with. Both run with the BLAS's own
thread count, as the tests do (they refuse ``OMP_NUM_THREADS`` and the like: one thread
gives the same machine another fingerprint).
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import os
import tempfile
from pathlib import Path
from unittest import mock

import cv2
import numpy as np

from vloc.clients.world import generate_world
from vloc.workers.core.evaluation.experiment import load_experiment
from vloc.workers.core.localisers import make_localiser

GOLDEN_DIR = Path(__file__).with_name("golden_estimates")
PARAMS_FILE = GOLDEN_DIR / "params.json"

FILTER_CASES: list[dict] = [
    {"config": "weiss2008"},
    {"config": "default"},
    # paths the named configurations leave off
    {"config": "default", "global_check": 3, "sift_candidates": 5, "global_trust": 3,
     "global_trust_level": 0.5},
    {"config": "weiss2008", "velocity": True, "resampler": "systematic",
     "replacement": "retrieval", "sift_reduce": "map", "global_features": ["grid_hist"],
     "global_measure": "bradley", "n_particles": 120},
    # not "fundamental": OpenCV's RANSAC for the fundamental matrix gives other inliers
    # from one call to the next on the same points, so it cannot be recorded
    {"config": "weiss2008", "sift_reduce": "query", "sift_verify": "homography",
     "sift_ratio": 0.8, "speed": None, "distance_scale": 6.0, "global_trust": 1,
     "global_trust_level": 0.0},
]
SINGLE_FRAME_CASES: dict[str, list[dict]] = {
    "retrieval": [{}, {"feature": "wgii", "measure": "l1"}],
    "hierarchical": [{}, {"k": 3, "sift_ratio": 0.7, "sift_verify": "homography"}],
}
CASES: list[tuple[str, dict]] = (
    [(mode, p) for mode in ("hybrid", "global", "sift") for p in FILTER_CASES]
    + [(mode, p) for mode, ps in SINGLE_FRAME_CASES.items() for p in ps])

WORLDS = {
    # kind, world seed, frames per pass, route length (m)
    "robot": ("robot", 3, 30, 30.0),
    "uav": ("uav", 3, 30, 200.0),
}
SENECA_FRAMES = 14
SEED = 7


def _magnitude(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``sqrt(x^2 + y^2)`` correctly rounded: exact for the integer gradients of WGOH."""
    return np.sqrt(x * x + y * y)


@contextlib.contextmanager
def repeatable_features():
    """Make the global features repeat bit for bit from one process to the next.

    ``cv2.magnitude`` (WGOH's gradient magnitude) differs in the last bit of some pixels
    from one run to the next, which moves global similarities by about 1e-7 and the
    estimates after them by as much; the recorded answers are taken, and compared, with
    the correctly rounded magnitude instead, so that equality can be exact.
    """
    with mock.patch.object(cv2, "magnitude", _magnitude):
        yield


def platform_fingerprint() -> str:
    """A digest of what OpenCV computes here for the operations the cases rest on.

    SIFT and ORB keypoints, resizing and warping differ in their last bits from one CPU (its
    vector instructions) or OpenCV build to another, and a filter step amplifies such bits
    into other estimates. The recorded answers hold where this digest is the one stored with
    them; elsewhere they are re-recorded rather than compared.
    """
    from vloc.workers.core.features.orb import extract_orb
    from vloc.workers.core.sift import extract_sift

    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur((rng.random((480, 640)) * 255).astype(np.uint8), (0, 0), 2.0)
    small = cv2.resize(img, (320, 240), interpolation=cv2.INTER_AREA)
    warped = cv2.warpAffine(small, cv2.getRotationMatrix2D((160.0, 120.0), 17.0, 1.1),
                            (320, 240), flags=cv2.INTER_LINEAR)
    digest = hashlib.sha256()
    for grey in (small, warped):
        sift, orb = extract_sift(grey), extract_orb(grey)
        for arr in (grey, sift.keypoints, sift.descriptors, orb.keypoints, orb.descriptors):
            digest.update(np.ascontiguousarray(arr).tobytes())
    for arr in _numeric_probes(rng):
        digest.update(np.ascontiguousarray(arr).tobytes())
    return digest.hexdigest()[:16]


def _numeric_probes(rng: np.random.Generator) -> list[np.ndarray]:
    """Results of the NumPy operations the filter rests on, whose last bits depend on the
    CPU's vector instructions (BLAS kernels, SIMD transcendental functions, pairwise sums):
    the same OpenCV features with another CPU still move the estimates by 1e-15."""
    a = rng.normal(size=(300, 64))
    b = rng.normal(size=(64, 50))
    w = rng.random(300)
    x = rng.normal(scale=30.0, size=1000)
    sq = a[:64] @ a[:64].T + 64.0 * np.eye(64)
    return [a @ b, (a.astype(np.float32) @ b.astype(np.float32)), np.einsum("ij,i->j", a, w),
            np.cov(a[:, :2].T, aweights=w), np.linalg.solve(sq, b), np.linalg.eigh(sq)[0],
            np.linalg.svd(a[:20, :6])[1], np.exp(x), np.log(np.abs(x) + 1.0),
            np.sin(x), np.arctan2(x, x[::-1]), np.hypot(x, x[::-1]), np.sum(x), w @ a]


def case_name(world: str, mode: str, params: dict) -> str:
    return f"{world}/{mode}/{json.dumps(params, sort_keys=True)}"


def estimate_record(e) -> list:
    """The parts of an estimate that must not change (not the timing)."""
    return [e.x, e.y, e.sigma_x, e.sigma_y, list(e.cov), e.feature, e.next_feature,
            str(e.status), e.n_particles, e.best_image]


def run_case(experiment, mode: str, params: dict, frames: int | None = None) -> list[list]:
    """Estimates of one localiser over the experiment's queries, restored half way."""
    queries = experiment.queries[:frames]
    loc = make_localiser(mode, experiment.map_data, params, seed=SEED)
    out = []
    for i, q in enumerate(queries):
        if i == len(queries) // 2:
            blob = loc.get_state()
            loc = make_localiser(mode, experiment.map_data, params, seed=SEED + 1000)
            loc.set_state(blob)
        out.append(estimate_record(loc.step(q)))
    return out


def synthetic_experiment(world: str, folder: Path):
    kind, seed, frames, route = WORLDS[world]
    path = folder / world
    if not (path / "world.json").is_file():
        generate_world(path, kind=kind, seed=seed, passes=("sunny", "cloudy"), frames=frames,
                       route_length=route, overwrite=True)
    return load_experiment(path, rule="pass", map_pass=1, query_pass=2)


def seneca_experiment(folder: Path):
    return load_experiment(folder, rule="pass", map_pass=1, query_pass=2)


BAD_PARAMS: list[tuple[str, dict]] = [
    ("hybrid", {"n_particles": 0}), ("hybrid", {"n_particles": 2.5}),
    ("sift", {"pull": 1.5}), ("global", {"motion_sigma": float("nan")}),
    ("hybrid", {"nonsense": 1}), ("hybrid", {"config": "nope"}),
    ("hybrid", {"sift_verify": "maybe"}), ("hybrid", {"global_features": ["colour"]}),
    ("hybrid", {"global_features": []}), ("hybrid", {"global_measure": "cosine"}),
    ("hybrid", {"sift_ratio": 1.0}), ("hybrid", {"sift_ratio": -0.1}),
    ("hybrid", {"global_trust": True}), ("hybrid", {"global_trust_level": 1.5}),
    ("hybrid", {"global_check": 1001}), ("hybrid", {"speed": "fast"}),
    ("hybrid", {"speed": 0}), ("hybrid", {"distance_scale": -1.0}),
    ("hybrid", {"replace_fraction": 1.0}), ("hybrid", {"resampler": "stratified"}),
    ("hybrid", {"replacement": "gaussian"}), ("hybrid", {"sift_reduce": "all"}),
    ("hybrid", {"seed": -1}), ("retrieval", {"feature": "colour"}),
    ("retrieval", {"measure": "cosine"}), ("retrieval", {"k": 3}),
    ("hierarchical", {"k": 0}), ("hierarchical", {"sift_ratio": 1.0}),
    ("hierarchical", {"sift_verify": "maybe"}), ("hierarchical", {"feature": "wgoh"}),
    ("teleport", {}),
]
"""Parameters the HTTP API and the command line refuse, each with its message."""


def validated_params() -> dict:
    """What :func:`validate_params` returns for every case, and its error for bad ones."""
    from vloc.workers.core.localisers import validate_params

    good = {f"{mode}/{json.dumps(p, sort_keys=True)}": validate_params(mode, {**p, "seed": 1})
            for mode, p in CASES + [("hybrid", {}), ("global", {"config": "weiss2008"})]}
    bad = {}
    for mode, p in BAD_PARAMS:
        try:
            validate_params(mode, p)
        except ValueError as exc:
            bad[f"{mode}/{json.dumps(p, sort_keys=True)}"] = str(exc)
    return {"valid": good, "refused": bad}


def record_all(experiments: dict, frames: dict[str, int | None]) -> dict[str, list[list]]:
    return {case_name(w, mode, p): run_case(exp, mode, p, frames.get(w))
            for w, exp in experiments.items() for mode, p in CASES}


def answers_file(platform: str) -> Path:
    return GOLDEN_DIR / f"{platform}.json"


def recorded_platforms() -> list[str]:
    return sorted(p.stem for p in GOLDEN_DIR.glob("*.json") if p != PARAMS_FILE)


def load_answers(platform: str) -> dict[str, list[list]] | None:
    """The estimates recorded on ``platform``, or None where none were."""
    path = answers_file(platform)
    return json.loads(path.read_text(encoding="utf-8")) if path.is_file() else None


THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
"""Variables that pin the BLAS's threads: recording refuses to run under them."""


def main() -> None:
    from tests.conftest import shared_dir

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seneca", action="store_true", help="also the seneca-uav frames")
    parser.add_argument("--add-platform", action="store_true",
                        help="keep the other platforms' answers (only when the code is the one "
                             "they were recorded with)")
    args = parser.parse_args()
    pinned = [name for name in THREAD_VARIABLES if name in os.environ]
    if pinned:
        # the fingerprint covers BLAS results, whose last bits depend on the thread count
        parser.error(f"{', '.join(pinned)} set: the tests run with the BLAS's own thread "
                     "count, and answers recorded with another belong to another platform "
                     "fingerprint; run this without them")
    platform = platform_fingerprint()
    stored = load_answers(platform) or {}
    with tempfile.TemporaryDirectory() as tmp, repeatable_features():
        exps = {w: synthetic_experiment(w, Path(tmp)) for w in WORLDS}
        if args.seneca:
            exps["seneca"] = seneca_experiment(shared_dir() / "datasets" / "seneca-uav")
        stored.update(record_all(exps, {"seneca": SENECA_FRAMES}))
    GOLDEN_DIR.mkdir(exist_ok=True)
    PARAMS_FILE.write_text(json.dumps(validated_params(), sort_keys=True, indent=1) + "\n",
                           encoding="utf-8")
    write_answers(answers_file(platform), stored)
    print(f"{len(stored)} cases written to {answers_file(platform)}")
    if not args.add_platform:
        for other in recorded_platforms():
            if other != platform:
                answers_file(other).unlink()
                print(f"removed the answers recorded on {other}: record them there again")


def write_answers(path: Path, stored: dict) -> None:
    """One case per line, keys sorted: a changed case shows as one changed line."""
    lines = [f"{json.dumps(k)}: {json.dumps(stored[k], sort_keys=True)}" for k in sorted(stored)]
    path.write_text("{\n" + ",\n".join(lines) + "\n}\n", encoding="utf-8")


def first_difference(want: list[list], got: list[list]) -> str:
    for i, (a, b) in enumerate(zip(want, got, strict=False)):
        if a != b:
            return f"step {i}: recorded {a}, now {b}"
    return f"{len(want)} steps recorded, {len(got)} now"


if __name__ == "__main__":
    main()
