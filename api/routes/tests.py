"""The robot's accuracy tests over the API (see ``service/runtime/accuracy_test.py`` for what runs).

POST /tests/{kind}               start a test (circle | iso9283 | table1): 202 {id, status, ...}
GET  /tests                      the tests, newest first
GET  /tests/{id}                 status, progress (0-1 and a sentence), n_samples, details
POST /tests/{id}/stop            record mode: finish and analyse; program mode: cancel
GET  /tests/{id}/report.json     the report: what ``posecell report KIND`` writes as report.json
GET  /tests/{id}/report          the same as a self-contained HTML page
GET  /tests/{id}/samples         the raw samples: ?format=csv (DESIGN section 5's columns) | json,
                                 ?per=frame | stop (ISO 9283 and Table 1: one row per stop, the default)

The tests' store and runner come up with the app (this router's lifespan, after the app's own,
which opened the measurement database and started the worker) and stop before it.
"""

from __future__ import annotations

import contextlib
import csv
import io
from collections.abc import AsyncIterator
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Body, Depends, FastAPI, Query, Request
from fastapi.responses import HTMLResponse, JSONResponse, Response

from api import plant
from api.errors import ApiError
from api.security import Authorized
from service.core.results import Reason
from service.runtime.accuracy_analysis import sample_table
from service.runtime.accuracy_test import AccuracyTests, TestError
from service.store.measurements import StorageError
from service.store.tests_store import TestStore


@contextlib.asynccontextmanager
async def lifespan(app: FastAPI) -> AsyncIterator[None]:
    store = TestStore(app.state.store.path)
    app.state.tests = AccuracyTests(app.state.worker, store, lambda message: plant.publish_test_report(app, message))
    try:
        yield
    finally:
        app.state.tests.close()
        store.close()


router = APIRouter(prefix="/tests", tags=["accuracy tests"], lifespan=lifespan)

# the report is one self-contained page (inline style and SVG, no script): its own policy, which the
# edge guard keeps, lets the dashboard of the same origin show it in a frame and nothing else run
REPORT_HEADERS = {
    "Content-Security-Policy": "default-src 'none'; style-src 'unsafe-inline'; img-src data:; base-uri 'none'; "
    "form-action 'none'; frame-ancestors 'self'",
    "X-Frame-Options": "SAMEORIGIN",
}


def get_tests(request: Request) -> AccuracyTests:
    tests = getattr(request.app.state, "tests", None)
    if tests is None:
        raise ApiError(Reason.initializing, "the service is starting; try again in a moment")
    return tests


TestsDep = Annotated[AccuracyTests, Depends(get_tests)]


def _err(e: TestError) -> ApiError:
    return ApiError(e.reason, e.message, status=409 if e.reason is Reason.busy else None)


def _call(fn: Any, *args: Any) -> Any:
    try:
        return fn(*args)
    except TestError as e:
        raise _err(e) from None
    except StorageError as e:
        raise ApiError(Reason.storage_unavailable, str(e)) from None


@router.get("", summary="The accuracy tests, newest first")
def list_tests(tests: TestsDep, limit: int = Query(100, ge=1, le=1000)) -> dict[str, Any]:
    return {"tests": _call(tests.recent, limit)}


@router.post(
    "/{kind}",
    dependencies=[Authorized],
    status_code=202,
    summary="Start an accuracy test: circle (ISO 230-4), iso9283 (ISO 9283 poses) or table1 (the paper's Table 1)",
)
def start(
    kind: Literal["circle", "iso9283", "table1"], tests: TestsDep, body: Annotated[dict[str, Any] | None, Body()] = None
) -> dict[str, Any]:
    return _call(tests.start, kind, body)


def _test(tests: AccuracyTests, test_id: int, full: bool = False) -> dict[str, Any]:
    t: dict[str, Any] = _call(tests.get, test_id, full)
    return t


@router.get("/{test_id}", summary="A test: status, progress, n_samples, details")
def get(test_id: int, tests: TestsDep) -> dict[str, Any]:
    t = _test(tests, test_id, full=True)
    t.pop("report", None)  # GET .../report.json has it
    return t


@router.post("/{test_id}/stop", dependencies=[Authorized], summary="Finish a recording, or cancel a program")
def stop(test_id: int, tests: TestsDep) -> dict[str, Any]:
    t: dict[str, Any] = _call(tests.stop, test_id)
    t.pop("report", None)
    return t


def _report(tests: AccuracyTests, test_id: int) -> tuple[str, dict[str, Any]]:
    t = _test(tests, test_id, full=True)
    if t["report"] is None:
        why = f": {t['error']}" if t.get("error") else ""
        raise ApiError(Reason.not_solved, f"test {test_id} is {t['status']} and has no report{why}")
    return t["kind"], t["report"]


@router.get("/{test_id}/report.json", summary="The report, as `posecell report` writes report.json")
def report_json(test_id: int, tests: TestsDep) -> JSONResponse:
    return JSONResponse(_report(tests, test_id)[1])


@router.get("/{test_id}/report", response_class=HTMLResponse, summary="The report as a self-contained HTML page")
def report_html(test_id: int, tests: TestsDep) -> HTMLResponse:
    from service.workflows.report_html import render_html

    kind, report = _report(tests, test_id)
    return HTMLResponse(render_html(kind, report), headers=REPORT_HEADERS)


@router.get("/{test_id}/samples", summary="The raw samples (CSV in DESIGN section 5's columns, or JSON)")
def samples(
    test_id: int,
    tests: TestsDep,
    format: Literal["csv", "json"] = "csv",
    per: Literal["frame", "stop"] | None = None,
) -> Response:
    t = _test(tests, test_id)
    if t["kind"] == "verify":
        raise ApiError(
            Reason.not_found,
            f"test {test_id} is a verification of the robot model: it keeps no samples, its per-pose drift "
            f"is in GET /tests/{test_id}/report.json",
        )
    rows = _call(tests.store.samples, test_id)
    if format == "json":
        return JSONResponse({"id": test_id, "kind": t["kind"], "samples": rows})
    per = per or ("frame" if t["kind"] == "circle" else "stop")
    columns, table = sample_table(t["kind"], rows, per)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(columns)
    w.writerows(["" if v is None else v for v in row] for row in table)
    name = f"test-{test_id}-{t['kind']}.csv"
    return Response(
        buf.getvalue(), media_type="text/csv", headers={"Content-Disposition": f'attachment; filename="{name}"'}
    )
