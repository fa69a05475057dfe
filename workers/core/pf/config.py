"""Particle-filter parameters in parts, validated, with the named configurations.

A :class:`FilterConfig` holds the particle count and resampler and one part per piece of
the filter: :class:`MotionConfig` (Weiss IV-A step 2), :class:`MeasurementConfig` (step 3),
:class:`SiftConfig` (section III), :class:`SwitchingConfig` (IV-B) and :class:`ResetConfig`
(step 6). The parts have no defaults: a configuration states every value.

``weiss2008`` is the filter of Weiss et al. 2008 unchanged (:data:`WEISS2008`, every value
with its source). ``default`` is ``weiss2008`` with the overrides that measurements on real
data (seneca-uav) showed to help (:data:`DEFAULT_OVERRIDES`).

Sessions and the command line name parameters by flat keys (``n_particles``, ``sift_ratio``,
``global_features`` ...): :data:`~.params.PARAMS` declares each: its part and field, the values it
takes and what it means (:mod:`.params`),
:func:`config_from_params` builds a configuration from a named base and flat overrides, and
:meth:`FilterConfig.to_params` gives the flat view back.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from .params import (
    PARAMS,
    POINT_ESTIMATES,
    REDUCTIONS,
    REPLACEMENTS,
    RESAMPLERS,
    VERIFICATIONS,
    check_params,
)


@dataclass(frozen=True)
class MotionConfig:
    """How particles move between frames (:mod:`.motion`).

    Attributes
    ----------
    sigma : float
        Per-axis sigma (m) of the Gaussian motion for one frame when frames carry no
        capture times, and the floor of the time-scaled sigma.
    speed : float, "auto" or None
        Typical platform speed (m/s). With capture times the motion sigma for a gap of
        ``dt`` seconds is ``hypot(sigma, speed * dt)``. ``"auto"``: the map's.
    pull : float
        Fraction of the distance to its nearest map image each particle moves.
    velocity : bool
        Particles carry a velocity (constant-velocity motion model).
    drift : bool
        The filter tracks the platform's velocity from its metric fixes (the displacement
        between consecutive steps that had one) and moves the whole cloud by it, with half
        the position noise. Not in the paper, whose robot moves 0.6 m a frame; a UAV flying
        a survey line moves 30 m, and a random walk loses that between fixes.
    """

    sigma: float
    speed: float | str | None
    pull: float
    velocity: bool
    drift: bool


@dataclass(frozen=True)
class MeasurementConfig:
    """How an image similarity becomes a particle's likelihood (:mod:`.measurement`).

    Attributes
    ----------
    global_features : tuple of str
        Global features whose similarities are multiplied (Weiss: WGOH x WGII): histogram
        features or place descriptors (``vlad_orb``, ``bow_orb``, ..., whose vocabulary the
        map trains at build).
    global_measure : str
        Similarity measure for the histogram features ("weiss": normalised intersection).
        Place descriptors are always compared by their cosine.
    global_power, sift_power : float
        Exponents applied to global and to SIFT similarities.
    distance_scale : float or None
        Length scale (m) of the factor ``exp(-d^2 / 2 s^2)`` that lowers a particle's weight
        with its distance d to its nearest map image; None: from the map's spacing.
    """

    global_features: tuple[str, ...]
    global_measure: str
    global_power: float
    sift_power: float
    distance_scale: float | None


@dataclass(frozen=True)
class SiftConfig:
    """SIFT matching in the filter's SIFT steps.

    Attributes
    ----------
    ratio : float
        Lowe ratio-test threshold on distances. The paper does not give one; 0.6 is the
        threshold of Lowe's own matching program. At Lowe's often quoted 0.8 about one in
        twenty keypoints of an unrelated image still passes, so with power 1 the weights
        barely separate places: on the robot world (sunny map, cloudy frames) the
        correct image's share was 0.17-0.31 against 0.04-0.09 for images 20-40 m away, and
        SIFT alone left the cloud at a median spread of 8.6 m, above d_SIFT, so the hybrid
        stayed on SIFT for 57 % of the steps. At 0.6 the far images drop to 0-0.007.
    verify : {"none", "homography", "fundamental"}
        Geometric verification: count only RANSAC inliers as matches.
    reduce : {"both", "map", "query", "none"}
        Feature reduction (Weiss III): map images keep the keypoints matching their two
        GPS-nearest map images, a frame those matching the previous frame.
    candidates : int
        Also score the map images the global features rank highest over the whole map (a
        shortlist, as in Li et al.'s hierarchy), so that replacement particles can start
        at places SIFT confirmed. 0: only the particles' images.
    """

    ratio: float
    verify: str
    reduce: str
    candidates: int


@dataclass(frozen=True)
class SwitchingConfig:
    """The hybrid rule (:mod:`.switching`).

    Attributes
    ----------
    d_global, d_sift : float
        Thresholds (m) at the paper's motion sigma; scaled with the motion sigma.
    global_check : int
        After a global step, switch to SIFT unless one of the ``global_check`` map images
        most similar to the frame (over the whole map) lies within d_global of the
        estimate. 0 disables the check (the paper).
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
    global_misses : int or None
        With ``refine_global``: after more than this many global steps in a row without a
        registered fix that agrees with the cloud, switch to SIFT. None disables (the
        paper).
    escalate : bool
        With ``refine_global``: a global step that finds no such fix, beyond the
        ``global_misses`` in a row allowed, is taken back and the frame is localised with
        SIFT instead, so no run of frames goes without a measurement that can place them.
        Not in the paper.
    """

    d_global: float
    d_sift: float
    global_check: int
    global_trust: int
    global_trust_level: float
    global_misses: int | None
    escalate: bool


@dataclass(frozen=True)
class ResetConfig:
    """Replacement of the worst particles after each step (Weiss IV-A step 6).

    Attributes
    ----------
    fraction : float
        Share of the worst particles replaced.
    replacement : {"uniform", "retrieval"}
        Where new particles go: uniformly over the map, or half around map images drawn
        by their similarity to the frame (sensor resetting) and half uniformly.
    """

    fraction: float
    replacement: str


@dataclass(frozen=True)
class RefineConfig:
    """Metric refinement (:mod:`workers.core.localisers.refine`): not in the paper.

    Attributes
    ----------
    enabled : bool
        Solve each SIFT step's camera pose against the best map images (camera geometry
        where the map has it, a match-weighted position between the best images where it
        does not) and fuse it as a position measurement.
    outlier : float
        Probability that a refined position is wrong: the floor of its likelihood.
    inject : float
        Share of the particles drawn around a refined position before weighting.
    on_global : bool
        Also register global steps, with ORB against the map's ORB ground points (maps
        with camera geometry only), as the cheap metric anchor of the hybrid.
    global_inliers : int
        Fewest pose inliers for a global step's fix to count.
    gate : float
        A global step's fix counts only within this many spreads of the predicted cloud
        (and at least the agreement radius, one map spacing) of its mean.
    sift_fallback : bool
        When a global step's ORB registration finds no fix, register the frame with SIFT
        against the same map images before giving the step up (the step then counts as a
        SIFT step): the global features have already said where to look, so SIFT verifies
        two or three images instead of scoring every image under the cloud.
    """

    enabled: bool
    outlier: float
    inject: float
    on_global: bool
    global_inliers: int
    gate: float
    sift_fallback: bool


@dataclass(frozen=True)
class FilterConfig:
    """Parameters of the particle filter and the hybrid switching rule.

    Attributes
    ----------
    n_particles : int
        m in Weiss IV-A.
    resampler : {"multinomial", "systematic"}
    point_estimate : {"mean", "cluster"}
        The position an estimate reports: the weighted mean of the whole cloud (IV-A step
        4), or that of its heaviest cluster where it holds most of the weight
        (:func:`.clusters.heaviest_cluster`; nav2's AMCL reports its heaviest cluster),
        the switching rule and the tracking status then judging that cluster's spread.
        Either way the covariance reported is the whole cloud's about the position.
    motion, measurement, sift, switching, reset, refine : the parts
    """

    n_particles: int
    resampler: str
    point_estimate: str
    motion: MotionConfig
    measurement: MeasurementConfig
    sift: SiftConfig
    switching: SwitchingConfig
    reset: ResetConfig
    refine: RefineConfig

    def __post_init__(self) -> None:
        check_params(self.to_params())

    def to_params(self) -> dict:
        """The flat parameters (keys of :data:`PARAMS`, in its order), JSON-ready."""
        out = {}
        for key, param in PARAMS.items():
            part, name = param.part, param.field
            value = getattr(self if part is None else getattr(self, part), name)
            out[key] = list(value) if isinstance(value, tuple) else value
        return out

    def with_params(self, **params) -> FilterConfig:
        """A copy with flat parameters replaced (unknown keys are a ``TypeError``)."""
        top: dict = {}
        parts: dict[str, dict] = {}
        for key, value in params.items():
            part, name = PARAMS[key].part, PARAMS[key].field
            if part is None:
                top[name] = value
            else:
                parts.setdefault(part, {})[name] = value
        for part, changes in parts.items():
            top[part] = replace(getattr(self, part), **changes)
        return replace(self, **top)


WEISS2008 = FilterConfig(
    n_particles=300,  # IV-A: m = 300
    resampler="multinomial",  # IV-A step 1: "randomly draw m particles according to the weights"
    point_estimate="mean",  # IV-A step 4: the weighted mean
    motion=MotionConfig(
        sigma=4.0,  # IV-A step 2: Gaussian, sigma 4 m
        speed="auto",  # the paper's frames are evenly spaced; timed frames scale the sigma
        pull=0.2,  # IV-A step 2: "move 0.2 of the way to the nearest map image"
        velocity=False,  # IV-A: no velocity in the state
        drift=False),  # not in the paper: off
    measurement=MeasurementConfig(
        global_features=("wgoh", "wgii"),  # II-C: s_WGOH x s_WGII
        global_measure="weiss",  # eq. 1
        global_power=20.0,  # IV-A step 3: global similarities to the 20th power
        sift_power=1.0,  # IV-A step 3: SIFT similarities as they are
        distance_scale=None),  # the paper names no scale: from the map's spacing
    sift=SiftConfig(
        ratio=0.6,  # not in the paper: Lowe's own matching program (see SiftConfig)
        verify="none",  # III: matches counted without geometry
        reduce="both",  # III: map and query feature reduction
        candidates=0),
    switching=SwitchingConfig(
        d_global=5.5, d_sift=7.0,  # IV-B
        global_check=0, global_trust=0,  # not in the paper: off
        global_trust_level=0.95,  # unused while global_trust is 0
        global_misses=None,  # not in the paper: off
        escalate=False),  # not in the paper: off
    reset=ResetConfig(
        fraction=0.05,  # IV-A step 6: the worst 5 %
        replacement="uniform"),  # IV-A step 6: "random particles"
    refine=RefineConfig(
        enabled=False,  # the paper places a frame through its map images only
        outlier=0.01,
        inject=0.2,
        on_global=False,
        global_inliers=15,
        gate=2.0,
        sift_fallback=False),
)
"""The filter of Weiss et al. 2008 (IV-A, IV-B), every value stated."""

DEFAULT_OVERRIDES: dict = {
    "replacement": "retrieval",
    "sift_verify": "homography",
    "sift_reduce": "none",
    "sift_power": 3.0,
    "sift_ratio": 0.7,
    "global_trust": 1,
    "refine": True,
    "global_features": ["vlad_orb"],
    "global_power": 5.0,
    "refine_global": True,
    "refine_sift_fallback": True,
    "escalate": True,
    "point_estimate": "cluster",
}
"""What ``default`` changes in ``weiss2008``: RANSAC homography verification of SIFT matches,
no SIFT reduction, SIFT similarities to the power 3, ratio 0.7, replacement particles seeded
around the best retrieved map images as well as uniformly; metric refinement: each SIFT step
solves the frame's camera pose against the best map images and fuses it as a position, with
a share of the particles drawn around it (seneca-uav mean error 14.4 m without refinement,
about 8 m with it); and the global step on the map's own vocabulary: VLAD over ORB (place
recall@1 on seneca-uav 75 % against 45 % for WGOH x WGII) to the power 5, registered with
ORB where the map has camera geometry, and taken back for SIFT when that finds no fix
agreeing with the cloud: first a SIFT registration against the same images
(``refine_sift_fallback``), then a full SIFT step (``escalate``); where it cannot register
(maps without geometry), global steps are allowed only while the global features' best image keeps agreeing with
the SIFT estimate (``global_trust``). An estimate reports its cloud's heaviest cluster
where that holds most of the weight, and its switching rule judges that cluster's spread
(``point_estimate``): with the global steps' fixes weighing the particles alone, the
hybrid's mean / median error fell from 5.6 / 3.2 to 5.0 / 2.6 m on seneca-uav and from
7.7 / 5.0 to 5.6 / 4.4 m on lewis-uav, SIFT on as many steps as before
(``bench/results/geometry.md``)."""

CONFIGS: dict[str, FilterConfig] = {
    "weiss2008": WEISS2008,
    "default": WEISS2008.with_params(**DEFAULT_OVERRIDES),
}


def config_from_params(params: dict | None = None) -> FilterConfig:
    """Build a config from a named base (``params["config"]``) and flat overrides.

    Raises
    ------
    ValueError
        Unknown config name, unknown parameter, or a parameter out of range.
    """
    params = dict(params or {})
    base_name = params.pop("config", "default")
    if base_name not in CONFIGS:
        raise ValueError(f"unknown config {base_name!r}; valid: {', '.join(CONFIGS)}")
    unknown = sorted(set(params) - set(PARAMS))
    if unknown:
        raise ValueError(f"unknown parameter(s) {', '.join(unknown)}; "
                         f"valid: {', '.join(sorted(PARAMS))}")
    if "global_features" in params:
        gf = params["global_features"]
        params["global_features"] = (gf,) if isinstance(gf, str) else tuple(gf)
    return CONFIGS[base_name].with_params(**params)


__all__ = ["CONFIGS", "DEFAULT_OVERRIDES", "PARAMS", "POINT_ESTIMATES", "REDUCTIONS",
           "REPLACEMENTS", "RESAMPLERS", "VERIFICATIONS", "WEISS2008", "FilterConfig",
           "MeasurementConfig", "MotionConfig", "ResetConfig", "SiftConfig", "SwitchingConfig",
           "config_from_params"]
