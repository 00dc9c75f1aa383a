"""The SDK's result types are the API's schemas: each dataclass of ``arcloud.client.results`` has the fields of the
pydantic model of its name (``service.schemas``), and reads that model's documented example; the stream's device
is the event stream's ``device_out``."""

from __future__ import annotations

import dataclasses
import inspect
import json

import pytest
from pydantic import BaseModel

from arcloud.client import results
from arcloud.client.results import DeviceEvent, DeviceOut, ObjectDetail, from_json, map_event
from arcloud.errors import ArcloudError
from arcloud.service import schemas
from arcloud.service.devices import DevicePose
from arcloud.service.event_stream import device_out

#: Dataclasses of the stream's events, which have no pydantic model (``service.event_stream`` writes them).
EVENT_TYPES = {"DeviceOut", "SnapshotEvent", "ResetEvent", "UpsertEvent", "RemovedEvent", "DeviceEvent", "DeviceRemovedEvent"}
TYPES = {name: cls for name, cls in inspect.getmembers(results, dataclasses.is_dataclass) if name not in EVENT_TYPES}


@pytest.mark.parametrize("name", sorted(TYPES))
def test_each_result_has_the_fields_of_the_schema_of_its_name(name: str) -> None:
    model = getattr(schemas, name)
    assert issubclass(model, BaseModel)
    assert [f.name for f in dataclasses.fields(TYPES[name])] == list(model.model_fields)


WITH_EXAMPLES = sorted(n for n in TYPES if "examples" in (getattr(schemas, n).model_config.get("json_schema_extra") or {}))


@pytest.mark.parametrize("name", WITH_EXAMPLES)
def test_each_result_reads_its_schemas_example_as_the_api_does(name: str) -> None:
    model = getattr(schemas, name)
    (example,) = model.model_config["json_schema_extra"]["examples"]
    sdk = json.loads(json.dumps(dataclasses.asdict(from_json(TYPES[name], example))))
    assert sdk == model.model_validate(example).model_dump(mode="json")


def test_an_object_detail_reads_nested_boxes_and_voxels_and_refuses_a_missing_field() -> None:
    answer = {
        **schemas.ObjectOut.model_config["json_schema_extra"]["examples"][0],
        "voxels": {"voxel_size_m": 0.05, "centers": [[0.0, 0.0, 0.0]], "weights": [1.0], "colors": None},
        "added_later": "ignored",
    }
    detail = from_json(ObjectDetail, answer)
    assert detail.aabb is not None and detail.aabb.max == (1.7, 0.95, 0.92) and detail.obb is not None
    assert detail.voxels is not None and detail.voxels.centers == ((0.0, 0.0, 0.0),) and detail.voxels.colors is None
    with pytest.raises(ArcloudError, match="ObjectDetail: the answer lacks a field"):
        from_json(ObjectDetail, {k: v for k, v in answer.items() if k != "label"})


def test_a_device_event_reads_what_the_stream_writes() -> None:
    pose = DevicePose("phone-1", "f7", tuple(float(v) for v in range(16)), (525.0, 525.0, 319.5, 239.5), 640, 480, 12.5)
    written = device_out(pose)
    assert [f.name for f in dataclasses.fields(DeviceOut)] == list(written)
    event = map_event("device", written)
    assert (
        isinstance(event, DeviceEvent) and event.device.cam2world == tuple(range(16)) and event.device.intrinsics["cx"] == 319.5
    )
    assert map_event("a-later-event", {}) is None
