"""The Dask dashboard setting: loopback only, and a clear word when the [dashboard] extra is missing."""

from __future__ import annotations

import importlib.util

import pytest

from maxfs.service.runs.dashboard import EXTRA, check_dashboard, dashboard_host
from maxfs.service.settings import Settings
from maxfs.storage.errors import InvalidInputError


@pytest.mark.parametrize(
    "address, host",
    [
        ("127.0.0.1:8787", "127.0.0.1"),
        ("localhost:8787", "localhost"),
        ("[::1]:8787", "::1"),
        ("http://127.0.0.1:8787/status", "127.0.0.1"),
        (":8787", ""),
        ("8787", ""),
        ("0.0.0.0:8787", "0.0.0.0"),
        ("lab-server:8787", "lab-server"),
    ],
)
def test_dashboard_host(address: str, host: str) -> None:
    assert dashboard_host(address) == host


@pytest.mark.parametrize("address", [":8787", "8787", "0.0.0.0:8787", "10.0.0.5:8787", "lab-server:8787"])
def test_dashboard_off_loopback_is_refused(address: str) -> None:
    with pytest.raises(InvalidInputError, match="ssh -L"):
        check_dashboard(Settings(dashboard=address))


def test_dashboard_on_loopback_needs_bokeh(monkeypatch: pytest.MonkeyPatch) -> None:
    assert check_dashboard(Settings(dashboard="")) is None
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: None if name == "bokeh" else real(name))
    assert EXTRA in check_dashboard(Settings(dashboard="127.0.0.1:8787"))
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: object() if name == "bokeh" else real(name))
    assert check_dashboard(Settings(dashboard="127.0.0.1:8787")) is None
