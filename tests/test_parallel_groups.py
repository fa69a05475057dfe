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


class _Item:
    def __init__(self, nodeid: str, group: str | None = None, slow: bool = False) -> None:
        self.nodeid = nodeid
        self.marks = {"xdist_group": pytest.mark.xdist_group(group).mark if group else None,
                      "slow": pytest.mark.slow.mark if slow else None}

    def get_closest_marker(self, name):
        return self.marks.get(name)


def test_long_groups_are_handed_out_first_and_keep_their_order():
    from tests.conftest import RAY_GROUP, _longest_first

    items = [_Item("a"), _Item("m1", "m"), _Item("r1", RAY_GROUP), _Item("m2", "m", slow=True),
             _Item("b"), _Item("s", slow=True), _Item("r2", RAY_GROUP), _Item("m3", "m")]
    _longest_first(items)
    # a group with one slow test goes first whole, in its own order; then the slow test
    # alone; then Ray's; then the rest as collected
    assert [i.nodeid for i in items] == ["m1", "m2", "m3", "s", "r1", "r2", "a", "b"]
