"""The web viewer: static pages under ``/ui/`` that read the API with the user's credentials.

Everything the page needs (its script, styles and Leaflet) is in :data:`STATIC_DIR` and is
installed with the package: the viewer works on a network without internet access.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import FastAPI, Request
from fastapi.responses import FileResponse, RedirectResponse
from fastapi.staticfiles import StaticFiles

STATIC_DIR = Path(__file__).with_name("static")
PREFIX = "/ui"


def install(app: FastAPI) -> None:
    """Serve the viewer at ``/ui/`` (``/ui`` redirects there)."""

    @app.get(PREFIX, include_in_schema=False)
    def _viewer_root() -> RedirectResponse:
        return RedirectResponse(PREFIX + "/", status_code=308)

    @app.get(PREFIX + "/config.json", include_in_schema=False)
    def _viewer_config(request: Request) -> dict:
        """What the operator configured for the page: an optional tile background."""
        settings = request.app.state.ctx.settings
        return {"tile_url": settings.viewer_tile_url,
                "tile_attribution": settings.viewer_tile_attribution}

    @app.get(PREFIX + "/device", include_in_schema=False)
    def _device_page() -> FileResponse:
        """The page a phone localises itself from (docs/devices/phone.md)."""
        return FileResponse(STATIC_DIR / "device.html")

    app.mount(PREFIX, StaticFiles(directory=STATIC_DIR, html=True), name="ui")
