"""API tokens: one per user, stored hashed in one JSON file beside the jobs.

A token is 32 random bytes (``secrets.token_urlsafe``), shown once when it is
made. The file keeps only its SHA-256 (a slow salted hash buys nothing for
256-bit random secrets) and is written atomically with mode 0600. Lookups
compare the presented token's hash with every stored hash using
:func:`hmac.compare_digest`, so timing reveals neither a prefix nor which user
matched. The server re-reads the file when it changes, so ``maxfs token
create`` takes effect without a restart.

Jobs belong to a user's name *and* identity (``uid``, made with the first token).
``maxfs token create NAME --replace`` rotates the token of the same person, who keeps
their jobs; ``maxfs token revoke NAME`` followed by ``create NAME`` makes a new
person under the old name, who does not see (or fetch, or delete) the old jobs.
Those stay visible to admins and go with the retention period.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import os
import re
import secrets
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from maxfs.storage.errors import ConflictError, InvalidInputError, NotFoundError, StoreError

TOKEN_PREFIX = "mfs_"
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")


@dataclass(frozen=True)
class User:
    """Who a request acts for."""

    name: str
    admin: bool = False
    #: Identity of the token's holder: kept when the token is replaced (``--replace``), new
    #: when a revoked name is given a token again, so that person does not get the old jobs.
    uid: str = ""


#: The user of a server with auth turned off, and of ``maxfs run``.
LOCAL_USER = User("local", admin=True)


def _digest(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


def check_user_name(name: str) -> str:
    if not _NAME.fullmatch(name):
        raise InvalidInputError(
            f"user name {name!r} is not allowed: use 1-64 letters, digits, '_', '.' or '-', "
            "starting with a letter or digit"
        )
    return name


class TokenStore:
    """The token file of one server."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self._cache: tuple[float, dict[str, dict]] | None = None

    def _load(self) -> dict[str, dict]:
        try:
            mtime = self.path.stat().st_mtime_ns
        except FileNotFoundError:
            return {}
        if self._cache is not None and self._cache[0] == mtime:
            return self._cache[1]
        try:
            users = json.loads(self.path.read_text())["users"]
        except (ValueError, KeyError, TypeError) as e:
            raise StoreError(f"token file {self.path} is corrupt: {e}") from None
        self._cache = (mtime, users)
        return users

    def _save(self, users: dict[str, dict]) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".maxfs-tokens-", dir=self.path.parent)
        try:
            os.fchmod(fd, 0o600)
            with os.fdopen(fd, "w") as f:
                json.dump({"users": users}, f, indent=1)
            os.replace(tmp, self.path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        self._cache = None

    def create(self, name: str, admin: bool = False, replace: bool = False) -> str:
        """Make a token for ``name`` and return it (it is not stored in clear)."""
        check_user_name(name)
        users = dict(self._load())
        if name in users and not replace:
            raise ConflictError(f"user {name!r} already has a token; revoke it first or pass --replace")
        token = TOKEN_PREFIX + secrets.token_urlsafe(32)
        uid = users[name].get("uid") if name in users else None  # --replace: the same person
        users[name] = {
            "sha256": _digest(token),
            "admin": bool(admin),
            "created_at": time.time(),
            "uid": uid or secrets.token_hex(8),
        }
        self._save(users)
        return token

    def revoke(self, name: str) -> None:
        users = dict(self._load())
        if name not in users:
            raise NotFoundError(f"no user {name!r}; `maxfs token list` shows who has a token")
        del users[name]
        self._save(users)

    def users(self) -> list[User]:
        return [User(n, bool(u.get("admin")), str(u.get("uid", ""))) for n, u in sorted(self._load().items())]

    def authenticate(self, token: str) -> User | None:
        """The user holding ``token``, or None. Every stored hash is compared, in constant time."""
        presented = _digest(token).encode()
        found: User | None = None
        for name, u in self._load().items():
            if hmac.compare_digest(presented, str(u.get("sha256", "")).encode()):
                found = User(name, bool(u.get("admin")), str(u.get("uid", "")))
        return found
