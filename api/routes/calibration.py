"""Calibration files: download, upload (validated, versioned, atomic), history and rollback.

An upload is checked by ``service.store.formats`` (finite numbers of the right type within physical
limits) before anything is stored; a refused one is a 422 and leaves the store and the worker as
they were.
"""

from __future__ import annotations

from enum import StrEnum
from typing import Annotated, Any

from fastapi import APIRouter, Body, Query, Request

from api.deps import WorkerDep
from api.errors import ApiError
from api.security import Authorized
from service.core.results import Reason
from service.store.formats import FormatError

router = APIRouter(prefix="/calibration", tags=["calibration"])


class Kind(StrEnum):
    camera = "camera"
    field = "field"
    handeye = "handeye"
    rig = "rig"
    robot = "robot"


@router.get("", summary="Which calibrations are loaded, their versions and sources")
def get_summary(worker: WorkerDep) -> dict[str, Any]:
    return worker.calibration.summary()


@router.get("/{kind}", summary="The current calibration file (camera, field, handeye, rig or robot .json)")
def get_calibration(kind: Kind, worker: WorkerDep) -> Any:
    try:
        return worker.calibration.payload(kind)
    except KeyError:
        raise ApiError(Reason.not_calibrated, f"no {kind} calibration is loaded", status=404) from None


@router.put(
    "/{kind}", dependencies=[Authorized], summary="Upload a calibration; the worker uses it from the next frame"
)
def put_calibration(
    kind: Kind,
    worker: WorkerDep,
    data: Annotated[dict[str, Any], Body()],
    note: Annotated[str, Query(max_length=1000, description="kept with the version, at most 1000 characters")] = "",
) -> dict[str, Any]:
    try:
        version = worker.calibration.update(kind, data, note=note or "uploaded over the API")
    except FormatError as e:
        raise ApiError(Reason.bad_input, str(e)) from None
    worker.event("info", "calibration_changed", f"{kind} calibration version {version} in use")
    return {"ok": True, "kind": str(kind), "version": version}


@router.get("/{kind}/versions", summary="Every stored version of a calibration")
def get_versions(kind: Kind, request: Request) -> list[dict[str, Any]]:
    store = request.app.state.calib_store
    return store.versions(kind) if kind in store.kinds_present() else []


@router.post("/{kind}/rollback/{version}", dependencies=[Authorized], summary="Make an old version current again")
def post_rollback(kind: Kind, version: int, request: Request, worker: WorkerDep) -> dict[str, Any]:
    store = request.app.state.calib_store
    try:
        data = store.get(kind, version)
    except Exception as e:  # the store's "missing" error carries the sentence
        raise ApiError(Reason.not_found, str(e)) from None
    try:
        new_version = worker.calibration.update(kind, data, note=f"rollback to version {version}")
    except FormatError as e:  # stored before today's checks existed
        raise ApiError(Reason.bad_input, f"version {version} cannot be used: {e}") from None
    worker.event("info", "calibration_changed", f"{kind} calibration rolled back to version {version}")
    return {"ok": True, "kind": str(kind), "version": new_version}
