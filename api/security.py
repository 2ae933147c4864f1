"""Bearer-token check for state-changing requests.

The token comes from the configuration, or is generated at the first start and
kept in ``<state_dir>/api-token`` (mode 0600) so that nothing is open by
default and the operator can read it on the cell PC. Reads stay open on the
bound interface (loopback unless configured), as dashboards expect.
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


def require_token(
    request: Request, credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]
) -> None:
    expected: str = request.app.state.token
    if credentials is None or not hmac.compare_digest(credentials.credentials.encode(), expected.encode()):
        raise ApiError(
            "unauthorized", "this request changes the cell's state and needs 'Authorization: Bearer <token>'"
        )


Authorized = Depends(require_token)
