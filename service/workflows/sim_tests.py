"""An accuracy test run by a running service over HTTP (``posecell report sim KIND``).

The test is the service's own (``POST /tests/{kind}``, :mod:`service.runtime.accuracy_test`):
this module only asks for it, follows its progress and fetches the report and the details — in
the simulated cell those hold the same analysis of the arm's *true* poses, so a user sees what
the measurement found next to what was there. The figures of the README's simulated KR15 come
from here.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import httpx

FINISHED = ("done", "failed", "cancelled", "interrupted")


class SimTestError(RuntimeError):
    """The service refused the test, or the test did not end as done (the sentence says why)."""


def _request(url: str, token: str, body: dict[str, Any] | None = None, timeout_s: float = 30.0) -> Any:
    headers = {"Authorization": f"Bearer {token}"}
    try:
        if body is None:
            r = httpx.get(url, headers=headers, timeout=timeout_s)
        else:
            r = httpx.post(url, json=body, headers=headers, timeout=timeout_s)
    except httpx.TransportError as e:
        raise SimTestError(f"{url}: the service does not answer ({e})") from None
    if r.status_code >= 400:
        try:
            message = r.json().get("message") or r.reason_phrase
        except ValueError:
            message = r.reason_phrase
        raise SimTestError(f"{url}: {r.status_code} {message}")
    return r.json()


def run_test(
    base_url: str,
    token: str,
    kind: str,
    params: dict[str, Any],
    progress: Callable[[float, str], None] | None = None,
    timeout_s: float = 3600.0,
    poll_s: float = 1.0,
) -> tuple[dict[str, Any], dict[str, Any]]:
    """Start the test ``kind`` with ``params`` on the service at ``base_url``, wait for it; its
    (report, test row with ``details``)."""
    row = _request(f"{base_url}/tests/{kind}", token, params)
    test_id = row["id"]
    deadline = time.monotonic() + timeout_s
    while row["status"] not in FINISHED:
        if time.monotonic() > deadline:
            _request(f"{base_url}/tests/{test_id}/stop", token, {})
            raise SimTestError(f"test {test_id} ({kind}) did not finish within {timeout_s:.0f} s: cancelled")
        time.sleep(poll_s)
        row = _request(f"{base_url}/tests/{test_id}", token)
        if progress is not None:
            progress(float(row.get("progress") or 0.0), str(row.get("progress_message") or row["status"]))
    if row["status"] != "done":
        raise SimTestError(f"test {test_id} ({kind}) ended {row['status']}: {row.get('error') or 'no reason given'}")
    return _request(f"{base_url}/tests/{test_id}/report.json", token), row
