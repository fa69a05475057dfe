"""The hybrid switching rule (Weiss et al. 2008, IV-B) alone, on hand-made evidence."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from vloc.workers.core.pf.config import CONFIGS, WEISS2008
from vloc.workers.core.pf.switching import (
    GLOBAL,
    SIFT,
    TRUST_RATE,
    StepEvidence,
    SwitchState,
    checks_global,
    decide,
    gap_to_best,
    judges_trust,
    start,
    thresholds,
)

PAPER = WEISS2008.switching
AT_4M = (5.5, 7.0)


def _next(used, spread, rule=PAPER, state=SwitchState(), **kw):
    return decide(rule, state, StepEvidence(used, spread, **kw), thresholds=AT_4M,
                  agree_radius=10.0).next


def test_first_step_is_sift_unless_pinned():
    assert start() == SIFT
    assert start(GLOBAL) == GLOBAL and start(SIFT) == SIFT


@pytest.mark.parametrize(("spread", "want"), [(6.99, GLOBAL), (7.0, SIFT), (20.0, SIFT),
                                              (5.6, GLOBAL)])
def test_after_sift_global_only_below_d_sift(spread, want):
    assert _next(SIFT, spread) == want


@pytest.mark.parametrize(("spread", "want"), [(5.5, GLOBAL), (5.51, SIFT), (1.0, GLOBAL),
                                              (6.9, SIFT)])
def test_after_global_sift_once_above_d_global(spread, want):
    assert _next(GLOBAL, spread) == want


def test_between_the_thresholds_the_rule_keeps_the_current_type():
    # the hysteresis of IV-B: d_global < spread < d_sift
    assert _next(SIFT, 6.0) == GLOBAL and _next(GLOBAL, 6.0) == SIFT
    assert _next(GLOBAL, 5.0) == GLOBAL and _next(SIFT, 8.0) == SIFT


def test_thresholds_scale_with_the_motion_sigma():
    k = np.hypot(4.0, 35.0) / 4.0
    assert thresholds(PAPER, np.hypot(4.0, 35.0)) == pytest.approx((5.5 * k, 7.0 * k))
    assert thresholds(PAPER, 4.0) == (5.5, 7.0)


def test_global_check_sends_a_confident_cloud_back_to_sift_when_global_disagrees():
    rule = WEISS2008.with_params(global_check=3).switching
    assert _next(GLOBAL, 2.0, rule, global_gap=5.0) == GLOBAL
    assert _next(GLOBAL, 2.0, rule, global_gap=5.6) == SIFT
    assert _next(GLOBAL, 2.0, rule) == GLOBAL  # not checked
    assert checks_global(rule, GLOBAL) and not checks_global(rule, SIFT)
    assert not checks_global(rule, GLOBAL, pinned=GLOBAL)
    assert not checks_global(PAPER, GLOBAL)


def test_trust_is_a_running_share_of_agreement_on_sift_steps():
    rule = CONFIGS["default"].switching  # trust in the best global image, level 0.95
    state = SwitchState(SIFT, 0.0)
    trusts = []
    for _ in range(9):
        state = decide(rule, state, StepEvidence(SIFT, 1.0, trust_gap=2.0),
                       thresholds=AT_4M, agree_radius=10.0)
        trusts.append(state.trust)
    want = [1.0 - (1.0 - TRUST_RATE) ** n for n in range(1, 10)]
    np.testing.assert_allclose(trusts, want, rtol=1e-12)
    # vetoed while below the level: eight agreeing steps are not enough, nine are
    assert trusts[7] < 0.95 <= trusts[8] and state.next == GLOBAL
    disagree = decide(rule, state, StepEvidence(SIFT, 1.0, trust_gap=10.5), thresholds=AT_4M,
                      agree_radius=10.0)
    assert disagree.trust == pytest.approx((1 - TRUST_RATE) * state.trust)
    assert disagree.next == SIFT


def test_low_trust_vetoes_global_even_after_a_global_step():
    rule = CONFIGS["default"].switching
    got = decide(rule, SwitchState(GLOBAL, 0.5), StepEvidence(GLOBAL, 1.0), thresholds=AT_4M,
                 agree_radius=10.0)
    assert got == SwitchState(SIFT, 0.5)  # a global step leaves the trust alone
    got = decide(rule, SwitchState(GLOBAL, 0.96), StepEvidence(GLOBAL, 1.0), thresholds=AT_4M,
                 agree_radius=10.0)
    assert got == SwitchState(GLOBAL, 0.96)


def test_without_trust_the_paper_rule_alone_decides():
    got = decide(PAPER, SwitchState(SIFT, 0.0), StepEvidence(SIFT, 1.0, trust_gap=100.0),
                 thresholds=AT_4M, agree_radius=10.0)
    assert got == SwitchState(GLOBAL, 0.0)
    assert not judges_trust(PAPER, SIFT)
    default = CONFIGS["default"].switching
    assert judges_trust(default, SIFT) and not judges_trust(default, GLOBAL)
    assert not judges_trust(default, SIFT, pinned=SIFT)


@pytest.mark.parametrize("pinned", [SIFT, GLOBAL])
def test_pinned_filters_keep_their_type_and_their_trust(pinned):
    rule = CONFIGS["default"].switching
    for used, spread in [(SIFT, 1.0), (SIFT, 50.0), (GLOBAL, 1.0), (GLOBAL, 50.0)]:
        got = decide(rule, SwitchState(pinned, 0.25), StepEvidence(used, spread, trust_gap=0.0),
                     thresholds=AT_4M, agree_radius=10.0, pinned=pinned)
        assert got == SwitchState(pinned, 0.25)


def test_gap_to_best_against_a_hand_computed_case():
    positions = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 30.0], [3.0, 4.0]])
    scores = np.array([0.1, 0.9, 0.8, 0.8])
    point = np.array([0.0, 0.0])
    assert gap_to_best(positions, scores, 1, point) == 10.0
    assert gap_to_best(positions, scores, 2, point) == 10.0  # ties: earlier position first
    assert gap_to_best(positions, scores, 3, point) == 5.0
    assert gap_to_best(positions, scores, 4, point) == 0.0


def _registered_rule(misses):
    return replace(CONFIGS["default"].switching, global_trust=0, global_misses=misses)


def test_misses_of_the_global_registration_send_the_cloud_to_sift():
    rule = _registered_rule(1)
    s = SwitchState(GLOBAL)
    s = decide(rule, s, StepEvidence(GLOBAL, 1.0, registered=False), thresholds=AT_4M,
               agree_radius=10.0)
    assert (s.next, s.misses) == (GLOBAL, 1)  # one miss is allowed
    s = decide(rule, s, StepEvidence(GLOBAL, 1.0, registered=False), thresholds=AT_4M,
               agree_radius=10.0)
    assert (s.next, s.misses) == (SIFT, 2)
    # a fix clears the count; so does a SIFT step
    assert decide(rule, s, StepEvidence(GLOBAL, 1.0, registered=True), thresholds=AT_4M,
                  agree_radius=10.0).misses == 0
    assert decide(rule, s, StepEvidence(SIFT, 1.0), thresholds=AT_4M,
                  agree_radius=10.0).misses == 0
    # without the rule (the paper), misses are counted but decide nothing
    off = _registered_rule(None)
    s = SwitchState(GLOBAL, misses=5)
    assert decide(off, s, StepEvidence(GLOBAL, 1.0, registered=False), thresholds=AT_4M,
                  agree_radius=10.0).next == GLOBAL


@pytest.mark.parametrize("spread", [1.0, 7.0, 50.0])
def test_where_global_steps_escalate_a_sift_step_is_followed_by_a_global_one(spread):
    """A global step that registers the frame, or is taken back for SIFT where it finds no
    fix, can follow a SIFT step however spread the cloud; elsewhere the spread decides."""
    rule = _registered_rule(None)
    for trust in (0.0, 1.0):
        got = decide(rule, SwitchState(SIFT, trust), StepEvidence(SIFT, spread),
                     thresholds=AT_4M, agree_radius=10.0, escalates=True)
        assert got.next == GLOBAL
    assert _next(SIFT, spread, rule) == (GLOBAL if spread < AT_4M[1] else SIFT)
    # after a global step the spread still decides, and pinned filters keep their type
    assert decide(rule, SwitchState(GLOBAL), StepEvidence(GLOBAL, spread), thresholds=AT_4M,
                  agree_radius=10.0, escalates=True).next \
        == (GLOBAL if spread <= AT_4M[0] else SIFT)
    assert decide(rule, SwitchState(SIFT), StepEvidence(SIFT, spread), thresholds=AT_4M,
                  agree_radius=10.0, pinned=SIFT, escalates=True).next == SIFT
