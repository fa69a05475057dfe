"""Which feature type the next filter step uses: the hybrid rule of Weiss et al. 2008, IV-B.

A pure policy: the state it keeps between steps and what one step showed go in, the state
for the next step comes out. The localiser gathers the evidence (the cloud's spread, and the
distances its optional checks need) and calls :func:`decide` once per step.

The rule, in the paper's words and this module's names:

- the first step uses SIFT (:func:`start`);
- after a SIFT step, switch to global features when sigma_x and sigma_y (eq. 2) are both
  below d_SIFT; after a global step, switch to SIFT when either exceeds d_global
  (:func:`decide`, thresholds from :func:`thresholds`);
- "for other motion models d_global and d_SIFT must be chosen differently": both scale with
  the motion sigma relative to the paper's 4 m (:data:`REFERENCE_SIGMA`).

Two checks beyond the paper, off in ``weiss2008``:

- ``global_check``: after a global step, stay global only while one of the best few map
  images under the global features (over the whole map) lies within d_global of the
  estimate (``StepEvidence.global_gap``);
- ``global_trust``: on each SIFT step, record whether the global features' best image agrees
  with the SIFT-based estimate (``StepEvidence.trust_gap`` within ``agree_radius``) in a
  running share (:data:`TRUST_RATE`); while that share is below ``global_trust_level`` the
  rule vetoes global steps.

One check for maps with camera geometry, off in ``weiss2008``:

- ``global_misses``: global steps register the frame with cheap local features
  (``StepEvidence.registered``); after more than ``global_misses`` global steps in a row
  without a fix that agrees with the cloud, the next step is SIFT. The fix, not the cloud's
  spread, shows that the cheap step still knows where it is: on real images the motion
  between frames can be large enough that the spread alone would allow long runs of
  unanchored global steps.
- ``escalate``: such a global step that finds no fix is taken back and the frame gets SIFT.
  Where it is (``decide(escalates=True)``), a SIFT step is followed by a global step however
  spread the cloud: that step either registers the frame or becomes the SIFT step the
  spread asked for, at the cost of one ORB attempt.

The ``global`` and ``sift`` localisers pin the feature type (``pinned``): the rule then
always answers the pinned type and leaves the trust alone.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .config import SwitchingConfig

SIFT = "sift"
GLOBAL = "global"

REFERENCE_SIGMA: float = 4.0
"""Motion sigma (m) the paper's thresholds were chosen for."""

TRUST_RATE: float = 0.3
"""Weight of the newest SIFT step in the running agreement of global features with SIFT."""


@dataclass(frozen=True)
class SwitchState:
    """What the rule carries from one step to the next.

    Attributes
    ----------
    next : {"sift", "global"}
        Feature type of the next step.
    trust : float
        Running share of SIFT steps on which the global features agreed, in [0, 1].
    misses : int
        Global steps in a row whose registration gave no usable fix.
    """

    next: str = SIFT
    trust: float = 0.0
    misses: int = 0


@dataclass(frozen=True)
class StepEvidence:
    """What one filter step showed, as far as the rule needs it.

    Attributes
    ----------
    used : {"sift", "global"}
        Feature type of the step.
    spread : float
        ``max(sigma_x, sigma_y)`` of the weighted cloud (Weiss eq. 2), metres.
    global_gap : float or None
        Global steps under ``global_check``: distance (m) from the estimate to the nearest
        of the ``global_check`` best map images; None where not checked.
    trust_gap : float or None
        SIFT steps under ``global_trust``: distance (m) from the estimate to the nearest of
        the ``global_trust`` best map images under the global features; None where not
        judged.
    registered : bool or None
        Global steps that tried to register the frame: whether a fix was found and agreed
        with the cloud; None where no registration was tried.
    """

    used: str
    spread: float
    global_gap: float | None = None
    trust_gap: float | None = None
    registered: bool | None = None


def start(pinned: str | None = None) -> str:
    """Feature type of a filter's first step: SIFT (IV-B), or the pinned type."""
    return SIFT if pinned is None else pinned


def thresholds(rule: SwitchingConfig, motion_sigma: float) -> tuple[float, float]:
    """``(d_global, d_sift)`` scaled to a motion sigma (m) between frames a nominal gap apart.

    The nominal gap, not the last one: after a long gap the cloud is spread because the
    platform could be anywhere, and that is exactly when SIFT is needed.
    """
    k = motion_sigma / REFERENCE_SIGMA
    return rule.d_global * k, rule.d_sift * k


def checks_global(rule: SwitchingConfig, used: str, pinned: str | None = None) -> bool:
    """Whether this step's evidence needs ``global_gap``."""
    return pinned is None and rule.global_check > 0 and used == GLOBAL


def judges_trust(rule: SwitchingConfig, used: str, pinned: str | None = None) -> bool:
    """Whether this step's evidence needs ``trust_gap``."""
    return pinned is None and rule.global_trust > 0 and used == SIFT


def gap_to_best(positions: np.ndarray, scores: np.ndarray, k: int, point: np.ndarray) -> float:
    """Distance from ``point`` to the nearest of the ``k`` best-scoring positions.

    Parameters
    ----------
    positions : (n, 2) float ndarray
    scores : (n,) float ndarray
        Higher is better; ties keep the order of ``positions``.
    k : int
    point : (2,) float ndarray
    """
    top = np.argsort(-scores, kind="stable")[:k]
    return float(np.min(np.linalg.norm(positions[top] - point, axis=1)))


def decide(rule: SwitchingConfig, state: SwitchState, evidence: StepEvidence, *,
           thresholds: tuple[float, float], agree_radius: float,
           pinned: str | None = None, escalates: bool = False) -> SwitchState:
    """The state for the next step.

    Parameters
    ----------
    rule : SwitchingConfig
    state : SwitchState
        The state the step just taken started from.
    evidence : StepEvidence
    thresholds : (float, float)
        ``(d_global, d_sift)`` in metres, from :func:`thresholds`.
    agree_radius : float
        Largest ``trust_gap`` (m) that counts as agreement.
    pinned : {"sift", "global"} or None
        The feature type of a single-feature filter.
    escalates : bool
        Whether a global step registers the frame and, finding no fix, is taken back for
        SIFT (``escalate`` on a map whose global steps register): a SIFT step is then
        followed by a global step whatever the spread. On seneca-uav (pass 2 on pass 1, 5
        starts) the spread after a failed SIFT registration asked for SIFT again where the
        next frame's ORB registered: SIFT steps 19.7 -> 18.1 % of the frames, the errors
        the same; lewis-uav and the worlds unchanged.
    """
    if pinned is not None:
        return replace(state, next=pinned)
    d_global, d_sift = thresholds
    if evidence.used == SIFT:
        nxt = GLOBAL if evidence.spread < d_sift or escalates else SIFT
    else:
        nxt = SIFT if evidence.spread > d_global else GLOBAL
        if nxt == GLOBAL and evidence.global_gap is not None and evidence.global_gap > d_global:
            # the global features disagree with the cloud: a sign of trouble that the
            # cloud's own spread cannot show
            nxt = SIFT
    misses = state.misses
    if evidence.used == GLOBAL and evidence.registered is not None:
        misses = 0 if evidence.registered else misses + 1
        if rule.global_misses is not None and misses > rule.global_misses:
            nxt = SIFT
    elif evidence.used == SIFT:
        misses = 0
    trust = state.trust
    if rule.global_trust:
        if evidence.trust_gap is not None:
            agree = float(evidence.trust_gap <= agree_radius)
            trust = (1.0 - TRUST_RATE) * trust + TRUST_RATE * agree
        if trust < rule.global_trust_level:
            nxt = SIFT
    return SwitchState(nxt, trust, misses)
