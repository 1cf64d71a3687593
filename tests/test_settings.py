"""The settings object reads ``MAXFS_*`` variables by field type; a bad value is a clear error."""

from __future__ import annotations

from pathlib import Path

import pytest

from maxfs.service.settings import Settings, cluster_settings
from maxfs.storage.errors import InvalidInputError

READS = [
    ("MAXFS_WORKERS", "3", "workers", 3),
    ("maxfs_workers", " 7 ", "workers", 7),
    ("MAXFS_AUTH", "no", "auth", False),
    ("MAXFS_AUTH", "TRUE", "auth", True),
    ("MAXFS_AUTH", "0", "auth", False),
    ("MAXFS_DATA_DIR", "/srv/maxfs", "data_dir", Path("/srv/maxfs")),
    ("MAXFS_PROGRESS_INTERVAL", "0.25", "progress_interval", 0.25),
    ("MAXFS_MAX_K", "1_000", "max_k", 1000),
    ("MAXFS_SCHEDULER", "tls://10.0.0.5:8786", "scheduler", "tls://10.0.0.5:8786"),
]


@pytest.mark.parametrize(("var", "value", "field", "expect"), READS)
def test_environment_values_are_read_by_type(monkeypatch, var, value, field, expect) -> None:
    monkeypatch.setenv(var, value)
    assert getattr(Settings(), field) == expect
    assert type(getattr(Settings(), field)) is type(expect)


REFUSED = [
    ("MAXFS_PORT", "eighty", "MAXFS_PORT must be an integer, got 'eighty'"),
    ("MAXFS_WORKERS", "2.5", "MAXFS_WORKERS must be an integer"),
    ("MAXFS_AUTH", "maybe", "MAXFS_AUTH must be true or false"),
    ("MAXFS_TILE_TIME_LIMIT", "soon", "MAXFS_TILE_TIME_LIMIT must be a number"),
]


@pytest.mark.parametrize(("var", "value", "message"), REFUSED)
def test_a_bad_environment_value_names_the_variable(monkeypatch, var, value, message) -> None:
    monkeypatch.setenv(var, value)
    with pytest.raises(InvalidInputError, match=message):
        Settings()


def test_keywords_win_over_the_environment_and_replace_keeps_the_rest(monkeypatch) -> None:
    monkeypatch.setenv("MAXFS_WORKERS", "3")
    monkeypatch.setenv("MAXFS_PORT", "9000")
    s = Settings(workers=1, data_dir="/tmp/x")
    assert (s.workers, s.port, s.data_dir) == (1, 9000, Path("/tmp/x"))
    t = s.replace(cluster="slurm")
    assert (t.cluster, t.workers, t.port, s.cluster) == ("slurm", 1, 9000, "")
    assert cluster_settings("tcp://h:1", 2, "").scheduler == "tcp://h:1"
    with pytest.raises(TypeError, match="unknown settings: colour"):
        Settings(colour="red")
    with pytest.raises(InvalidInputError, match="workers must be an integer"):
        Settings(workers=True)
