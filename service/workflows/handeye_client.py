"""``posecell calibrate handeye-session``: the guided hand-eye calibration of a running service, from a shell.

A thin client of the service's ``/calibration/handeye/session`` routes (standard
library HTTP, so the cell PC's operator needs nothing else):

    start [--poses N]   propose N robot poses around the field (printed as UR poses and KUKA A,B,C)
    move K              simulated cell only: move the arm to proposal K
    sample              record a sample at the robot's current resting pose
    status              proposals done, samples, motion quality
    solve [--apply]     solve X and Z; --apply stores and uses them
    export              the samples, as `posecell calibrate handeye --samples` reads them
"""

from __future__ import annotations

import json
import os
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

PREFIX = "/calibration/handeye/session"


class ClientError(Exception):
    """The service refused or could not be reached; the message is its sentence."""


def default_token() -> str:
    env = os.environ.get("POSECELL_TOKEN")
    if env:
        return env
    for path in (Path("/var/lib/posecell/api-token"), Path("~/.local/state/posecell/api-token").expanduser()):
        try:
            return path.read_text(encoding="utf-8").strip()
        except OSError:
            continue
    return ""


def call(url: str, token: str, method: str, path: str, body: Any = None, timeout_s: float = 60.0) -> Any:
    data = None if body is None else json.dumps(body).encode()
    req = urllib.request.Request(url.rstrip("/") + path, data=data, method=method)
    req.add_header("Content-Type", "application/json")
    if token:
        req.add_header("Authorization", f"Bearer {token}")
    try:
        with urllib.request.urlopen(req, timeout=timeout_s) as r:
            return json.loads(r.read() or b"null")
    except urllib.error.HTTPError as e:
        try:
            detail = json.loads(e.read())
            raise ClientError(f"{detail.get('reason')}: {detail.get('message')}") from None
        except (ValueError, AttributeError):
            raise ClientError(f"HTTP {e.code} from {url}{path}") from None
    except urllib.error.URLError as e:
        raise ClientError(
            f"the service at {url} cannot be reached ({e.reason}); is `posecell serve` running?"
        ) from None


def run(action: str, url: str, token: str, poses: int = 12, index: int | None = None, apply: bool = False) -> Any:
    if action == "start":
        return call(url, token, "POST", PREFIX, {"n_poses": poses})
    if action == "move":
        if index is None:
            raise ClientError("move needs the proposal's index")
        return call(url, token, "POST", f"{PREFIX}/move/{index}")
    if action == "sample":
        return call(url, token, "POST", f"{PREFIX}/samples")
    if action == "status":
        return call(url, token, "GET", PREFIX)
    if action == "solve":
        return call(url, token, "POST", f"{PREFIX}/solve?apply={'true' if apply else 'false'}")
    if action == "export":
        return call(url, token, "GET", f"{PREFIX}/export")
    raise ClientError(f"unknown action {action!r}")
