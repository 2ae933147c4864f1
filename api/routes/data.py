"""History: stored measurements (JSON or CSV) and events.

Times must carry a time zone (``Z`` or an offset such as ``+01:00``): a time without one
names no instant, so it is refused with a 422 rather than guessed.
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Annotated, Any

from fastapi import APIRouter, Query
from fastapi.responses import Response
from pydantic import AfterValidator
from pydantic_core import PydanticCustomError

from api.deps import StoreDep

router = APIRouter(tags=["history"])

MAX_OFFSET = 1_000_000_000  # rows; far above any retention, far below SQLite's 64-bit limit


def _aware(t: datetime) -> datetime:
    if t.tzinfo is None:
        raise PydanticCustomError(
            "timezone_missing", "the time has no time zone: add Z (UTC) or an offset such as +01:00"
        )
    try:
        t.astimezone(UTC)  # what the store does with it
    except OverflowError:
        raise PydanticCustomError("datetime_range", "the time in UTC lies outside the years 1 to 9999") from None
    return t


AwareTime = Annotated[datetime, AfterValidator(_aware)]
From = Annotated[AwareTime | None, Query(alias="from", description="ISO 8601 with a time zone, inclusive")]
To = Annotated[AwareTime | None, Query(alias="to", description="ISO 8601 with a time zone, exclusive")]
Offset = Annotated[int, Query(ge=0, le=MAX_OFFSET, description="rows to skip, [0, 10^9]")]


@router.get("/measurements", summary="Stored measurements, newest first, with time filters (JSON or CSV)")
def get_measurements(
    store: StoreDep,
    t_from: From = None,
    t_to: To = None,
    limit: Annotated[int, Query(ge=1, le=100_000)] = 1000,
    offset: Offset = 0,
    ok: bool | None = None,
    camera: str | None = None,
    format: Annotated[str, Query(pattern="^(json|csv)$")] = "json",
) -> Any:
    rows = store.measurements(t_from=t_from, t_to=t_to, limit=limit, offset=offset, ok=ok, camera=camera)
    if format == "csv":
        return Response(
            store.export_csv(rows),
            media_type="text/csv",
            headers={"Content-Disposition": 'attachment; filename="measurements.csv"'},
        )
    return {"count": len(rows), "measurements": rows}


@router.get("/events", summary="Device and service events (connections, failures, calibration changes)")
def get_events(
    store: StoreDep,
    t_from: From = None,
    t_to: To = None,
    limit: Annotated[int, Query(ge=1, le=10_000)] = 200,
    offset: Offset = 0,
) -> dict[str, Any]:
    rows = store.events(t_from=t_from, t_to=t_to, limit=limit, offset=offset)
    return {"count": len(rows), "events": rows}
