"""The HTTP API (FastAPI): :func:`create_app` builds it; serve it with uvicorn.

The parts, one job each: the ``/jobs`` routes (:mod:`service.routes`), their bearer-token
check (:mod:`service.auth`), upload staging (:mod:`service.uploads`), request and answer
models (:mod:`service.models`), and the JSON error answers (:mod:`service.error_handlers`,
by the table of :mod:`service.statuses`). Every error is ``{"error": <class>, "detail": <what
is wrong and how to fix it>}``.
"""

from __future__ import annotations

from contextlib import asynccontextmanager
from typing import Any

from fastapi import FastAPI

from service.dashboard import check_dashboard
from service.docs import install_docs
from service.error_handlers import install_error_handlers
from service.guards import NoSniff, RequestGuard
from service.jobs import JobManager
from service.models import Health
from service.page import install_page
from service.routes import JobRoutes
from service.settings import Settings
from storage.tokens import TokenStore


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
    # the token before any body is read; JSON bodies capped (service.guards)
    app.add_middleware(RequestGuard, settings=settings, tokens=tokens)
    app.add_middleware(NoSniff)  # outermost: the guard's own error answers get it too
    install_docs(app)
    install_page(app)
    install_error_handlers(app)  # service.statuses: one table from error class to status

    @app.get("/health", tags=["service"], response_model=Health)
    async def health() -> dict[str, Any]:
        """Liveness, without a token; says nothing about anyone's jobs."""
        return {"status": "ok", "auth": settings.auth}

    return app
