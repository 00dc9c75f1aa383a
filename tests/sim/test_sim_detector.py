"""SimulatedDetector and its faults: perfect without faults, deterministic per frame id, rates as set."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from arcloud.core.checks import check_detections
from arcloud.core.types import CLASSES, Intrinsics
from arcloud.errors import InvalidInput
from arcloud.ports import Detector
from arcloud.sim.detector import (
    CONFUSIONS,
    DetectorFaults,
    FrameTruths,
    SimulatedDetector,
    apply_depth_faults,
    frame_truth,
    pose_noise,
    reported_pose,
    true_pose,
)
from arcloud.sim.room import Room, generate_room, room_renderer, room_walk
from arcloud.sim.sequence import simulate_sequence

# Half VGA keeps the tests fast; pixel thresholds are scaled by hand where it matters.
K = Intrinsics(262.5, 262.5, 159.5, 119.5)
W, H = 320, 240


@pytest.fixture(scope="module")
def room() -> Room:
    return generate_room(2)


@pytest.fixture(scope="module")
def poses(room: Room) -> list[np.ndarray]:
    return room_walk(room, 150, seed=2)[::3]  # 50 views spread over the walk


def frames_of(room: Room, poses: list[np.ndarray], faults: DetectorFaults, seed: int = 2) -> list:
    return simulate_sequence(
        room, n_frames=len(poses), seed=seed, width=W, height=H, intrinsics=K, faults=faults, poses=poses, workers=1
    )


def test_without_faults_every_visible_instance_is_detected_exactly(room: Room, poses: list[np.ndarray]) -> None:
    perfect = DetectorFaults.none()
    frames = frames_of(room, poses[:8], perfect)
    detector = SimulatedDetector(room, perfect, seed=2)
    assert isinstance(detector, Detector)
    renderer = room_renderer(room)
    labels = {o.instance_id: o.label for o in room.objects}
    for frame, pose in zip(frames, poses[:8]):
        np.testing.assert_array_equal(frame.cam2world, pose)  # no pose noise
        instance = renderer.render(pose, K, W, H).instance
        visible = [k for k in np.unique(instance) if k != 0]
        detections = detector.detect(frame)
        check_detections(detections, (H, W))
        assert len(detections) == len(visible)
        by_mask = {int(np.unique(instance[d.mask])[0]): d for d in detections}
        for k in visible:
            d = by_mask[int(k)]
            assert d.label == labels[int(k)] and d.score == 1.0
            np.testing.assert_array_equal(d.mask, instance == k)


def test_same_frame_id_same_detections_for_any_device_order_or_detector(room: Room, poses: list[np.ndarray]) -> None:
    faults = DetectorFaults(spurious_rate=1.5, confusion_rate=0.3, split_rate=0.3)
    frames = frames_of(room, poses[:6], faults)
    first = [SimulatedDetector(room, faults, seed=2).detect(f) for f in frames]
    other = SimulatedDetector(room, faults, seed=2)
    moved = [dataclasses.replace(f, device_id=f"user-{9 - i}", map_id="elsewhere") for i, f in enumerate(frames)]
    again = [other.detect(f) for f in reversed(moved)][::-1]
    assert sum(len(d) for d in first) > 0
    for a, b in zip(first, again):
        assert [(d.label, d.score) for d in a] == [(d.label, d.score) for d in b]
        for da, db in zip(a, b):
            np.testing.assert_array_equal(da.mask, db.mask)
    # Another detector seed draws other faults.
    reseeded = SimulatedDetector(room, faults, seed=3)
    assert any(
        [(d.label, d.score) for d in reseeded.detect(dataclasses.replace(f, cam2world=reported_pose(p, faults, 3, f.frame_id)))]
        != [(d.label, d.score) for d in a]
        for f, p, a in zip(frames, poses, first)
    )


@pytest.mark.parametrize("threads", [0, 1])  # 0: one ray-casting thread per core
def test_recorded_truth_and_a_fresh_ray_cast_give_the_same_detections(room: Room, poses: list[np.ndarray], threads: int) -> None:
    faults = DetectorFaults()
    truths = FrameTruths(room)
    frames = simulate_sequence(
        room, n_frames=4, seed=2, width=W, height=H, intrinsics=K, faults=faults, poses=poses[:4], workers=1, truths=truths
    )
    assert len(truths) == 4
    detector = SimulatedDetector(room, faults, seed=2, truths=truths)
    fresh = SimulatedDetector(room, faults, seed=2, threads=threads)  # no truths: ray-casts every frame
    for frame in frames:
        a, b = detector.detect(frame), fresh.detect(frame)
        assert [(d.label, d.score) for d in a] == [(d.label, d.score) for d in b]
        for da, db in zip(a, b):
            np.testing.assert_array_equal(da.mask, db.mask)


@pytest.fixture(scope="module")
def clean_views(room: Room, poses: list[np.ndarray]) -> list[tuple]:
    """(frame, true instance image) of every view, without sensor faults: detectors whose faults
    have no pose or depth noise see the same frames."""
    frames = frames_of(room, poses, DetectorFaults.none())
    truth = SimulatedDetector(room, DetectorFaults.none(), seed=2)
    # The instance images the sequence rendered (exact; checked against a fresh render above).
    instance_of = np.append(room.triangle_instance, 0)  # triangle -1 (no hit) -> 0
    return [(frame, instance_of[truth.truth(frame).triangle()]) for frame in frames]


def _truth_counts(room: Room, views: list[tuple], faults: DetectorFaults) -> tuple[int, int, list]:
    """(visible instances, detections on objects, [(instance image, detections)]) over the views."""
    assert faults.pose_noise_m == 0 and faults.pose_noise_deg == 0
    detector = SimulatedDetector(room, faults, seed=2)
    visible = detected = 0
    results = []
    for frame, instance in views:
        visible += len([k for k in np.unique(instance) if k != 0])
        detections = detector.detect(frame)
        detected += sum(np.count_nonzero(instance[d.mask]) > d.mask.sum() / 2 for d in detections)
        results.append((instance, detections))
    return visible, detected, results


def test_miss_rate_matches_its_setting(room: Room, clean_views: list[tuple]) -> None:
    faults = DetectorFaults.none().replace(miss_rate=0.3)
    visible, detected, _ = _truth_counts(room, clean_views, faults)
    assert visible > 120  # so that the tolerance is at least 2.5 binomial standard deviations
    assert abs((1 - detected / visible) - 0.3) < 0.1


def test_small_and_truncated_instances_are_missed_more(room: Room, clean_views: list[tuple]) -> None:
    faults = DetectorFaults.none().replace(small_area_px=4000, small_miss_rate=1.0, min_area_px=1)
    _, _, results = _truth_counts(room, clean_views, faults)
    for instance, detections in results:
        areas = np.bincount(instance.ravel())
        for d in detections:
            assert areas[int(np.bincount(instance[d.mask]).argmax())] >= 1  # sanity
        hits = {int(np.bincount(instance[d.mask]).argmax()) for d in detections}
        tiny = {k for k in np.flatnonzero(areas) if k != 0 and areas[k] <= 1}
        assert not hits & tiny  # a 1-pixel instance is never detected when small ones always miss


def test_hard_objects_are_missed_in_every_frame_and_classes_can_be_harder(room: Room, clean_views: list[tuple]) -> None:
    faults = DetectorFaults.none().replace(hard_instance_rate=0.5, hard_miss_rate=1.0)
    _, _, results = _truth_counts(room, clean_views, faults)
    visible, detected = set(), set()
    for instance, detections in results:
        visible |= {int(k) for k in np.unique(instance) if k != 0}
        detected |= {int(np.bincount(instance[d.mask]).argmax()) for d in detections}
    never = visible - detected
    assert never and detected  # some objects are hard (never found), the others always found
    for instance, detections in results:
        found = {int(np.bincount(instance[d.mask]).argmax()) for d in detections}
        assert found == {int(k) for k in np.unique(instance) if k != 0} - never
    labels = {o.instance_id: o.label for o in room.objects}
    _, _, results = _truth_counts(room, clean_views, DetectorFaults.none().replace(class_miss_rates=(("table", 1.0),)))
    found_labels = {d.label for _, detections in results for d in detections}
    assert "table" not in found_labels and found_labels == set(labels.values()) - {"table"}


def test_spurious_rate_matches_its_setting(room: Room, clean_views: list[tuple]) -> None:
    faults = DetectorFaults.none().replace(spurious_rate=2.0, spurious_score_min=0.2, spurious_score_max=0.6)
    _, _, results = _truth_counts(room, clean_views, faults)
    spurious = []
    for instance, detections in results:
        extra = [d for d in detections if np.count_nonzero(instance[d.mask]) <= d.mask.sum() / 2]
        assert all(0.2 <= d.score <= 0.6 and d.label in CLASSES for d in extra)
        spurious.append(len(extra))
    # Blobs smaller than 100 px are dropped, so slightly fewer than the Poisson mean.
    assert 1.4 <= np.mean(spurious) <= 2.3


def test_confusions_swap_similar_classes_only(room: Room, clean_views: list[tuple]) -> None:
    faults = DetectorFaults.none().replace(confusion_rate=0.5)
    labels = {o.instance_id: o.label for o in room.objects}
    _, _, results = _truth_counts(room, clean_views[:20], faults)
    changed = total = 0
    for instance, detections in results:
        for d in detections:
            true = labels[int(np.bincount(instance[d.mask]).argmax())]
            total += 1
            if d.label != true:
                changed += 1
                assert d.label in CONFUSIONS[true]
                assert d.score < 1.0
    assert abs(changed / total - 0.5) < 0.15


def test_mask_borders_move_by_a_few_pixels(room: Room, clean_views: list[tuple]) -> None:
    faults = DetectorFaults.none().replace(border_px=2.0)
    _, _, results = _truth_counts(room, clean_views[:10], faults)
    ious = []
    for instance, detections in results:
        for d in detections:
            k = int(np.bincount(instance[d.mask]).argmax())
            true = instance == k
            if true.sum() > 2000:
                ious.append((d.mask & true).sum() / (d.mask | true).sum())
    assert ious and 0.75 < np.median(ious) < 0.99


def test_default_scores_rise_with_visible_area(room: Room, poses: list[np.ndarray]) -> None:
    faults = DetectorFaults().replace(spurious_rate=0.0)
    detector = SimulatedDetector(room, faults, seed=2)
    pairs = [(int(d.mask.sum()), d.score) for frame in frames_of(room, poses[::2], faults) for d in detector.detect(frame)]
    areas, scores = np.array(pairs).T
    assert np.all((scores > 0) & (scores < 1))
    assert np.median(scores[areas > np.median(areas)]) > np.median(scores[areas <= np.median(areas)])


def test_depth_noise_grows_with_depth_squared_and_edges_drop() -> None:
    faults = DetectorFaults(depth_dropout=0.0, depth_flying_rate=0.0)
    depth = np.full((200, 200), 2.0, np.float32)
    depth[:, 100:] = 4.0  # a step: the far side's edge column drops out half the time
    noisy = apply_depth_faults(depth, faults, np.random.default_rng(0))
    for z, block in ((2.0, noisy[:, :90]), (4.0, noisy[:, 110:])):
        sigma = faults.depth_sigma_a_m + faults.depth_sigma_b * (z - faults.depth_sigma_z0_m) ** 2
        assert abs(block.std() / sigma - 1) < 0.1 and abs(block.mean() - z) < 0.01
    assert 0.35 < np.mean(noisy[:, 100] == 0) < 0.65 and np.all(noisy[:, 99] > 0)
    assert np.array_equal(apply_depth_faults(depth, DetectorFaults.none(), np.random.default_rng(0)), depth)
    far = apply_depth_faults(np.full((10, 10), 7.0, np.float32), faults, np.random.default_rng(0))
    assert np.all(far == 0)  # beyond the sensor's range


def test_pose_noise_is_small_and_invertible() -> None:
    faults = DetectorFaults()
    pose = np.eye(4)
    pose[:3, 3] = [1.0, 2.0, 1.5]
    shifts, angles = [], []
    for i in range(300):
        frame_id = f"f{i:06d}"
        reported = reported_pose(pose, faults, 0, frame_id)
        np.testing.assert_allclose(true_pose(reported, faults, 0, frame_id), pose, atol=1e-12)
        noise = pose_noise(faults, 0, frame_id)
        shifts.append(noise[:3, 3])
        angles.append(np.degrees(np.arccos(np.clip((np.trace(noise[:3, :3]) - 1) / 2, -1, 1))))
    assert abs(np.std(shifts) - 0.01) < 0.002
    assert abs(np.sqrt(np.mean(np.square(angles))) - 0.3) < 0.05
    np.testing.assert_array_equal(pose_noise(DetectorFaults.none(), 0, "f000001"), np.eye(4))


@pytest.mark.parametrize(
    "changes",
    [
        {"miss_rate": 1.5},
        {"border_px": -1.0},
        {"score_min": 0.9, "score_max": 0.5},
        {"spurious_rate": float("nan")},
        {"class_miss_rates": (("sofa", 0.1),)},
        {"class_miss_rates": (("table", 2.0),)},
    ],
)
def test_bad_faults_raise_invalid_input(changes: dict) -> None:
    with pytest.raises(InvalidInput):
        DetectorFaults(**changes)


def test_detector_refuses_other_fault_objects(room: Room) -> None:
    with pytest.raises(InvalidInput):
        SimulatedDetector(room, faults={"miss_rate": 0.1})  # type: ignore[arg-type]  # on purpose: a dict is refused


@pytest.mark.parametrize("threads", [-1, 1.5, True, "2"])
def test_detector_refuses_bad_thread_counts(room: Room, threads: object) -> None:
    with pytest.raises(InvalidInput, match="threads"):
        SimulatedDetector(room, threads=threads)  # type: ignore[arg-type]  # on purpose: a refused thread count


def test_truths_belong_to_one_room_and_keep_the_latest_frames(room: Room) -> None:
    other = generate_room(3)
    with pytest.raises(InvalidInput, match="truths"):
        SimulatedDetector(room, truths=FrameTruths(other))
    with pytest.raises(InvalidInput, match="truths"):
        simulate_sequence(room, n_frames=1, truths=FrameTruths(other), workers=1)
    truths = FrameTruths(room, max_frames=2)
    views = [np.zeros((2, 2), np.int32) for _ in range(3)]
    for k, view in enumerate(views):
        truths.record(("f", k), frame_truth(room, view - 1, view.astype(np.float32), np.eye(4), K))
    assert len(truths) == 2 and truths.get(("f", 0)) is None and truths.get(("f", 2)) is not None
