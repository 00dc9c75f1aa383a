"""Params checks its fields when built: each kind of field refuses what it cannot mean."""

import dataclasses
import math

import pytest

from arcloud.core.errors import InvalidInput
from arcloud.core.types import _PARAM_KINDS, Params


def test_the_defaults_and_every_override_in_use_are_accepted():
    Params()
    Params(voxel_size_m=0.1, erode_px=0, prune_min_seen=10, layer_margin_m=None, split_min_frames=10**9, floor_standing=())
    Params(up=(0, -1, 0), world2aligned=tuple(tuple(float(i == j) for j in range(4)) for i in range(4)), pixel_stride_max_px=1)


def test_every_field_has_a_check():
    assert {f.name for f in dataclasses.fields(Params)} == set(_PARAM_KINDS)


@pytest.mark.parametrize(
    ("field", "value", "expected"),
    [
        # positive sizes
        ("voxel_size_m", -1, "> 0"),
        ("voxel_size_m", 0.0, "> 0"),
        ("index_cell_m", math.nan, "> 0"),
        ("lock_ttl_s", math.inf, "> 0"),
        ("floor_bin_m", "0.04", "> 0"),
        # non-negative amounts, optional ones
        ("layer_jump_m", -0.01, ">= 0"),
        ("box_pad_voxels", True, ">= 0"),
        ("layer_margin_m", -0.1, "None or a finite number >= 0"),
        # fractions
        ("association_min_overlap", 1.5, "[0, 1]"),
        ("confirm_min_score", -0.1, "[0, 1]"),
        ("floor_min_vote_share", None, "[0, 1]"),
        # counts and the stride
        ("erode_px", -1, "integer >= 0"),
        ("confirm_min_frames", 2.5, "integer >= 0"),
        ("min_voxels_per_detection", True, "integer >= 0"),
        ("pixel_stride_max_px", 0, "integer >= 1"),
        # flags
        ("class_aware", 1, "True or False"),
        # class tuples
        ("layer_classes", ("sofa",), "class names"),
        ("floor_standing", ["chair"], "class names"),
        # angles
        ("floor_max_tilt_deg", 120.0, "[0, 90]"),
        # up
        ("up", (0.0, 0.0, 0.0), "not all 0"),
        ("up", (0.0, 1.0), "3 finite numbers"),
        ("up", [0.0, 0.0, 1.0], "tuple of 3"),
        ("up", (0.0, math.nan, 1.0), "3 finite numbers"),
        # transforms
        ("world2aligned", ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)), "(4, 4)"),
        ("world2aligned", tuple((math.inf,) * 4 for _ in range(4)), "finite"),
    ],
)
def test_a_field_out_of_its_range_is_refused_by_name(field, value, expected):
    with pytest.raises(InvalidInput, match=expected) as caught:
        Params(**{field: value})
    assert caught.value.field == f"Params.{field}" and caught.value.got == repr(value)


def test_an_empty_depth_range_is_refused():
    with pytest.raises(InvalidInput, match="more than depth_min_m") as caught:
        Params(depth_min_m=2.0, depth_max_m=1.0)
    assert caught.value.field == "Params.depth_max_m"


def test_replace_checks_again():
    with pytest.raises(InvalidInput, match="voxel_size_m"):
        Params().replace(voxel_size_m=-0.05)
