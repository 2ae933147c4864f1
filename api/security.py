"""Bearer-token check for state-changing requests.

The token comes from the configuration, or is generated at the first start and
kept in ``<state_dir>/api-token`` (mode 0600) so that nothing is open by
default and the operator can read it on the cell PC. Reads stay open on the
bound interface (loopback unless configured), as dashboards expect.

The check runs twice with the one function :func:`token_matches`: in the edge
middleware (``api/middleware.py``) for every method but GET, HEAD and OPTIONS,
from the headers alone and before a byte of the body is read; and as the
``Authorized`` dependency of each state-changing route (defence in depth, and
what puts the "Authorize" button into ``/docs``).
"""

from __future__ import annotations

import hmac
import os
import secrets
from pathlib import Path
from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from api.errors import ApiError
from service.core.results import Reason

_bearer = HTTPBearer(auto_error=False)


def resolve_token(configured: str, state_dir: Path) -> str:
    if configured:
        return configured
    path = state_dir / "api-token"
    try:
        token = path.read_text(encoding="utf-8").strip()
        if token:
            return token
    except FileNotFoundError:
        pass
    token = secrets.token_urlsafe(24)
    state_dir.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        f.write(token + "\n")
    return token


UNAUTHORIZED = "this request changes the cell's state and needs 'Authorization: Bearer <token>'"


def token_matches(authorization: str | None, expected: str | None) -> bool:
    """Whether an ``Authorization`` header value is ``Bearer <expected>`` (compared in constant time).

    >>> token_matches("Bearer s3cret", "s3cret"), token_matches("bearer  s3cret ", "s3cret")
    (True, True)
    >>> token_matches("Basic s3cret", "s3cret"), token_matches(None, "s3cret"), token_matches("Bearer ", "")
    (False, False, False)
    """
    if not authorization or not expected:
        return False
    scheme, _, credentials = authorization.strip().partition(" ")
    if scheme.lower() != "bearer":
        return False
    return hmac.compare_digest(credentials.strip().encode(), expected.encode())


def require_token(
    request: Request, credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]
) -> None:
    # the scheme's parse (credentials) only feeds the OpenAPI security scheme; the header decides
    if not token_matches(request.headers.get("authorization"), getattr(request.app.state, "token", None)):
        raise ApiError(Reason.unauthorized, UNAUTHORIZED)


Authorized = Depends(require_token)
