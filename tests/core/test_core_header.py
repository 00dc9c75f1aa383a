"""The map header: what gives a map's stored data its meaning, and the check against our settings."""

import json

import pytest

from arcloud.core.errors import InvalidInput, MapMismatch, StoreError
from arcloud.core.header import HEADER_SETTINGS, MapHeader, check_header
from arcloud.core.types import CLASSES, Params

ALIGNED = ((0.0, 1.0, 0.0, 2.0), (-1.0, 0.0, 0.0, 0.5), (0.0, 0.0, 1.0, 0.0), (0.0, 0.0, 0.0, 1.0))


def test_a_header_holds_the_settings_of_the_params_it_was_made_from():
    params = Params(voxel_size_m=0.04, index_cell_m=2, up=(0, -1, 0), world2aligned=ALIGNED)
    header = MapHeader.from_params(params, codec_version=3, created_at_s=1_700_000_000.5)
    assert (header.voxel_size_m, header.index_cell_m, header.floor_bin_m) == (0.04, 2.0, params.floor_bin_m)
    assert header.up == (0.0, -1.0, 0.0) and header.world2aligned == ALIGNED and header.classes == CLASSES
    assert (header.codec_version, header.created_at_s) == (3, 1_700_000_000.5)
    assert header.differences(params) == [] and header.differences(params, codec_version=3) == []
    check_header(header, params, codec_version=3)


def test_the_record_survives_json():
    for params in (Params(), Params(world2aligned=ALIGNED, up=(0.0, 0.6, 0.8))):
        header = MapHeader.from_params(params, 1, 12.25)
        assert MapHeader.from_record(json.loads(json.dumps(header.to_record()))) == header


@pytest.mark.parametrize(
    ("change", "setting"),
    [
        ({"voxel_size_m": 0.04}, "voxel_size_m"),
        ({"index_cell_m": 2.0}, "index_cell_m"),
        ({"floor_bin_m": 0.05}, "floor_bin_m"),
        ({"up": (0.0, -1.0, 0.0)}, "up"),
        ({"world2aligned": ALIGNED}, "world2aligned"),
    ],
)
def test_each_differing_setting_is_named_with_both_values(change, setting):
    header = MapHeader.from_params(Params(), 1, 0.0)
    with pytest.raises(MapMismatch) as caught:
        check_header(header, Params(**change), map_id="office")
    ours = getattr(MapHeader.from_params(Params(**change), 1, 0.0), setting)
    assert caught.value.differences == [(setting, getattr(header, setting), ours)]
    assert caught.value.map_id == "office" and f"{setting}: map {getattr(header, setting)!r}, ours {ours!r}" in str(caught.value)
    assert isinstance(caught.value, StoreError)


def test_all_differences_are_named_at_once_and_settings_that_do_not_matter_are_not():
    header = MapHeader.from_params(Params(), 1, 0.0)
    assert header.differences(Params(confirm_min_score=0.5, lock_ttl_s=3.0)) == []  # tuning, not meaning
    with pytest.raises(MapMismatch, match="voxel_size_m: map 0.05, ours 0.1; up: .*; codec_version: map 1, ours 2"):
        check_header(header, Params(voxel_size_m=0.1, up=(1.0, 0.0, 0.0)), codec_version=2)


def test_a_map_in_another_codec_version_is_refused():
    header = MapHeader.from_params(Params(), 2, 0.0)
    check_header(header, Params(), codec_version=2)
    assert header.differences(Params()) == []  # without a version of ours: not compared
    assert header.differences(Params(), 3) == [("codec_version", 2, 3)]
    with pytest.raises(MapMismatch, match="codec_version: map 2, ours 3"):
        check_header(header, Params(), codec_version=3)
    newer = MapHeader.from_params(Params(), 4, 0.0)
    assert newer.differences(Params(), 3) == [("codec_version", 4, 3)]


def test_the_class_order_is_part_of_the_meaning():
    header = MapHeader.from_params(Params(), 1, 0.0)
    reordered = MapHeader(**{**{n: getattr(header, n) for n in header.__dataclass_fields__}, "classes": CLASSES[::-1]})
    assert [d[0] for d in reordered.differences(Params())] == ["classes"]


def test_header_settings_are_params_fields():
    assert set(HEADER_SETTINGS) <= set(Params.__dataclass_fields__)


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("voxel_size_m", -0.05),
        ("voxel_size_m", "0.05"),
        ("up", [0, 0, 0]),
        ("world2aligned", [[1, 0, 0], [0, 1, 0], [0, 0, 1]]),
        ("classes", "chair"),
        ("codec_version", 0),
        ("codec_version", 1.5),
        ("created_at_s", None),
    ],
)
def test_a_malformed_record_is_refused_by_field(field, value):
    record = MapHeader.from_params(Params(), 1, 0.0).to_record()
    with pytest.raises(InvalidInput) as caught:
        MapHeader.from_record({**record, field: value})
    assert caught.value.field == f"MapHeader.{field}"


def test_a_record_missing_a_field_is_refused_by_name():
    record = MapHeader.from_params(Params(), 1, 0.0).to_record()
    del record["index_cell_m"]
    with pytest.raises(InvalidInput, match="MapHeader.index_cell_m"):
        MapHeader.from_record(record)


def test_our_codec_version_must_be_one_or_more():
    with pytest.raises(InvalidInput, match="codec_version"):
        MapHeader.from_params(Params(), 0, 0.0)
