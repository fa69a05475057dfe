"""Every localiser mode and configuration gives exactly the recorded estimates.

The answers were recorded with :mod:`tests.core.golden` before the filter's code was
restructured; a restructuring must not move a single bit of them. Equality is exact: with
:func:`tests.core.golden.repeatable_features` the same code on the same inputs and seeds gives
the same floating-point results from one run to the next.
"""

from __future__ import annotations

import json

import pytest

from tests.core import golden


@pytest.fixture(scope="module")
def stored():
    here = golden.platform_fingerprint()
    answers = golden.load_answers(here)
    if answers is None:
        pytest.skip(f"no estimates recorded on a platform that computes features like this one "
                    f"(fingerprint {here}; recorded: {', '.join(golden.recorded_platforms())}): "
                    f"record them with `python -m tests.core.golden --seneca --add-platform` "
                    f"using the code the others were recorded with")
    return answers


@pytest.fixture(scope="module", autouse=True)
def repeatable():
    with golden.repeatable_features():
        yield


@pytest.fixture(scope="module")
def synthetic(repeatable, stored, tmp_path_factory):
    folder = tmp_path_factory.mktemp("worlds")
    return {w: golden.synthetic_experiment(w, folder) for w in golden.WORLDS}


@pytest.fixture(scope="module")
def seneca(repeatable, stored, seneca_dir):
    return golden.seneca_experiment(seneca_dir)


def _check(stored, experiment, world: str, mode: str, params: dict,
           frames: int | None = None):
    name = golden.case_name(world, mode, params)
    want = stored[name]
    got = golden.run_case(experiment, mode, params, frames)
    assert got == want, f"{name}: {golden.first_difference(want, got)}"


@pytest.mark.parametrize("world", sorted(golden.WORLDS))
@pytest.mark.parametrize(("mode", "params"), golden.CASES,
                         ids=[golden.case_name("", m, p)[1:] for m, p in golden.CASES])
def test_synthetic_world_estimates_are_unchanged(stored, synthetic, world, mode, params):
    _check(stored, synthetic[world], world, mode, params)


@pytest.mark.slow
@pytest.mark.dataset
@pytest.mark.parametrize(("mode", "params"), golden.CASES,
                         ids=[golden.case_name("", m, p)[1:] for m, p in golden.CASES])
def test_seneca_estimates_are_unchanged(stored, seneca, mode, params):
    _check(stored, seneca, "seneca", mode, params, golden.SENECA_FRAMES)


def test_the_platform_fingerprint_is_repeatable():
    assert golden.platform_fingerprint() == golden.platform_fingerprint()


def test_validated_parameters_and_refusals_are_unchanged():
    recorded = json.loads(golden.PARAMS_FILE.read_text(encoding="utf-8"))
    assert golden.validated_params() == recorded


def test_every_platform_holds_every_case():
    """A platform's answers cover the same cases as the others' (none left from an old set)."""
    names = {golden.case_name(w, m, p) for w in golden.WORLDS for m, p in golden.CASES}
    names |= {golden.case_name("seneca", m, p) for m, p in golden.CASES}
    platforms = golden.recorded_platforms()
    assert platforms
    for platform in platforms:
        assert set(golden.load_answers(platform)) == names, platform


def test_recording_refuses_a_pinned_blas(monkeypatch):
    """One BLAS thread gives the platform another fingerprint than the tests see: recording
    under it would leave the tests nothing to compare with."""
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    monkeypatch.setattr("sys.argv", ["golden", "--seneca"])
    with pytest.raises(SystemExit) as stop:
        golden.main()
    assert stop.value.code == 2
