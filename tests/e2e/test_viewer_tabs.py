"""The viewer as a person moves around it: the sign-in form shows the fields of the chosen
credentials, the Replays tab has the plan to itself and gives the view back, the sessions
table counts the frames as they come, and the strip of step kinds says what its colours are.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests.app.conftest import ADMIN_KEY
from tests.e2e.browser import PageLog
from tests.e2e.test_viewer import _marker_at, _page, _send, _session, _sign_in, _wait_live


def _visible(page, selector: str) -> bool:
    """Whether the element takes room on the page (``hidden`` may lose to a CSS rule)."""
    return page.eval_on_selector(selector, "e => e.getClientRects().length > 0")


def test_sign_in_shows_the_session_id_for_a_token_only(browser, live):
    page = _page(browser, live, PageLog())
    assert page.is_checked("input[name=kind][value=admin]")
    assert not _visible(page, "#session-field")
    page.check("input[name=kind][value=session]")
    assert _visible(page, "#session-field")
    page.check("input[name=kind][value=admin]")
    assert not _visible(page, "#session-field")
    page.close()


def _replay_file(tmp_path) -> str:
    """A replay 2 km away from the map, so that its framing differs from the map's."""
    from vloc.workers.core.evaluation.evaluate import ModeSummary, Run
    from vloc.workers.core.evaluation.report import tracks_dict

    n = 20
    truth = np.c_[2000 + 5 * np.arange(n, dtype=float), np.full(n, 2000.0)]
    run = Run(mode="hybrid", config="default", start=0, frames=np.arange(n), truth=truth,
              estimate=truth + 1.0, sigma=np.ones((n, 2)), feature=["sift"] * n,
              status=["tracking"] * n, ms=np.ones(n))
    data = tracks_dict(truth[::4], {"default": {"hybrid": ModeSummary("hybrid", "default",
                                                                       [run])}})
    path = tmp_path / "replay.json"
    path.write_text(json.dumps({"modes": {}} | data))
    return str(path)


def test_replays_hide_the_live_tracks_and_give_the_view_back(browser, live, world, tmp_path):
    log = PageLog()
    page = _page(browser, live, log)
    _sign_in(page, ADMIN_KEY)
    sid, token = _session(live, world)
    page.click("#tab-live")
    page.locator(f"#sessions-table tr[data-session-id='{sid}'] input").check()
    _wait_live(page, sid)
    for q in world["queries"][:3]:
        pose = _send(live, sid, token, q.jpeg)
    _marker_at(page, sid, pose)
    live_parts = "path.vloc-track, path.vloc-marker, path.vloc-ellipse"
    assert page.locator(live_parts).count() == 3
    before = page.evaluate("window.vlocViewer.view()")

    page.click("#tab-replays")
    assert page.locator(live_parts).count() == 0
    page.set_input_files("#replay-file", _replay_file(tmp_path))
    page.locator("path.vloc-replay-track").wait_for(state="attached")
    assert page.evaluate("window.vlocViewer.view()") != before  # framed on the replay

    page.click("#tab-live")
    assert page.locator(live_parts).count() == 3
    assert page.locator("path.vloc-replay-track").count() == 0
    assert page.evaluate("window.vlocViewer.view()") == pytest.approx(before)
    page.click("#tab-maps")
    assert page.evaluate("window.vlocViewer.view()") == pytest.approx(before)
    assert not log.errors, log.errors
    page.close()


def test_the_sessions_table_counts_frames_as_they_come(browser, live, world):
    log = PageLog()
    page = _page(browser, live, log)
    _sign_in(page, ADMIN_KEY)
    sid, token = _session(live, world)
    page.click("#tab-live")
    row = page.locator(f"#sessions-table tr[data-session-id='{sid}']")
    row.locator("input").check()
    _wait_live(page, sid)
    assert row.locator("td").nth(3).inner_text() == "0"
    for q in world["queries"][:4]:
        pose = _send(live, sid, token, q.jpeg)
    _marker_at(page, sid, pose)
    page.wait_for_function(
        "sid => document.querySelector(`#sessions-table tr[data-session-id='${sid}'] "
        "[data-f=frames]`).textContent === '4'", arg=sid)
    assert row.locator("input").is_checked()  # the row was updated, not rebuilt unticked
    assert not log.errors, log.errors
    page.close()


def test_the_step_strip_has_a_legend_in_its_colours(browser, live, world):
    page = _page(browser, live, PageLog())
    _sign_in(page, ADMIN_KEY)
    sid, token = _session(live, world)
    page.click("#tab-live")
    page.locator(f"#sessions-table tr[data-session-id='{sid}'] input").check()
    _wait_live(page, sid)
    _marker_at(page, sid, _send(live, sid, token, world["queries"][0].jpeg))
    card = f".card[data-session-id='{sid}']"
    legend = page.locator(f"{card} .steps-legend")
    assert legend.is_visible()
    assert legend.inner_text().split("\n") == ["global features", "SIFT",
                                               "refined (registered)"]
    colour = "e => getComputedStyle(e).backgroundColor"
    strip = page.eval_on_selector(f"{card} .steps .step-cell", colour)
    kind = page.eval_on_selector(f"{card} .steps .step-cell", "e => e.className.split(' ')[1]")
    assert page.eval_on_selector(f"{card} .steps-legend .{kind}", colour) == strip
    swatches = page.eval_on_selector_all(f"{card} .steps-legend .step-cell",
                                         f"cells => cells.map({colour})")
    assert len(set(swatches)) == 3
    page.close()
