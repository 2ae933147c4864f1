"""History: stored measurements (JSON or CSV) and events."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any

from fastapi import APIRouter, Query
from fastapi.responses import Response

from api.deps import StoreDep

router = APIRouter(tags=["history"])


@router.get("/measurements", summary="Stored measurements, newest first, with time filters (JSON or CSV)")
def get_measurements(
    store: StoreDep,
    t_from: Annotated[datetime | None, Query(alias="from", description="ISO 8601, inclusive")] = None,
    t_to: Annotated[datetime | None, Query(alias="to", description="ISO 8601, exclusive")] = None,
    limit: Annotated[int, Query(ge=1, le=100_000)] = 1000,
    offset: Annotated[int, Query(ge=0)] = 0,
    ok: bool | None = None,
    camera: str | None = None,
    format: Annotated[str, Query(pattern="^(json|csv)$")] = "json",
) -> Any:
    rows = store.measurements(t_from=t_from, t_to=t_to, limit=limit, offset=offset, ok=ok, camera=camera)
    if format == "csv":
        return Response(store.export_csv(rows), media_type="text/csv",
                        headers={"Content-Disposition": 'attachment; filename="measurements.csv"'})
    return {"count": len(rows), "measurements": rows}


@router.get("/events", summary="Device and service events (connections, failures, calibration changes)")
def get_events(
    store: StoreDep,
    t_from: Annotated[datetime | None, Query(alias="from")] = None,
    t_to: Annotated[datetime | None, Query(alias="to")] = None,
    limit: Annotated[int, Query(ge=1, le=10_000)] = 200,
) -> dict[str, Any]:
    rows = store.events(t_from=t_from, t_to=t_to, limit=limit)
    return {"count": len(rows), "events": rows}
