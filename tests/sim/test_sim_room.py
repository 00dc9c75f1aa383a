"""Generated rooms: deterministic, plausible, objects apart, exact GT boxes."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest

from arcloud.core.types import CLASSES
from arcloud.errors import InvalidInput
from arcloud.sim.room import Room, generate_room, gt_boxes, office_room

SEEDS = (0, 1, 2, 5)


@pytest.fixture(scope="module")
def rooms() -> dict[int, Room]:
    return {seed: generate_room(seed) for seed in SEEDS}


def _boxes(room: Room) -> list[tuple[str, np.ndarray, np.ndarray]]:
    return [(o.label, o.aabb_min, o.aabb_max) for o in room.objects] + [(c.kind, c.aabb_min, c.aabb_max) for c in room.clutter]


def test_same_seed_same_room_other_seed_other_room() -> None:
    a, b, c = generate_room(3), generate_room(3), generate_room(4)
    for name in ("vertices", "triangles", "triangle_colors", "triangle_instance", "triangle_clutter"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert [(o.instance_id, o.label) for o in a.objects] == [(o.instance_id, o.label) for o in b.objects]
    for oa, ob in zip(a.objects, b.objects):
        np.testing.assert_array_equal(oa.aabb_min, ob.aabb_min)
    assert a.vertices.shape != c.vertices.shape or not np.array_equal(a.vertices, c.vertices)


def test_mesh_arrays_have_the_documented_types(rooms: dict[int, Room]) -> None:
    room = rooms[0]
    n = len(room.triangles)
    assert room.vertices.dtype == np.float32 and room.vertices.shape[1] == 3
    assert room.triangles.dtype == np.int32 and room.triangles.shape == (n, 3)
    assert room.triangle_colors.dtype == np.uint8 and room.triangle_colors.shape == (n, 3)
    assert room.triangle_instance.dtype == np.int32 and room.triangle_instance.shape == (n,)
    assert room.triangles.min() >= 0 and room.triangles.max() < len(room.vertices)
    assert not room.vertices.flags.writeable
    ids = {o.instance_id for o in room.objects}
    assert set(np.unique(room.triangle_instance)) == ids | {0}
    assert ids == set(range(1, len(room.objects) + 1))
    # Clutter triangles are background.
    assert np.all(room.triangle_instance[room.triangle_clutter > 0] == 0)


def test_default_furniture_counts(rooms: dict[int, Room]) -> None:
    for room in rooms.values():
        counts = Counter(o.label for o in room.objects)
        assert set(counts) == set(CLASSES)
        assert 2 <= counts["table"] <= 3
        assert 4 <= counts["chair"] <= 6
        assert counts["couch"] == 2 and counts["tv"] == 2
        assert 2 <= counts["laptop"] <= 3
        kinds = {c.kind for c in room.clutter}
        assert {"door", "window"} <= kinds and kinds & {"bookshelf", "plant", "boxes", "lamp", "cabinet"}


def test_gt_boxes_are_the_bounds_of_each_objects_own_triangles(rooms: dict[int, Room]) -> None:
    for room in rooms.values():
        for obj in room.objects:
            vertices = room.vertices[room.triangles[room.triangle_instance == obj.instance_id].ravel()]
            np.testing.assert_array_equal(vertices.min(axis=0), obj.aabb_min)
            np.testing.assert_array_equal(vertices.max(axis=0), obj.aabb_max)
        assert [(label, lo.tolist(), hi.tolist()) for label, lo, hi in gt_boxes(room)] == [
            (o.label, o.aabb_min.tolist(), o.aabb_max.tolist()) for o in room.objects
        ]


def test_objects_and_clutter_do_not_overlap_and_stay_inside(rooms: dict[int, Room]) -> None:
    for room in rooms.values():
        boxes = _boxes(room)
        for i, (name_a, lo_a, hi_a) in enumerate(boxes):
            assert np.all(lo_a[:2] >= 0) and np.all(hi_a <= room.size_m), name_a
            assert lo_a[2] >= 0
            for name_b, lo_b, hi_b in boxes[i + 1 :]:
                overlap = np.clip(np.minimum(hi_a, hi_b) - np.maximum(lo_a, lo_b), 0, None)
                assert np.prod(overlap) == 0.0, f"room {room.seed}: {name_a} and {name_b} overlap"


def test_sizes_are_realistic_per_class(rooms: dict[int, Room]) -> None:
    # (min, max) of the larger horizontal extent and of the height, in metres (boxes of turned objects
    # are a little larger than the objects).
    ranges = {
        "chair": ((0.42, 0.75), (0.75, 1.0)),
        "table": ((1.2, 1.9), (0.72, 0.77)),
        "couch": ((1.6, 2.4), (0.75, 0.9)),
        "tv": ((0.7, 1.5), (0.43, 1.0)),
        "laptop": ((0.28, 0.5), (0.15, 0.3)),
    }
    for room in rooms.values():
        for obj in room.objects:
            (w_lo, w_hi), (h_lo, h_hi) = ranges[obj.label]
            size = obj.size
            assert w_lo <= max(size[:2]) <= w_hi, (obj.label, size)
            assert h_lo <= size[2] <= h_hi, (obj.label, size)


def test_laptops_stand_on_a_table_or_a_cabinet(rooms: dict[int, Room]) -> None:
    for room in rooms.values():
        supports = [(o.aabb_min, o.aabb_max) for o in room.objects if o.label == "table"]
        supports += [(c.aabb_min, c.aabb_max) for c in room.clutter if "cabinet" in c.kind]
        for laptop in (o for o in room.objects if o.label == "laptop"):
            on = [
                lo
                for lo, hi in supports
                if laptop.aabb_min[2] == hi[2] and np.all(laptop.aabb_min[:2] >= lo[:2]) and np.all(laptop.aabb_max[:2] <= hi[:2])
            ]
            assert on, f"room {room.seed}: laptop {laptop.instance_id} floats"


def test_tvs_stand_on_a_cabinet_or_hang_near_a_wall(rooms: dict[int, Room]) -> None:
    for room in rooms.values():
        cabinet_tops = {float(c.aabb_max[2]) for c in room.clutter if c.kind == "tv cabinet"}
        for tv in (o for o in room.objects if o.label == "tv"):
            wall_gap = min(tv.aabb_min[0], tv.aabb_min[1], room.size_m[0] - tv.aabb_max[0], room.size_m[1] - tv.aabb_max[1])
            assert float(tv.aabb_min[2]) in cabinet_tops or (tv.aabb_min[2] >= 0.85 and wall_gap < 0.15)


def test_counts_choose_the_objects() -> None:
    room = generate_room(7, counts={"chair": 3, "tv": 1})
    assert Counter(o.label for o in room.objects) == {"chair": 3, "tv": 1}
    empty = generate_room(7, counts={})
    assert empty.objects == () and np.all(empty.triangle_instance == 0)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"counts": {"sofa": 1}}, "counts"),
        ({"counts": {"chair": -1}}, "counts['chair']"),
        ({"counts": {"couch": 30}}, "counts"),
        ({"size_m": (2.0, 6.0, 2.7)}, "size_m"),
        ({"size_m": (8.0, 6.0)}, "size_m"),
    ],
)
def test_bad_arguments_raise_invalid_input(kwargs: dict, field: str) -> None:
    with pytest.raises(InvalidInput) as info:
        generate_room(0, **kwargs)
    assert info.value.field == field


def test_negative_seed_is_refused() -> None:
    with pytest.raises(InvalidInput):
        generate_room(-1)


@pytest.mark.parametrize("seed", [0, 3])
def test_the_office_has_desks_pushed_together_and_monitors_side_by_side_and_back_to_back(seed: int) -> None:
    room = office_room(seed)
    assert office_room(seed).objects == room.objects  # the same room for the same seed
    assert Counter(o.label for o in room.objects) == {"tv": 3, "chair": 3, "table": 2, "laptop": 1}
    first, second = (o for o in room.objects if o.label == "table")
    gap = np.maximum(first.aabb_min[:2] - second.aabb_max[:2], second.aabb_min[:2] - first.aabb_max[:2])
    assert gap.max() < 0.01  # the desks' boxes meet: pushed together
    tvs = [o for o in room.objects if o.label == "tv"]
    turned = [t for t in tvs if abs(np.cos(t.yaw_rad - first.yaw_rad) + 1) < 1e-6]
    facing = [t for t in tvs if abs(np.cos(t.yaw_rad - first.yaw_rad) - 1) < 1e-6]
    assert len(turned) == 1 and len(facing) == 2  # two monitors face one user, one the other
    side_by_side = np.linalg.norm(facing[0].center[:2] - facing[1].center[:2])
    assert 0.5 < side_by_side < 0.72  # two 0.5-0.62 m monitors, 0.02-0.08 m apart
    for monitor in facing:  # back to back with the turned one: within a monitor's width, 0.25-0.35 m behind
        assert np.linalg.norm(monitor.center[:2] - turned[0].center[:2]) < 0.75
    tops = [first.aabb_max[2], second.aabb_max[2]]
    assert facing[0].aabb_min[2] == pytest.approx(facing[1].aabb_min[2])  # on one desk
    assert facing[0].aabb_min[2] != pytest.approx(turned[0].aabb_min[2]) or tops[0] == pytest.approx(tops[1])
    for monitor in tvs:  # standing on a desk top
        assert min(abs(monitor.aabb_min[2] - top) for top in tops) < 1e-6


def test_the_office_cases_walk_the_office() -> None:
    from arcloud.accuracy.sim import FULL_CASES, OFFICE_SEEDS

    office = [c for c in FULL_CASES if c.split == "office"]
    assert [c.room_seed for c in office] == list(OFFICE_SEEDS) and office[0].name == "office-00"
    assert office[0].room().objects == office_room(OFFICE_SEEDS[0]).objects
    assert not {c.name for c in office} & {c.name for c in FULL_CASES if c.split != "office"}
