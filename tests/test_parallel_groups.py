"""``make test`` runs tests sharing a module-wide fixture on one worker: the group the conftest
gives them must reach pytest-xdist's scheduler intact, or every worker builds its own copy of
each shared server and map (and two Ray clusters compete for two cores)."""

import pytest
from xdist.scheduler.loadgroup import LoadGroupScheduling


@pytest.fixture(scope="module", params=["one[kind]", "two@kinds"])
def shared(request) -> str:
    return request.param


def test_a_test_sharing_a_module_fixture_is_scheduled_by_its_group(request, shared):
    mark = request.node.get_closest_marker("xdist_group")
    assert mark is not None
    group = mark.args[0]
    assert group.startswith(f"{__name__}(shared=")
    # the scheduler's reading of an id tagged with the group gives the group back, whatever
    # characters the fixture's parameter has
    base = request.node.nodeid.removesuffix(f"@{group}")
    assert LoadGroupScheduling._split_scope(None, f"{base}@{group}") == group
    if request.config.getoption("loadgroup", False):  # run by --dist loadgroup
        assert request.node.nodeid == f"{base}@{group}"


def test_a_test_sharing_nothing_goes_wherever_a_worker_is_free(request):
    assert request.node.get_closest_marker("xdist_group") is None
    assert "@" not in request.node.nodeid
