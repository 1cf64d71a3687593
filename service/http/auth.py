"""Who is asking: the bearer-token dependency of every ``/jobs`` route.

:func:`make_auth` checks ``Authorization: Bearer <token>`` against the token store (or, with
auth off, makes every request the local user) and puts the :class:`User` in
``request.state.user``; routes read it back with :func:`user_of`.
"""

from __future__ import annotations

from fastapi import Request

from maxfs.service.settings import Settings
from maxfs.storage.errors import AuthError
from maxfs.storage.tokens import LOCAL_USER, TokenStore, User


def make_auth(settings: Settings, tokens: TokenStore):
    """The dependency that puts the request's :class:`User` in ``request.state.user``."""

    async def authenticate(request: Request) -> None:
        if not settings.auth:
            request.state.user = LOCAL_USER
            return
        scheme, _, token = request.headers.get("authorization", "").partition(" ")
        if scheme.lower() != "bearer" or not token.strip():
            raise AuthError(
                "this server needs an API token: send 'Authorization: Bearer <token>' "
                "(an administrator makes one with `maxfs token create NAME`)"
            )
        user = tokens.authenticate(token.strip())
        if user is None:
            raise AuthError("the API token is not valid (mistyped or revoked); ask for a new one")
        request.state.user = user

    return authenticate


def user_of(request: Request) -> User:
    """The user :func:`make_auth` found for ``request``."""
    return request.state.user
