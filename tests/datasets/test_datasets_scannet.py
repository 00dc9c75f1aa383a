"""The ScanNet reader on a tiny scene built in tmp_path: parsing, invalid poses, colour resize, axis
alignment, label mapping (v1 and v2 tsv), ground-truth boxes from the v1 and the v2 annotation."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest
from datasets_builders import (
    ALIGNMENT,
    DEPTH_K,
    DEPTH_WH,
    SCENE_ID,
    TINY_V2_INSTANCES,
    TINY_V2_NYU40,
    TinyScanNet,
    build_scannet,
    write_v2_labels,
)

from arcloud.core.types import Intrinsics
from arcloud.datasets.files import read_ply_mesh
from arcloud.datasets.scannet import (
    DEFAULT_CLASS_MAPPING,
    ClassMapping,
    find_label_table,
    find_scene_dirs,
    load_axis_alignment,
    load_scannet_scene,
    read_label_table,
)
from arcloud.errors import DatasetError, InvalidInput


def aligned_box(lo: np.ndarray, hi: np.ndarray, scan2aligned: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    moved = corners @ scan2aligned[:3, :3].T + scan2aligned[:3, 3]
    return moved.min(axis=0), moved.max(axis=0)


def test_parses_frames_skipping_invalid_poses(tiny_scannet: TinyScanNet, caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING):
        scene = load_scannet_scene(tiny_scannet.scene_dir)
    assert scene.scene_id == SCENE_ID
    assert scene.frame_names == ("0", "2", "10")  # numeric order, "1" dropped
    assert scene.skipped_frames == ("1",)
    assert "skipped 1 of 4 frames" in caplog.text
    assert scene.depth_intrinsics == Intrinsics(*DEPTH_K)
    assert scene.color_intrinsics == Intrinsics(60.0, 60.0, 31.0, 23.0)


def test_frames_are_at_depth_size_with_colour_resized(tiny_scannet: TinyScanNet) -> None:
    scene = load_scannet_scene(tiny_scannet.scene_dir)
    frames = list(scene.frames())
    assert [f.frame_id for f in frames] == ["0", "2", "10"]
    assert [f.timestamp_s for f in frames] == pytest.approx([0.0, 2 / 30, 10 / 30])  # file numbers are 30 Hz frames
    frame = frames[1]
    assert frame.rgb.shape == (DEPTH_WH[1], DEPTH_WH[0], 3) and frame.depth_m.shape == (DEPTH_WH[1], DEPTH_WH[0])
    # left half red, right half blue survives the 2x downsizing
    assert frame.rgb[:, :14, 0].min() > 200 and frame.rgb[:, :14, 2].max() < 60
    assert frame.rgb[:, 18:, 2].min() > 200 and frame.rgb[:, 18:, 0].max() < 60
    assert frame.depth_m[0, 0] == 0.0 and frame.depth_m[1:, 1:].min() >= 0.5 and frame.depth_m.max() < 3.0
    assert frame.map_id == SCENE_ID and frame.intrinsics == Intrinsics(*DEPTH_K)
    assert [f.frame_id for f in scene.frames(stride=2)] == ["0", "10"]
    assert [f.frame_id for f in scene.frames(limit=1)] == ["0"]


def test_axis_alignment_applied_to_poses(tiny_scannet: TinyScanNet) -> None:
    scene = load_scannet_scene(tiny_scannet.scene_dir)
    np.testing.assert_allclose(scene.scan2aligned, ALIGNMENT)
    for name in scene.frame_names:
        np.testing.assert_allclose(scene.pose(name), ALIGNMENT @ tiny_scannet.poses_scan[name], atol=1e-9)
    np.testing.assert_allclose(scene.load_frame("2").cam2world, ALIGNMENT @ tiny_scannet.poses_scan["2"], atol=1e-9)


def test_missing_axis_alignment_is_identity_and_can_be_overridden(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    tiny = build_scannet(tmp_path, alignment=False)
    with caplog.at_level(logging.WARNING):
        scene = load_scannet_scene(tiny.scene_dir)
    assert "no axisAlignment" in caplog.text and "--axis-alignment gives it" in caplog.text
    assert scene.alignment_source.startswith("none") and "the scan's frame" in scene.alignment_source
    np.testing.assert_array_equal(scene.scan2aligned, np.eye(4))
    np.testing.assert_allclose(scene.pose("0"), tiny.poses_scan["0"])
    override = tmp_path / "frames.json"
    override.write_text(json.dumps({"axis_align_matrix": ALIGNMENT.tolist()}))
    scene = load_scannet_scene(tiny.scene_dir, scan2aligned=override)
    np.testing.assert_allclose(scene.pose("0"), ALIGNMENT @ tiny.poses_scan["0"])
    assert scene.alignment_source == "given (--axis-alignment)"


def test_the_segments_are_those_the_aggregation_names_not_the_first_segs_file(tmp_path: Path) -> None:
    tiny = build_scannet(tmp_path)
    # ScanNet's download puts the high-resolution mesh's segments beside the low-resolution one's; it sorts first
    (tiny.scene_dir / f"{SCENE_ID}_vh_clean.segs.json").write_text(json.dumps({"segIndices": [0] * 1000}))
    aggregation = tiny.scene_dir / f"{SCENE_ID}.aggregation.json"
    named = {**json.loads(aggregation.read_text()), "segmentsFile": f"scannet.{SCENE_ID}_vh_clean_2.0.010000.segs.json"}
    aggregation.write_text(json.dumps(named))
    assert [inst.label for inst in load_scannet_scene(tiny.scene_dir).objects] == ["chair", "table", "table"]
    aggregation.write_text(json.dumps({k: v for k, v in named.items() if k != "segmentsFile"}))  # v1's: none named
    assert [inst.label for inst in load_scannet_scene(tiny.scene_dir).objects] == ["chair", "table", "table"]


def test_the_labels_tsv_is_found_in_meta_data_as_scannets_code_keeps_it(tmp_path: Path) -> None:
    tiny = build_scannet(tmp_path / "scans")
    tsv = tmp_path / "scans" / "scannetv2-labels.combined.tsv"
    (tmp_path / "meta_data").mkdir()
    tsv.rename(tmp_path / "meta_data" / tsv.name)
    assert find_label_table(tiny.scene_dir) == tmp_path / "meta_data" / tsv.name
    assert [inst.label for inst in load_scannet_scene(tiny.scene_dir).objects] == ["chair", "table", "table"]


@pytest.mark.parametrize("tsv_version", [1, 2])
def test_label_mapping_and_gt_boxes(tmp_path: Path, tsv_version: int) -> None:
    tiny = build_scannet(tmp_path, tsv_version=tsv_version, binary_ply=tsv_version == 2)
    scene = load_scannet_scene(tiny.scene_dir)
    by_raw = {inst.raw_category: inst for inst in scene.instances}
    assert {raw: inst.label for raw, inst in by_raw.items()} == {
        "chair": "chair",
        "table": "table",
        "desk": "table",
        "floor": None,
    }
    assert {raw: inst.nyu40_id for raw, inst in by_raw.items()} == {"chair": 5, "table": 7, "desk": 14, "floor": 2}
    assert [inst.object_id for inst in scene.objects] == [0, 1, 2]
    for raw, (lo, hi) in tiny.boxes_scan.items():
        want_lo, want_hi = aligned_box(lo, hi, ALIGNMENT)
        np.testing.assert_allclose(by_raw[raw].aabb_min, want_lo, atol=1e-6)
        np.testing.assert_allclose(by_raw[raw].aabb_max, want_hi, atol=1e-6)
    assert len(by_raw["chair"].vertex_indices) == 8
    boxes = scene.gt_boxes()
    assert [b.label for b in boxes] == ["chair", "table", "table"]
    np.testing.assert_allclose(boxes[1].size, [0.8, 1.2, 0.75], atol=1e-6)  # the table, turned 90 degrees


def test_label_table_reads_both_tsv_versions(tmp_path: Path) -> None:
    tiny = build_scannet(tmp_path, tsv_version=1)
    v1 = read_label_table(tiny.scene_dir.parent / "scannetv2-labels.combined.tsv")
    (tmp_path / "v2").mkdir()
    tiny2 = build_scannet(tmp_path / "v2", tsv_version=2)
    v2 = read_label_table(tiny2.scene_dir.parent / "scannetv2-labels.combined.tsv")
    for table in (v1, v2):
        assert table.nyu40_of("Chair ") == 5 and table.label_id_of("desk") == 9
        assert table.class_of("tv") == "tv" and table.class_of("laptop") == "laptop" and table.class_of("floor") is None
        assert table.class_of_label_id(4) == "table" and table.class_of_label_id(11) is None
        assert table.class_of_label_id(12345) is None and table.nyu40_of("unknown thing") == 0
    bad = tmp_path / "bad.tsv"
    bad.write_text("name\tcount\nchair\t3\n")
    with pytest.raises(DatasetError, match="expected columns"):
        read_label_table(bad)


def test_class_mapping_is_configurable_and_checked() -> None:
    assert DEFAULT_CLASS_MAPPING.class_of("desk", 14) == "table"
    assert DEFAULT_CLASS_MAPPING.class_of("computer monitor", 40) == "tv"
    no_desk = ClassMapping(nyu40={5: "chair", 7: "table"}, raw={})
    assert no_desk.class_of("desk", 14) is None
    with pytest.raises(InvalidInput, match="classes among"):
        ClassMapping(nyu40={5: "stool"}, raw={})


def test_ascii_and_binary_ply_read_the_same(tmp_path: Path) -> None:
    a = build_scannet(tmp_path / "a", binary_ply=False)
    b = build_scannet(tmp_path / "b", binary_ply=True)
    va, ca, ta = read_ply_mesh(a.scene_dir / f"{SCENE_ID}_vh_clean_2.ply")
    vb, cb, tb = read_ply_mesh(b.scene_dir / f"{SCENE_ID}_vh_clean_2.ply")
    np.testing.assert_allclose(va, vb)
    np.testing.assert_array_equal(ca, cb)
    np.testing.assert_array_equal(ta, tb)
    assert va.shape == (32, 3) and ta.shape == (48, 3) and ca.dtype == np.uint8 and ta.dtype == np.int32


def test_errors_name_the_file(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="no such folder"):
        load_scannet_scene(tmp_path / "missing")
    tiny = build_scannet(tmp_path)
    (tiny.scene_dir / "pose" / "2.txt").write_text("1 2 3")
    with pytest.raises(DatasetError, match=r"2\.txt: expected 16 numbers"):
        load_scannet_scene(tiny.scene_dir)
    with pytest.raises(DatasetError, match="16 finite numbers"):
        load_axis_alignment("1 2 3")


def test_find_scene_dirs(tmp_path: Path) -> None:
    build_scannet(tmp_path / "scans")
    assert [p.name for p in find_scene_dirs(tmp_path)] == [SCENE_ID]
    assert [p.name for p in find_scene_dirs(tmp_path / "scans" / SCENE_ID)] == [SCENE_ID]
    with pytest.raises(DatasetError, match="scene0999_00"):
        find_scene_dirs(tmp_path, ["scene0999_00"])


def test_v2_instances_and_boxes(tiny_scannet: TinyScanNet, caplog: pytest.LogCaptureFixture) -> None:
    write_v2_labels(tiny_scannet.scene_dir, TINY_V2_INSTANCES, TINY_V2_NYU40)
    with caplog.at_level(logging.INFO):
        scene = load_scannet_scene(tiny_scannet.scene_dir, annotation="v2")
    assert scene.annotation == "v2" and "from the v2 annotation" in caplog.text
    by_id = {inst.object_id: inst for inst in scene.instances}
    assert sorted(by_id) == [1, 5, 12]
    assert {i: (inst.nyu40_id, inst.label, inst.raw_category) for i, inst in by_id.items()} == {
        1: (2, None, "nyu40:2"),
        5: (7, "table", "nyu40:7"),  # 10 vertices vote table, 6 desk
        12: (5, "chair", "nyu40:5"),
    }
    np.testing.assert_array_equal(by_id[5].vertex_indices, np.arange(8, 24))
    # boxes in the aligned frame, as v1's: the table and the desk together
    table_lo, table_hi = aligned_box(*tiny_scannet.boxes_scan["table"], ALIGNMENT)
    desk_lo, desk_hi = aligned_box(*tiny_scannet.boxes_scan["desk"], ALIGNMENT)
    np.testing.assert_allclose(by_id[5].aabb_min, np.minimum(table_lo, desk_lo), atol=1e-6)
    np.testing.assert_allclose(by_id[5].aabb_max, np.maximum(table_hi, desk_hi), atol=1e-6)
    np.testing.assert_allclose(by_id[12].aabb_min, aligned_box(*tiny_scannet.boxes_scan["chair"], ALIGNMENT)[0], atol=1e-6)
    assert sorted(b.label for b in scene.gt_boxes()) == ["chair", "table"]


def test_ties_take_the_smallest_nyu40_id(tiny_scannet: TinyScanNet) -> None:
    nyu40 = TINY_V2_NYU40.copy()
    nyu40[8:24] = [14] * 8 + [7] * 8  # table and desk, 8 votes each
    write_v2_labels(tiny_scannet.scene_dir, TINY_V2_INSTANCES, nyu40)
    table = next(i for i in load_scannet_scene(tiny_scannet.scene_dir).instances if i.object_id == 5)
    assert table.nyu40_id == 7


def test_auto_takes_v2_when_both_files_are_there(tiny_scannet: TinyScanNet, caplog: pytest.LogCaptureFixture) -> None:
    scene = load_scannet_scene(tiny_scannet.scene_dir)
    assert scene.annotation == "v1" and len(scene.instances) == 4
    write_v2_labels(tiny_scannet.scene_dir, TINY_V2_INSTANCES, TINY_V2_NYU40)
    assert load_scannet_scene(tiny_scannet.scene_dir).annotation == "v2"
    assert len(load_scannet_scene(tiny_scannet.scene_dir, annotation="v1").instances) == 4  # v1 still on request
    (tiny_scannet.scene_dir / "labels_v2" / f"{SCENE_ID}_sem_label_all.npy").unlink()
    with caplog.at_level(logging.WARNING):
        assert load_scannet_scene(tiny_scannet.scene_dir).annotation == "v1"
    assert "only one of the two v2 label files" in caplog.text
    assert load_scannet_scene(tiny_scannet.scene_dir, load_mesh=False).annotation is None  # no instances read


@pytest.mark.parametrize(
    ("instance_ids", "nyu40_ids", "message"),
    [
        (TINY_V2_INSTANCES[:-1], TINY_V2_NYU40, r"ins_label_all\.npy: expected one label per mesh vertex \(32\), got 31"),
        (
            TINY_V2_INSTANCES,
            np.append(TINY_V2_NYU40, 0),
            r"sem_label_all\.npy: expected one label per mesh vertex \(32\), got 33",
        ),
        (TINY_V2_INSTANCES.astype(np.float32), TINY_V2_NYU40, r"ins_label_all\.npy: expected integer labels .*got dtype float32"),
        (TINY_V2_INSTANCES.reshape(4, 8), TINY_V2_NYU40, r"ins_label_all\.npy: expected shape \(32,\).*got \(4, 8\)"),
        (TINY_V2_INSTANCES.astype(np.int32) - 2, TINY_V2_NYU40, r"ins_label_all\.npy: expected labels >= 0, got -1"),
    ],
)
def test_malformed_v2_files_are_named(
    tiny_scannet: TinyScanNet, instance_ids: np.ndarray, nyu40_ids: np.ndarray, message: str
) -> None:
    write_v2_labels(tiny_scannet.scene_dir, instance_ids, nyu40_ids)
    with pytest.raises(DatasetError, match=message):
        load_scannet_scene(tiny_scannet.scene_dir)


def test_v2_asked_for_without_its_files(tiny_scannet: TinyScanNet) -> None:
    with pytest.raises(
        DatasetError,
        match=rf"labels_v2: expected the v2 annotation files \['{SCENE_ID}_ins_label_all.npy', '{SCENE_ID}_sem_label_all.npy'\]",
    ):
        load_scannet_scene(tiny_scannet.scene_dir, annotation="v2")
    (tiny_scannet.scene_dir / "labels_v2").mkdir()
    (tiny_scannet.scene_dir / "labels_v2" / f"{SCENE_ID}_ins_label_all.npy").write_bytes(b"not numpy")
    with pytest.raises(DatasetError, match=rf"expected the v2 annotation files \['{SCENE_ID}_sem_label_all.npy'\]"):
        load_scannet_scene(tiny_scannet.scene_dir, annotation="v2", load_mesh=False)
    np.save(tiny_scannet.scene_dir / "labels_v2" / f"{SCENE_ID}_sem_label_all.npy", TINY_V2_NYU40)
    with pytest.raises(DatasetError, match=r"ins_label_all\.npy: expected a numpy array"):
        load_scannet_scene(tiny_scannet.scene_dir, annotation="v2")
    with pytest.raises(InvalidInput, match="annotation"):
        load_scannet_scene(tiny_scannet.scene_dir, annotation="v3")  # type: ignore[arg-type]  # on purpose: a refused annotation
