"""Every reason is a member of ``Reason`` and has its HTTP status in ``api.errors.STATUS``; no error is
raised or answered with a reason spelled as a bare string."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from api.errors import STATUS, ApiError
from service.core.results import Reason

ROOT = Path(__file__).resolve().parents[2]
# callables that take a reason, and the position of the reason among their arguments
TAKES_REASON = {"ApiError": 0, "SessionError": 0, "SolveError": 0, "Failure": 0, "body": 0, "_refuse": 3, "_answer": 2}


def test_every_reason_has_its_http_status():
    assert set(STATUS) == set(Reason), sorted(set(Reason) - set(STATUS))
    assert all(400 <= s < 600 for s in STATUS.values())


def test_an_api_error_takes_its_status_from_the_table_and_refuses_an_unknown_reason():
    assert ApiError(Reason.robot_moving, "the arm moves").status == 409
    assert ApiError(Reason.storage_unavailable, "disk").status == 503
    with pytest.raises(ValueError):
        ApiError("no_such_reason", "spelled by hand")  # type: ignore[arg-type]


def _sources():
    for d in ("service", "api", "drivers"):
        yield from sorted((ROOT / d).rglob("*.py"))


@pytest.mark.parametrize("path", list(_sources()), ids=lambda p: str(p.relative_to(ROOT)))
def test_no_reason_is_a_bare_string(path):
    bare = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if not isinstance(node, ast.Call):
            continue
        f = node.func
        name = f.id if isinstance(f, ast.Name) else f.attr if isinstance(f, ast.Attribute) else None
        k = TAKES_REASON.get(name or "")
        if k is not None and len(node.args) > k:
            arg = node.args[k]
            if isinstance(arg, ast.Constant) and isinstance(arg.value, str):
                bare.append(f"line {node.lineno}: {name}({arg.value!r}, ...)")
    assert not bare, "use a Reason member: " + "; ".join(bare)
