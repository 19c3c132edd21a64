"""``GET /docs`` (Swagger UI) and ``GET /redoc`` (ReDoc) with their scripts and styles served
by the service itself, not a CDN: the pages work on a depot network without internet.

The assets come from the ``fastapi-offline`` package (a dependency of the ``service`` extra,
MIT): only its ``static`` folder is used, mounted at :data:`STATIC_PATH`; the pages are
FastAPI's own (``get_swagger_ui_html`` / ``get_redoc_html``) pointed at it, without Google
Fonts. Like ``/openapi.json`` they need no key.
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

from fastapi import FastAPI
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from fastapi.responses import HTMLResponse
from fastapi.staticfiles import StaticFiles

__all__ = ["STATIC_PATH", "install_docs", "static_folder"]

#: Where the pages' assets are served.
STATIC_PATH = "/docs/static"


def static_folder() -> Path:
    """The folder of Swagger UI's and ReDoc's bundled assets."""
    return Path(str(files("fastapi_offline") / "static"))


def install_docs(app: FastAPI) -> None:
    """Add ``/docs``, ``/redoc`` and their assets to ``app`` (made with ``docs_url=None,
    redoc_url=None``)."""
    title = f"{app.title} API"
    openapi_url = app.openapi_url or "/openapi.json"

    async def swagger_ui() -> HTMLResponse:
        return get_swagger_ui_html(
            openapi_url=openapi_url,
            title=title,
            swagger_js_url=f"{STATIC_PATH}/swagger-ui-bundle.js",
            swagger_css_url=f"{STATIC_PATH}/swagger-ui.css",
            swagger_favicon_url=f"{STATIC_PATH}/favicon.png",
        )

    async def redoc() -> HTMLResponse:
        return get_redoc_html(
            openapi_url=openapi_url,
            title=title,
            redoc_js_url=f"{STATIC_PATH}/redoc.standalone.js",
            redoc_favicon_url=f"{STATIC_PATH}/favicon.png",
            with_google_fonts=False,
        )

    app.add_api_route("/docs", swagger_ui, methods=["GET"], include_in_schema=False)
    app.add_api_route("/redoc", redoc, methods=["GET"], include_in_schema=False)
    app.mount(STATIC_PATH, StaticFiles(directory=static_folder()), name="docs-static")
