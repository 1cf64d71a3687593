"""API docs that work without internet: ``/docs`` (Swagger UI) and ``/redoc`` (ReDoc).

FastAPI's own docs pages load their JavaScript and CSS from a CDN and their favicon from
fastapi.tiangolo.com, so on a lab server without internet ``/docs`` is blank. Here the same pages load
every asset from this server: the Swagger UI and ReDoc bundles vendored by the ``fastapi-offline``
package, served under ``/static/docs/``. ReDoc gets no Google fonts and Swagger UI no online validator,
and both pages carry a Content-Security-Policy that lets them load nothing from any other host: the one
link the ReDoc bundle still has (the Redocly logo in its footer) is blocked in the browser, never sent.
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

from fastapi import FastAPI, Request
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from fastapi.responses import HTMLResponse
from fastapi.staticfiles import StaticFiles

DOCS_STATIC = "/static/docs"
#: Swagger UI and ReDoc pages: their own inline start-up script and styles, ReDoc's web worker, and
#: nothing from another host.
DOCS_HEADERS = {
    "Content-Security-Policy": (
        "default-src 'self'; script-src 'self' 'unsafe-inline' blob:; worker-src 'self' blob:; "
        "style-src 'self' 'unsafe-inline'; img-src 'self' data: blob:; font-src 'self' data:; "
        "connect-src 'self'; frame-ancestors 'none'; base-uri 'none'"
    ),
    "Referrer-Policy": "no-referrer",
    "X-Content-Type-Options": "nosniff",
}


def assets_dir() -> Path:
    """The folder of the vendored Swagger UI and ReDoc files (inside the installed fastapi-offline)."""
    return Path(str(files("fastapi_offline") / "static"))


def install_docs(app: FastAPI) -> None:
    """Serve ``/docs`` and ``/redoc`` with local assets (``app`` is built with ``docs_url=None`` and
    ``redoc_url=None``)."""
    assert app.docs_url is None and app.redoc_url is None, "FastAPI's CDN docs pages must be off"
    app.mount(DOCS_STATIC, StaticFiles(directory=assets_dir()), name="docs-static")

    def urls(request: Request) -> tuple[str, str]:
        root = request.scope.get("root_path", "")
        return f"{root}{app.openapi_url}", f"{root}{DOCS_STATIC}"

    @app.get("/docs", include_in_schema=False)
    async def swagger_ui(request: Request) -> HTMLResponse:
        openapi, static = urls(request)
        page = get_swagger_ui_html(
            openapi_url=openapi,
            title=f"{app.title} - API",
            swagger_js_url=f"{static}/swagger-ui-bundle.js",
            swagger_css_url=f"{static}/swagger-ui.css",
            swagger_favicon_url=f"{static}/favicon.png",
            oauth2_redirect_url=None,
            # no online validator badge; the token typed into "Authorize" stays in the page only
            swagger_ui_parameters={"validatorUrl": None, "persistAuthorization": False},
        )
        page.headers.update(DOCS_HEADERS)
        return page

    @app.get("/redoc", include_in_schema=False)
    async def redoc(request: Request) -> HTMLResponse:
        openapi, static = urls(request)
        page = get_redoc_html(
            openapi_url=openapi,
            title=f"{app.title} - API reference",
            redoc_js_url=f"{static}/redoc.standalone.js",
            redoc_favicon_url=f"{static}/favicon.png",
            with_google_fonts=False,
        )
        page.headers.update(DOCS_HEADERS)
        return page
