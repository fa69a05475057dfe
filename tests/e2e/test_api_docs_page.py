"""``/docs`` in a real headless Chromium with no way out of the machine.

The page must render the service's own description (OpenAPI 3.1): every operation listed,
the security schemes offered by "Authorize", and a request made with the key entered there
answered 200. Every request to another host is refused inside the browser, so a page that
needs a CDN fails here.
"""

from __future__ import annotations

import httpx
import pytest

from tests.app.conftest import ADMIN_KEY
from tests.e2e.browser import PageLog

TIMEOUT_MS = 20_000
METHODS = ("get", "put", "post", "delete", "patch")


@pytest.fixture
def page(browser, live):
    """``/docs`` loaded offline: requests to any other origin are aborted (and recorded)."""
    log = PageLog()
    outside: list[str] = []
    context = browser.new_context(viewport={"width": 1280, "height": 900})
    context.route("**/*", lambda route: route.continue_()
                  if route.request.url.startswith(live.base_url)
                  else (outside.append(route.request.url), route.abort()))
    page = context.new_page()
    page.set_default_timeout(TIMEOUT_MS)
    log.watch(page)
    page.goto(f"{live.base_url}/docs")
    page.wait_for_selector(".opblock", state="attached")
    yield page
    assert outside == [], f"the page reached outside this server: {outside}"
    assert log.errors == [], log.errors
    context.close()


def _operations(live) -> set[tuple[str, str]]:
    spec = httpx.get(f"{live.base_url}/openapi.json").json()
    assert spec["openapi"].startswith("3.1")
    return {(method.upper(), path) for path, ops in spec["paths"].items()
            for method in ops if method in METHODS}


def test_docs_lists_every_operation(page, live):
    assert "Unable to render this definition" not in page.content()
    shown = page.eval_on_selector_all(
        ".opblock",
        """blocks => blocks.map(b => [
             b.querySelector('.opblock-summary-method').textContent.trim(),
             b.querySelector('.opblock-summary-path').getAttribute('data-path')])""")
    expected = _operations(live)
    assert len(expected) > 20
    assert {tuple(op) for op in shown} == expected


def test_authorize_offers_every_scheme_and_its_key_is_used(page, live):
    page.click("button.authorize")
    dialog = page.locator(".dialog-ux .modal-ux")
    dialog.wait_for()
    text = dialog.inner_text()
    schemes = httpx.get(f"{live.base_url}/openapi.json").json()["components"][
        "securitySchemes"]
    assert {"adminKey", "adminApiKey", "sessionToken"} <= set(schemes)
    for scheme in schemes:
        assert scheme in text
    # the admin key as a bearer token, then a request through "Try it out"
    block = dialog.locator(".auth-container", has_text="adminKey")
    block.locator("input").fill(ADMIN_KEY)
    block.locator("button.authorize").click()
    block.locator("button", has_text="Logout").wait_for()
    assert "Authorized" in block.inner_text()
    dialog.locator("button.close-modal").click()
    assert page.locator("button.authorize.locked").count() == 1

    listing = page.locator("#operations-maps-list_maps_v1_maps_get")
    listing.locator(".opblock-summary").click()
    listing.locator("button.try-out__btn").click()
    with page.expect_response(lambda r: r.url.startswith(f"{live.base_url}/v1/maps")) as got:
        listing.locator("button.execute").click()
    response = got.value
    assert response.status == 200, response.text()
    assert response.request.headers.get("authorization") == f"Bearer {ADMIN_KEY}"
