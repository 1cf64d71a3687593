"""The job page: ``GET /`` on ``maxfs serve``, for people who would rather look than read JSON.

One HTML file with a little plain JavaScript and CSS (``service/static/page/``, shipped as package data;
no build step, nothing from another host). It signs in with an API token, which the browser keeps in
the tab's session storage and sends as ``Authorization: Bearer``, never in a URL; lists the user's jobs
(an admin's: everyone's) with state and progress, updated every second from ``GET /jobs``; shows the
previews of the selected job and links to its NPY arrays and ``results.zip``; and starts or cancels it.
Everything it shows comes from the documented API, with the same checks as any other client.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import FastAPI
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles

STATIC = Path(__file__).parents[1] / "static" / "page"
PAGE_STATIC = "/static/page"

#: The page runs only its own script and talks only to this server.
PAGE_HEADERS = {
    "Content-Security-Policy": (
        "default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' blob: data:; "
        "connect-src 'self'; form-action 'none'; frame-ancestors 'none'; base-uri 'none'"
    ),
    "Referrer-Policy": "no-referrer",
    "X-Content-Type-Options": "nosniff",
    "Cache-Control": "no-cache",
}


def install_page(app: FastAPI) -> None:
    """Serve the job page at ``/`` and its assets under ``/static/page/``."""
    app.mount(PAGE_STATIC, StaticFiles(directory=STATIC), name="page-static")

    @app.get("/", include_in_schema=False)
    async def job_page() -> FileResponse:
        return FileResponse(STATIC / "index.html", media_type="text/html", headers=PAGE_HEADERS)
