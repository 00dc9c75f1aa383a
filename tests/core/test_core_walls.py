"""The wall behind a screen kept per object (core.walls): frames that found the wall vote for where they cut,
and the object's box leaves out what lies behind that plane, whichever frame put it there."""

from __future__ import annotations

import math
import random

import numpy as np
from handmade_frames import plane_frame, rect_mask

from arcloud.core.boxes import refine
from arcloud.core.fusion import fuse_detection, merge_objects, new_object
from arcloud.core.gravity import Gravity
from arcloud.core.types import Detection, Params
from arcloud.core.voxels import key_centers, voxelize_detections
from arcloud.core.walls import WALL_MIN_FRAMES, WALL_MIN_SHARE, add_wall_votes, object_wall, outside_wall, wall_vote

GRAVITY = Gravity.of((0.0, 0.0, 1.0))
# The hand-made wall at z = 3 m faces the camera: vertical when up is -y (image rows run down).
UPRIGHT = Params(voxel_size_m=0.05, erode_px=0, floor_min_samples=5, up=(0.0, -1.0, 0.0))


def horizontal(degrees: float) -> np.ndarray:
    return np.array([math.cos(math.radians(degrees)), math.sin(math.radians(degrees)), 0.0])


def tally(*votes) -> dict[int, tuple[int, int]]:
    out: dict[int, tuple[int, int]] = {}
    for vote in votes:
        out = add_wall_votes(out, dict([vote]))
    return out


def degrees_between(a: np.ndarray, b: np.ndarray) -> float:
    return math.degrees(math.acos(min(1.0, float(a @ b))))


def test_the_wall_is_where_its_frames_cut_within_their_noise():
    rng = random.Random(7)
    angles = [123.4 + rng.uniform(-1.5, 1.5) for _ in range(20)]
    offsets = [2.0 + rng.uniform(-0.01, 0.01) for _ in angles]
    normal, offset_m = object_wall(tally(*(wall_vote(horizontal(a), o, GRAVITY) for a, o in zip(angles, offsets))), 20, GRAVITY)
    assert degrees_between(normal, horizontal(float(np.mean(angles)))) < 0.3  # every frame's vote, not the likeliest degree's
    assert abs(normal[2]) < 1e-12 and abs(np.linalg.norm(normal) - 1) < 1e-12
    assert abs(offset_m - float(np.mean(offsets))) < 0.001


def test_a_wall_across_north_is_pooled_over_the_wrap():
    votes = [wall_vote(horizontal(a), o, GRAVITY) for a, o in ((359.4, 1.0), (0.3, 1.0), (0.6, 1.0), (358.8, 1.2))]
    normal, offset_m = object_wall(tally(*votes), 4, GRAVITY)
    assert degrees_between(normal, horizontal(-0.225)) < 0.3 and abs(offset_m - 1.05) < 1e-9


def test_one_frame_is_not_a_wall_and_the_most_frames_win():
    one = wall_vote(horizontal(90.0), 1.0, GRAVITY)
    assert WALL_MIN_FRAMES > 1 and object_wall(tally(one), 1, GRAVITY) is None
    # A screen in a corner: its rings found the wall behind it in three frames, the side wall in two.
    back = [wall_vote(horizontal(90.0), 1.0, GRAVITY)] * 3
    side = [wall_vote(horizontal(180.0), -0.4, GRAVITY)] * 2
    normal, offset_m = object_wall(tally(*side, *back), 6, GRAVITY)
    assert normal @ horizontal(90.0) > 0.999 and offset_m == 1.0


def test_a_plane_that_few_of_its_frames_found_is_no_wall():
    # A monitor on a desk: now and then its ring is the back of the monitor behind it.
    votes = tally(*[wall_vote(horizontal(90.0), 1.0, GRAVITY)] * 10)
    assert object_wall(votes, math.ceil(10 / WALL_MIN_SHARE), GRAVITY) is not None
    assert object_wall(votes, math.ceil(10 / WALL_MIN_SHARE) + 1, GRAVITY) is None


def test_the_tally_does_not_depend_on_the_order_of_frames():
    rng = random.Random(3)
    votes = [wall_vote(horizontal(rng.uniform(40, 50)), rng.uniform(0.9, 1.1), GRAVITY) for _ in range(30)]
    shuffled = list(votes)
    rng.shuffle(shuffled)
    assert tally(*votes) == tally(*shuffled)
    halves = add_wall_votes(tally(*votes[:11]), tally(*votes[11:]))
    assert halves == tally(*votes) == add_wall_votes(tally(*votes[11:]), tally(*votes[:11]))


def test_voxels_behind_the_wall_by_more_than_half_a_voxel_are_outside():
    centers = np.array([[0.0, 1.0, 0.0], [0.0, 0.98, 0.0], [0.0, 0.97, 0.0], [5.0, 0.5, 3.0]])
    assert outside_wall(centers, (horizontal(90.0), 1.0), 0.05).tolist() == [True, True, False, False]


def screen(frame, mask):
    (observation,) = voxelize_detections(frame, [Detection("tv", 0.9, mask)], UPRIGHT)
    return observation


def test_a_screen_whose_later_frame_sees_no_wall_keeps_its_box_off_the_wall():
    # Face-on, the ring around the mask is the wall at 3 m and the rule cuts there (each frame votes for it).
    on_wall = plane_frame(3.0, patches=((slice(20, 40), slice(30, 50), 2.82),))
    face_on = screen(on_wall, rect_mask(slice(17, 43), slice(27, 53)))
    assert face_on.wall_vote is not None
    # Later the screen's lower half returns no depth of its own (the wall shows through it) and nothing
    # around it returns any: no ring, no plane, every sample kept.
    through = plane_frame(0.0, patches=((slice(20, 30), slice(30, 50), 2.82), (slice(30, 40), slice(30, 50), 3.0)))
    dark = screen(through, rect_mask(slice(20, 40), slice(30, 50)))
    assert dark.wall_vote is None and key_centers(dark.keys, 0.05)[:, 2].max() > 2.9

    obj = new_object(1, face_on, "a", 0.0)
    for _ in range(WALL_MIN_FRAMES - 1):
        obj = fuse_detection(obj, face_on, "a")
    obj = fuse_detection(obj, dark, "b")
    boxed = refine(obj, UPRIGHT)
    assert key_centers(boxed.keys, 0.05)[:, 2].max() > 2.9  # the wall's voxels are the object's ...
    assert boxed.aabb.max[2] < 2.9  # ... but not its box
    assert refine(obj.replace(wall_votes={}), UPRIGHT).aabb.max[2] > 2.9  # the votes are what kept it out
    assert refine(obj.replace(label="chair", votes=obj.votes[:, ::-1]), UPRIGHT).aabb.max[2] > 2.9  # screens only


def test_merged_pieces_of_a_screen_add_their_votes():
    on_wall = plane_frame(3.0, patches=((slice(20, 40), slice(30, 50), 2.82),))
    face_on = screen(on_wall, rect_mask(slice(17, 43), slice(27, 53)))
    a, b = new_object(1, face_on, "a", 0.0), new_object(2, face_on, "b", 0.0)
    assert object_wall(a.wall_votes, a.n_frames, UPRIGHT.gravity) is None  # one frame each
    merged = merge_objects(a, b)
    assert merged.wall_votes == add_wall_votes(a.wall_votes, b.wall_votes) == merge_objects(b, a).wall_votes
    assert object_wall(merged.wall_votes, merged.n_frames, UPRIGHT.gravity) is not None
