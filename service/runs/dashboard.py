"""The Dask dashboard of the server's cluster: an optional extra, and on loopback only.

``MAXFS_DASHBOARD=127.0.0.1:8787`` asks for it (:mod:`service.runs.cluster` passes it on). It needs bokeh,
which the service does not install: ``pip install "maxfs-ps[dashboard]"``. The dashboard has no
authentication and shows every task of every user, so it is refused on any address but loopback (a bare
port such as ``:8787`` would listen on every interface); to look at it from another machine, tunnel it:
``ssh -L 8787:127.0.0.1:8787 server``.
"""

from __future__ import annotations

import importlib.util
import logging

from maxfs.service.settings import LOOPBACK, Settings
from maxfs.storage.errors import InvalidInputError

log = logging.getLogger("maxfs.dashboard")

EXTRA = 'pip install "maxfs-ps[dashboard]"'


def dashboard_host(address: str) -> str:
    """The host part of ``host:port``, ``[v6]:port`` or ``http://host:port`` ("" for a bare port)."""
    rest = address.split("://", 1)[-1].split("/", 1)[0]
    if rest.startswith("["):
        return rest[1:].split("]", 1)[0]
    return rest.rpartition(":")[0] if ":" in rest else ("" if rest.isdigit() else rest)


def check_dashboard(settings: Settings) -> str | None:
    """Refuse a dashboard off loopback; say (and return) what is missing when bokeh is not installed."""
    if not settings.dashboard:
        return None
    host = dashboard_host(settings.dashboard)
    if host not in LOOPBACK:
        raise InvalidInputError(
            f"MAXFS_DASHBOARD={settings.dashboard} would publish the Dask dashboard (no authentication, "
            "every user's tasks) beyond this machine; use 127.0.0.1:PORT and tunnel it: "
            "ssh -L PORT:127.0.0.1:PORT this-host"
        )
    if importlib.util.find_spec("bokeh") is None:
        msg = f"MAXFS_DASHBOARD is set but bokeh is not installed, so Dask serves no dashboard: {EXTRA}"
        log.warning(msg)
        return msg
    return None
