"""Particle-filter parameters, validated, with the named configurations.

``weiss2008`` is the filter of Weiss et al. 2008 (IV-A, IV-B) unchanged: 300 particles,
Gaussian motion with sigma 4 m per frame plus a pull of 0.2 towards the nearest map image,
power 20 for global similarities, the worst 5 % replaced by uniform particles, thresholds
d_global = 5.5 m and d_SIFT = 7.0 m.

``default`` keeps that structure and adds what measurements on real data (seneca-uav)
showed to help: RANSAC homography verification of SIFT matches, no SIFT reduction, SIFT
similarities to the power 3, ratio 0.7, replacement particles seeded around the best
retrieved map images as well as uniformly, and global steps only while the global
features' best image keeps agreeing with the SIFT estimate (``global_trust``).

The motion noise scales with the time between frames when frames carry capture times
(``speed``, metres per second; ``"auto"`` takes the platform's typical speed from the map's
capture times). The switching thresholds belong to the motion model (Weiss IV-B: "for other
motion models d_global and d_SIFT must be chosen differently"), so they scale with the
motion sigma relative to the paper's 4 m.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace

REFERENCE_SIGMA: float = 4.0
"""Motion sigma (m) the paper's thresholds were chosen for."""

RESAMPLERS = ("multinomial", "systematic")
REPLACEMENTS = ("uniform", "retrieval")
VERIFICATIONS = ("none", "homography", "fundamental")
REDUCTIONS = ("both", "map", "query", "none")


@dataclass(frozen=True)
class FilterConfig:
    """Parameters of the particle filter and the hybrid switching rule.

    Attributes
    ----------
    n_particles : int
        m in Weiss IV-A.
    motion_sigma : float
        Per-axis sigma (m) of the Gaussian motion for one frame when frames carry no
        capture times, and the floor of the time-scaled sigma.
    speed : float, "auto" or None
        Typical platform speed (m/s). With capture times the motion sigma for a gap of
        ``dt`` seconds is ``hypot(motion_sigma, speed * dt)``. ``"auto"``: the map's.
    pull : float
        Fraction of the distance to its nearest map image each particle moves (0.2).
    global_power : float
        Exponent applied to global similarities (20).
    replace_fraction : float
        Share of the worst particles replaced after each step (0.05).
    replacement : {"uniform", "retrieval"}
        Where replacement particles go: uniformly over the map, or half around map images
        drawn by their similarity to the frame and half uniformly.
    d_global, d_sift : float
        Thresholds (m) at ``REFERENCE_SIGMA``; scaled by ``sigma / REFERENCE_SIGMA``.
    distance_scale : float or None
        Length scale (m) of the factor ``exp(-d^2 / 2 s^2)`` that lowers a particle's weight
        with its distance d to its nearest map image; None: twice the map's median spacing.
    global_features : tuple of str
        Global features whose similarities are multiplied (Weiss: WGOH x WGII): histogram
        features or place descriptors (``vlad_orb``, ``bow_orb``, ..., whose vocabulary the
        map trains at build).
    global_measure : str
        Similarity measure for the histogram features ("weiss": normalised intersection).
        Place descriptors are always compared by their cosine.
    sift_ratio : float
        Lowe ratio-test threshold on distances. The paper does not give one; 0.6 is the
        threshold of Lowe's own matching program. At Lowe's often quoted 0.8 about one in
        twenty keypoints of an unrelated image still passes, so with power 1 the weights
        barely separate places: on the robot world (sunny map, cloudy frames) the
        correct image's share was 0.17-0.31 against 0.04-0.09 for images 20-40 m away, and
        SIFT alone left the cloud at a median spread of 8.6 m, above d_SIFT, so the hybrid
        stayed on SIFT for 57 % of the steps. At 0.6 the far images drop to 0-0.007.
    sift_verify : {"none", "homography", "fundamental"}
        Geometric verification: count only RANSAC inliers as matches.
    sift_reduce : {"both", "map", "query", "none"}
        Feature reduction (Weiss III): map images keep the keypoints matching their two
        GPS-nearest map images, a frame those matching the previous frame.
    sift_power : float
        Exponent applied to SIFT similarities (1 in the paper).
    sift_candidates : int
        In a SIFT step, also score the map images the global features rank highest over
        the whole map (a shortlist, as in Li et al.'s hierarchy), so that replacement
        particles can start at places SIFT confirmed. 0: only the particles' images.
    global_check : int
        After a global step, switch to SIFT unless one of the ``global_check`` map images
        most similar to the frame (over the whole map) lies within d_global of the
        estimate: the global features disagreeing with the cloud is a sign of trouble
        that the cloud's own spread cannot show. 0 disables the check (the paper).
    global_trust : int
        Hybrid only: on each SIFT step, check whether one of the ``global_trust`` map
        images the global features rank highest lies within d_global of the SIFT-based
        estimate, and keep a running share of agreement; switch to global features only
        while that share is at least ``global_trust_level``. Global features that fail
        under the current light (dusk, colour casts) are then left alone. 0 disables (the
        paper). ``default`` checks the best image alone: with the best three, chance
        agreement let in global steps that cost seneca-uav 1.2 m of mean error.
    global_trust_level : float
        The running agreement needed before global steps are allowed. 0.95 takes nine
        agreeing SIFT steps in a row from no trust: on seneca-uav, global features that
        agree with SIFT on half or even three quarters of the steps still cost accuracy
        (hybrid median 20.8 m and 16.1 m against SIFT's 12.3 m).
    velocity : bool
        Particles carry a velocity (constant-velocity motion model).
    resampler : {"multinomial", "systematic"}
        Weiss draws m particles at random by weight: multinomial.
    """

    n_particles: int = 300
    motion_sigma: float = 4.0
    speed: float | str | None = "auto"
    pull: float = 0.2
    global_power: float = 20.0
    replace_fraction: float = 0.05
    replacement: str = "uniform"
    d_global: float = 5.5
    d_sift: float = 7.0
    distance_scale: float | None = None
    global_features: tuple[str, ...] = ("wgoh", "wgii")
    global_measure: str = "weiss"
    sift_ratio: float = 0.6
    sift_verify: str = "none"
    sift_reduce: str = "both"
    sift_power: float = 1.0
    global_check: int = 0
    sift_candidates: int = 0
    global_trust: int = 0
    global_trust_level: float = 0.95
    velocity: bool = False
    resampler: str = "multinomial"

    def __post_init__(self) -> None:
        _check(self)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["global_features"] = list(self.global_features)
        return d


def _check(c: FilterConfig) -> None:
    def positive(name: str, value: float) -> None:
        if not isinstance(value, int | float) or not math.isfinite(value) or value <= 0:
            raise ValueError(f"{name} must be a positive number, got {value!r}")

    if not isinstance(c.n_particles, int) or not 1 <= c.n_particles <= 100_000:
        raise ValueError(f"n_particles must be an integer in 1..100000, got {c.n_particles!r}")
    for name in ("motion_sigma", "global_power", "d_global", "d_sift", "sift_ratio",
                 "sift_power"):
        positive(name, getattr(c, name))
    for name in ("global_check", "sift_candidates", "global_trust"):
        value = getattr(c, name)
        if not isinstance(value, int) or isinstance(value, bool) or not 0 <= value <= 1000:
            raise ValueError(f"{name} must be an integer in 0..1000, got {value!r}")
    if c.distance_scale is not None:
        positive("distance_scale", c.distance_scale)
    if c.speed is not None and c.speed != "auto":
        positive("speed", c.speed)
    if not 0.0 <= c.global_trust_level <= 1.0:
        raise ValueError(f"global_trust_level must be in [0, 1], got {c.global_trust_level!r}")
    if not 0.0 <= c.pull < 1.0:
        raise ValueError(f"pull must be in [0, 1), got {c.pull!r}")
    if not 0.0 <= c.replace_fraction < 1.0:
        raise ValueError(f"replace_fraction must be in [0, 1), got {c.replace_fraction!r}")
    if c.sift_ratio >= 1.0:
        raise ValueError(f"sift_ratio must be below 1, got {c.sift_ratio!r}")
    for name, value, allowed in (("replacement", c.replacement, REPLACEMENTS),
                                 ("sift_verify", c.sift_verify, VERIFICATIONS),
                                 ("sift_reduce", c.sift_reduce, REDUCTIONS),
                                 ("resampler", c.resampler, RESAMPLERS)):
        if value not in allowed:
            raise ValueError(f"{name} must be one of {', '.join(allowed)}; got {value!r}")
    if not c.global_features:
        raise ValueError("global_features must name at least one feature")
    from ..features import ALL_FEATURE_NAMES
    from ..similarity import MEASURES
    for name in c.global_features:
        if name not in ALL_FEATURE_NAMES:
            raise ValueError(f"unknown global feature {name!r}; valid: "
                             f"{', '.join(ALL_FEATURE_NAMES)}")
    if c.global_measure not in MEASURES:
        raise ValueError(f"unknown measure {c.global_measure!r}; valid: {', '.join(MEASURES)}")


CONFIGS: dict[str, FilterConfig] = {
    "weiss2008": FilterConfig(),
    "default": FilterConfig(replacement="retrieval", sift_verify="homography", sift_reduce="none",
                            sift_power=3.0, sift_ratio=0.7, global_trust=1),
}


def config_from_params(params: dict | None = None) -> FilterConfig:
    """Build a config from a named base (``params["config"]``) and overrides.

    Raises
    ------
    ValueError
        Unknown config name, unknown parameter, or a parameter out of range.
    """
    params = dict(params or {})
    base_name = params.pop("config", "default")
    if base_name not in CONFIGS:
        raise ValueError(f"unknown config {base_name!r}; valid: {', '.join(CONFIGS)}")
    known = {f.name for f in fields(FilterConfig)}
    unknown = sorted(set(params) - known)
    if unknown:
        raise ValueError(f"unknown parameter(s) {', '.join(unknown)}; valid: {', '.join(sorted(known))}")
    if "global_features" in params:
        gf = params["global_features"]
        params["global_features"] = (gf,) if isinstance(gf, str) else tuple(gf)
    return replace(CONFIGS[base_name], **params)
