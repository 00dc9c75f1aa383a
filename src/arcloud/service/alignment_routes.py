"""The devices' alignments (``ports.DeviceAlignments``): where each device's session world stands in the map.

    PUT    /v1/maps/{map_id}/devices/{device_id}/alignment   admin: store the device's ``device_from_map``
    GET    /v1/maps/{map_id}/devices/{device_id}/alignment   read: the stored one (404: none)
    DELETE /v1/maps/{map_id}/devices/{device_id}/alignment   admin
    GET    /v1/maps/{map_id}/alignments                      read: every device's, by device id

Devices of one map whose AR sessions started at different places (each session has its own origin and
heading) write one map once each has its alignment: a rigid 4x4 mapping map points to the device's world (in
the map's axes and up: ``core.conventions``), which the API applies to every frame of the device that brings
none of its own (``frames.validate_message``), from the next frame on; frames queued before keep the pose they
were accepted with. An app may also send ``device_from_map`` with every frame (from a shared anchor); an
operator sets it here. Refused with 422 naming ``device_from_map``: anything but a finite rigid transform, a
translation beyond ``MAX_TRANSLATION_M``, a rotation that tilts the map's up by more than
``MAX_ALIGNMENT_TILT_DEG``. A map holds at most ``MAX_ALIGNED_DEVICES`` alignments (409 beyond: one admin key
could otherwise grow the store without bound, and ``GET .../alignments`` answers them all at once).
"""

from __future__ import annotations

from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Depends, HTTPException, Path
from starlette.concurrency import run_in_threadpool

from arcloud.core.checks import check_id, check_map_id
from arcloud.core.conventions import check_device_from_map
from arcloud.ports import DeviceAlignments
from arcloud.service.access import require
from arcloud.service.app import MapId, RuntimeDep
from arcloud.service.map_header import check_map_header
from arcloud.service.runtime import Runtime
from arcloud.service.schemas import (
    PROBLEM_RESPONSES,
    AlignmentDeleted,
    DeviceAlignment,
    DeviceAlignmentIn,
    DeviceAlignmentList,
    Problem,
)

router = APIRouter(tags=["devices"])

#: Devices of one map with an alignment, at most: a map shared by many users' AR sessions has one a session.
MAX_ALIGNED_DEVICES = 1000

DeviceId = Annotated[str, Path(description="the device id its frames carry", examples=["phone-2"])]
ALIGNMENT = "/v1/maps/{map_id}/devices/{device_id}/alignment"


def _alignments(runtime: Runtime) -> DeviceAlignments:
    if runtime.alignments is None:
        raise HTTPException(501, "this service was started without device alignments")
    return runtime.alignments


def _out(map_id: str, device_id: str, device_from_map: np.ndarray) -> dict[str, Any]:
    rows = np.asarray(device_from_map, np.float64).reshape(4, 4)
    return {"map_id": map_id, "device_id": device_id, "device_from_map": [[float(v) for v in row] for row in rows]}


@router.put(
    ALIGNMENT,
    dependencies=[Depends(require("admin"))],
    response_model=DeviceAlignment,
    responses={
        **PROBLEM_RESPONSES,
        400: {"model": Problem, "description": "a body that is not JSON"},
        409: {"model": Problem, "description": "a map of other settings, or one holding MAX_ALIGNED_DEVICES alignments"},
        413: {"model": Problem, "description": "body too large"},
    },
    summary="Set where a device's session world stands in the map (admin)",
    description="`device_from_map` maps map points to the device's world, once its frames are in the map's axes and "
    "up (their `pose_convention` and `world_up` applied): a rotation about the map's up and a translation. Applied to "
    "every frame of the device accepted from now on that brings no `device_from_map` of its own. The map need not "
    "exist yet.",
)
async def put_alignment(map_id: MapId, device_id: DeviceId, body: DeviceAlignmentIn, runtime: RuntimeDep) -> dict[str, Any]:
    check_map_id("map_id", map_id)
    check_id("device_id", device_id)
    alignments = _alignments(runtime)
    device_from_map = check_device_from_map("device_from_map", body.flat(), runtime.params.up)
    await run_in_threadpool(check_map_header, runtime.store, map_id, runtime.params)  # 409: a map of other settings
    stored = await run_in_threadpool(alignments.of_map, map_id)
    if device_id not in stored and len(stored) >= MAX_ALIGNED_DEVICES:
        raise HTTPException(
            409,
            f"map {map_id!r} holds {len(stored)} devices' alignments, the most it holds (MAX_ALIGNED_DEVICES); delete one "
            "that is no longer used",
        )
    await run_in_threadpool(alignments.put, map_id, device_id, device_from_map)
    return _out(map_id, device_id, device_from_map)


@router.get(
    ALIGNMENT,
    dependencies=[Depends(require("read"))],
    response_model=DeviceAlignment,
    responses=PROBLEM_RESPONSES,
    summary="A device's stored alignment",
)
def get_alignment(map_id: MapId, device_id: DeviceId, runtime: RuntimeDep) -> dict[str, Any]:
    check_map_id("map_id", map_id)
    check_id("device_id", device_id)
    found = _alignments(runtime).get(map_id, device_id)
    if found is None:
        raise HTTPException(404, f"device {device_id!r} of map {map_id!r} has no alignment")
    return _out(map_id, device_id, found)


@router.delete(
    ALIGNMENT,
    dependencies=[Depends(require("admin"))],
    response_model=AlignmentDeleted,
    responses=PROBLEM_RESPONSES,
    summary="Remove a device's alignment (admin): its next frames are in the map's frame as they come",
)
def delete_alignment(map_id: MapId, device_id: DeviceId, runtime: RuntimeDep) -> AlignmentDeleted:
    check_map_id("map_id", map_id)
    check_id("device_id", device_id)
    deleted = _alignments(runtime).delete(map_id, device_id)
    return AlignmentDeleted(map_id=map_id, device_id=device_id, deleted=deleted)


@router.get(
    "/v1/maps/{map_id}/alignments",
    dependencies=[Depends(require("read"))],
    response_model=DeviceAlignmentList,
    responses=PROBLEM_RESPONSES,
    summary="Every stored device alignment of the map, by device id",
)
def list_alignments(map_id: MapId, runtime: RuntimeDep) -> dict[str, Any]:
    check_map_id("map_id", map_id)
    found = _alignments(runtime).of_map(map_id)
    return {"map_id": map_id, "alignments": [_out(map_id, device, found[device]) for device in sorted(found)]}


__all__ = ["router"]
