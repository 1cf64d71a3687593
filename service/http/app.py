"""The HTTP API (FastAPI): :func:`create_app` builds it; serve it with uvicorn.

The parts, one job each: the ``/jobs`` routes (:mod:`service.http.routes`), their bearer-token
check (:mod:`service.http.auth`), upload staging (:mod:`service.http.uploads`), request and answer
models (:mod:`service.http.models`), and the JSON error answers (:mod:`service.http.error_handlers`,
by the table of :mod:`service.http.statuses`). Every error is ``{"error": <class>, "detail": <what
is wrong and how to fix it>}``.
"""

from __future__ import annotations

from contextlib import asynccontextmanager
from typing import Any

from fastapi import FastAPI

from maxfs.service.http.docs import install_docs
from maxfs.service.http.error_handlers import install_error_handlers
from maxfs.service.http.guards import NoSniff, RequestGuard
from maxfs.service.http.jobs import JobManager
from maxfs.service.http.models import Health
from maxfs.service.http.page import install_page
from maxfs.service.http.routes import JobRoutes
from maxfs.service.runs.dashboard import check_dashboard
from maxfs.service.settings import Settings
from maxfs.storage.tokens import TokenStore


def create_app(settings: Settings | None = None, manager: JobManager | None = None) -> FastAPI:
    """Build the application; the manager (and its Dask client) starts in the lifespan."""
    settings = settings or Settings()
    check_dashboard(settings)  # loopback only; warns when bokeh (the [dashboard] extra) is missing
    manager = manager or JobManager(settings)
    tokens = TokenStore(settings.tokens_file)

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        await manager.start()
        try:
            yield
        finally:
            await manager.close()

    app = FastAPI(
        title="maxfs-ps",
        version="0.1.0",
        description="Robust photometric stereo by exact maximum feasible Lambertian subsystems.",
        lifespan=lifespan,
        docs_url=None,  # served with local assets by install_docs: no CDN
        redoc_url=None,
    )
    app.state.manager = manager
    app.include_router(JobRoutes(manager, settings, tokens).router)
    # the token before any body is read; JSON bodies capped (service.http.guards)
    app.add_middleware(RequestGuard, settings=settings, tokens=tokens)
    app.add_middleware(NoSniff)  # outermost: the guard's own error answers get it too
    install_docs(app)
    install_page(app)
    install_error_handlers(app)  # service.http.statuses: one table from error class to status

    @app.get("/health", tags=["service"], response_model=Health)
    async def health() -> dict[str, Any]:
        """Liveness, without a token; says nothing about anyone's jobs."""
        return {"status": "ok", "auth": settings.auth}

    return app
