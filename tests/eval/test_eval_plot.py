"""The top-down picture and boxes projected into camera images."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from arcloud.core.types import OBB, LabelledBox
from arcloud.errors import InvalidInput
from arcloud.eval.plot import (
    BACKGROUND_RGB,
    CLASS_COLORS_RGB,
    GT_COLOR_RGB,
    MAX_SIDE_PX,
    POINT_COLOR_RGB,
    box_corners,
    color_for,
    draw_boxes_in_image,
    draw_top_down,
    render_top_down,
)

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
RED = (255, 0, 0)


def pixels_of(image: np.ndarray, color) -> np.ndarray:
    """(K, 2) (u, v) of the pixels that have exactly ``color``."""
    v, u = np.nonzero(np.all(image == np.array(color, np.uint8), axis=-1))
    return np.stack([u, v], axis=1)


# ---------------------------------------------------------------- top-down


def gravity_obb(center, size, yaw_rad):
    """A z-up gravity-aligned OBB turned by ``yaw_rad`` about z."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return OBB(np.asarray(center, float), np.asarray(size, float), rotation, yaw_rad)


def test_draw_top_down_writes_a_png_of_plausible_size(tmp_path):
    rng = np.random.default_rng(0)
    gt = [LabelledBox("chair", (0, 0, 0), (0.5, 0.5, 1)), LabelledBox("table", (1, 1, 0), (3, 2, 0.8))]
    pred = [LabelledBox("chair", (0.05, 0, 0), (0.55, 0.5, 1), 0.9), LabelledBox("sofa", (2, 0, 0), (3, 0.5, 1), 0.4)]
    points = rng.uniform((0, 0, 0), (3, 2, 1), (500, 3))
    obbs = [("tv", gravity_obb((1.5, 0.5, 0.5), (0.6, 0.3, 1.0), 0.3))]
    path = draw_top_down(
        tmp_path / "nested" / "dir" / "scene.png", gt=gt, predictions=pred, points_xyz=points, obbs=obbs, title="t"
    )
    assert path == tmp_path / "nested" / "dir" / "scene.png"
    assert path.read_bytes()[:8] == PNG_SIGNATURE
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert image is not None
    height, width = image.shape[:2]
    # 3 m x 2 m at 80 px/m, a margin around, a title above, legend and scale bar below.
    assert 3 * 80 < width < 3 * 80 + 200
    assert 2 * 80 < height < 2 * 80 + 250
    colors = {tuple(c[::-1]) for c in image.reshape(-1, 3)}  # BGR on disk -> RGB
    assert {GT_COLOR_RGB, CLASS_COLORS_RGB["chair"], color_for("sofa"), POINT_COLOR_RGB} <= colors


def test_box_lands_where_the_view_says_with_x_right_and_y_up():
    gt = LabelledBox("chair", (0, 0, 0), (1, 1, 1))
    pred = LabelledBox("table", (2, 3, 0), (3, 4, 1), 0.5)  # right of and above the GT box
    picture = render_top_down(gt=[gt], predictions=[pred], px_per_m=50)
    image, view = picture.image_rgb, picture.view

    green = pixels_of(image, GT_COLOR_RGB)
    blue = pixels_of(image, CLASS_COLORS_RGB["table"])
    green = green[green[:, 1] < image.shape[0] - 60]  # leave out the legend sample below the map
    blue = blue[blue[:, 1] < image.shape[0] - 60]
    # Outline of a 1 m box at 50 px/m: 50 px between line centres, plus the line thickness.
    assert 50 <= np.ptp(green[:, 0]) <= 54 and 50 <= np.ptp(green[:, 1]) <= 54
    assert blue[:, 0].min() > green[:, 0].max()  # world x grows to the right
    assert blue[:, 1].max() < green[:, 1].min()  # world y grows upwards

    (u0, v0), (u1, v1) = np.rint(view.to_px(np.array([[0.0, 0.0], [1.0, 1.0]]))).astype(int)
    assert u1 - u0 == 50 and v0 - v1 == 50
    for u, v in [(u0, v0), (u1, v1), ((u0 + u1) // 2, v0), (u0, (v0 + v1) // 2)]:
        assert tuple(image[v, u]) == GT_COLOR_RGB
    assert tuple(image[(v0 + v1) // 2, (u0 + u1) // 2]) == (255, 255, 255)  # outline only


def test_points_are_drawn_grey_under_the_boxes():
    points = np.array([[0.25, 0.75, 0.0], [5.0, 5.0, 1.0]])
    picture = render_top_down(gt=[LabelledBox("tv", (0, 0, 0), (1, 1, 1))], points_xyz=points, point_radius_px=0)
    u, v = np.rint(picture.view.to_px(points[:, :2])).astype(int).T
    assert tuple(picture.image_rgb[v[0], u[0]]) == POINT_COLOR_RGB
    assert tuple(picture.image_rgb[v[1], u[1]]) == POINT_COLOR_RGB  # content extends to fit the far point
    assert picture.image_rgb.shape[1] >= 5 * 80


def test_oriented_box_footprint_is_rotated():
    # A 2 m x 0.2 m box turned 90 degrees: tall and thin in the picture.
    picture = render_top_down(obbs=[("couch", gravity_obb((0, 0, 0), (2.0, 0.2, 1.0), np.pi / 2))], px_per_m=40)
    image, couch = picture.image_rgb, CLASS_COLORS_RGB["couch"]
    rotated = np.rint(picture.view.to_px(np.array([[0.1, 1.0], [-0.1, 1.0], [-0.1, -1.0], [0.1, -1.0]])))
    for u, v in rotated.astype(int):
        assert tuple(image[v, u]) == couch
    unrotated = np.rint(picture.view.to_px(np.array([[1.0, 0.1], [-1.0, -0.1]])))
    for u, v in unrotated.astype(int):
        assert tuple(image[v, u]) != couch


def test_empty_and_huge_content():
    empty = render_top_down()
    assert empty.image_rgb.ndim == 3 and empty.image_rgb.dtype == np.uint8
    huge = render_top_down(gt=[LabelledBox("table", (0, 0, 0), (200, 1, 1))], px_per_m=80)
    assert huge.view.px_per_m == pytest.approx(MAX_SIDE_PX / 200)
    assert huge.image_rgb.shape[1] <= MAX_SIDE_PX + 100


def test_top_down_rejects_bad_input(tmp_path):
    with pytest.raises(InvalidInput, match="path: expected a file name ending in .png"):
        draw_top_down(tmp_path / "scene.jpg")
    with pytest.raises(InvalidInput, match=r"points_xyz: expected shape \(N, 3\)"):
        render_top_down(points_xyz=np.zeros((4, 5)))
    with pytest.raises(InvalidInput, match=r"predictions\[0\]: expected a LabelledBox"):
        render_top_down(predictions=[((0, 0, 0), (1, 1, 1))])
    with pytest.raises(InvalidInput, match=r"obbs\[0\]"):
        render_top_down(obbs=[((0, 0, 0), (1, 1, 1))])
    with pytest.raises(InvalidInput, match=r"obbs\[0\]: expected \(label, OBB\)"):
        render_top_down(obbs=[("tv", ((0, 0, 0), (1, 1, 1), 0.0))])
    with pytest.raises(InvalidInput, match="px_per_m: expected a number > 0"):
        render_top_down(px_per_m=0)


def test_color_for_is_stable_and_distinct():
    assert color_for("chair") == CLASS_COLORS_RGB["chair"]
    assert color_for("lamp") == color_for("lamp") != color_for("plant")
    assert len(set(CLASS_COLORS_RGB.values()) | {GT_COLOR_RGB}) == len(CLASS_COLORS_RGB) + 1


# ---------------------------------------------------------------- boxes in camera images

FX, FY, CX, CY = 400.0, 300.0, 160.0, 120.0
H, W = 240, 320


def test_box_corners_are_the_eight_extremes():
    corners = box_corners(LabelledBox("tv", (0, 1, 2), (3, 4, 5)))
    assert corners.shape == (8, 3)
    assert {tuple(c) for c in corners} == {(x, y, z) for x in (0, 3) for y in (1, 4) for z in (2, 5)}


def test_box_in_front_projects_where_the_pinhole_model_says():
    box = LabelledBox("tv", (-0.2, -0.1, 2.0), (0.3, 0.2, 3.0))
    black = np.zeros((H, W, 3), np.uint8)
    image = draw_boxes_in_image(black, [box], np.eye(4), (FX, FY, CX, CY), color_rgb=RED, thickness_px=1, show_labels=False)
    assert not black.any()  # input untouched
    drawn = pixels_of(image, RED)
    for x, y, z in box_corners(box):
        u, v = FX * x / z + CX, FY * y / z + CY
        du, dv = drawn[:, 0] - u, drawn[:, 1] - v
        assert np.min(np.hypot(du, dv)) <= 1.0, (x, y, z)
    # Every drawn pixel lies within the projected near face (the larger one), the centre stays empty.
    near_u = FX * np.array([-0.2, 0.3]) / 2.0 + CX
    near_v = FY * np.array([-0.1, 0.2]) / 2.0 + CY
    assert near_u[0] - 1 <= drawn[:, 0].min() and drawn[:, 0].max() <= near_u[1] + 1
    assert near_v[0] - 1 <= drawn[:, 1].min() and drawn[:, 1].max() <= near_v[1] + 1
    far_centre = np.rint([FX * 0.05 / 3.0 + CX, FY * 0.05 / 3.0 + CY]).astype(int)
    assert not image[far_centre[1], far_centre[0]].any()


def test_camera_pose_moves_the_projection():
    box = LabelledBox("tv", (-0.1, -0.1, -0.1), (0.1, 0.1, 0.1))  # around the world origin
    cam2world = np.eye(4)
    cam2world[:3, 3] = (0.5, 0.0, -2.0)  # camera 2 m behind the origin and 0.5 m to its right
    image = draw_boxes_in_image(
        np.zeros((H, W, 3), np.uint8), [box], cam2world, (FX, FY, CX, CY), color_rgb=RED, show_labels=False
    )
    drawn = pixels_of(image, RED)
    expected_u = FX * (-0.5) / 2.0 + CX  # the origin seen from the camera: x = -0.5, z = 2
    assert abs(drawn[:, 0].mean() - expected_u) < 3 and abs(drawn[:, 1].mean() - CY) < 3


def test_box_behind_the_camera_draws_nothing_and_straddling_edges_are_clipped():
    black = np.zeros((H, W, 3), np.uint8)
    behind = LabelledBox("chair", (-0.5, -0.5, -3.0), (0.5, 0.5, -1.0))
    out = draw_boxes_in_image(black, [behind], np.eye(4), (FX, FY, CX, CY), show_labels=False)
    assert not out.any()
    # A floor-like slab from behind the camera to 4 m ahead, 1 m below it: the visible part is drawn,
    # nothing is drawn above the horizon row (where points at infinite depth would land).
    slab = LabelledBox("table", (-1.0, 1.0, -2.0), (1.0, 1.0, 4.0))
    out = draw_boxes_in_image(black, [slab], np.eye(4), (FX, FY, CX, CY), color_rgb=RED, show_labels=False)
    drawn = pixels_of(out, RED)
    assert drawn.size and drawn[:, 1].min() >= CY + FY * 1.0 / 4.0 - 1.5  # the far edge at z = 4


def test_edges_far_outside_the_image_are_clipped_not_overflowed():
    wide = LabelledBox("couch", (-1e6, -0.01, 2.0), (1e6, 0.01, 2.0))  # a line across the whole view
    out = draw_boxes_in_image(
        np.zeros((H, W, 3), np.uint8), [wide], np.eye(4), (FX, FY, CX, CY), color_rgb=RED, show_labels=False
    )
    drawn = pixels_of(out, RED)
    assert drawn[:, 0].min() == 0 and drawn[:, 0].max() == W - 1
    assert np.all(np.abs(drawn[:, 1] - CY) <= 4)


def test_labels_are_drawn_when_asked():
    box = LabelledBox("tv", (-0.2, -0.1, 2.0), (0.3, 0.2, 3.0), score=0.75)
    grey = np.full((H, W, 3), 90, np.uint8)
    plain = draw_boxes_in_image(grey, [box], np.eye(4), (FX, FY, CX, CY), show_labels=False)
    labelled = draw_boxes_in_image(grey, [box], np.eye(4), (FX, FY, CX, CY), show_labels=True)
    changed = np.any(plain != labelled, axis=-1)
    assert changed.sum() > 50
    assert np.nonzero(changed)[0].max() < FY * -0.1 / 2.0 + CY  # above the box's top edge


def test_draw_boxes_in_image_rejects_bad_input():
    with pytest.raises(InvalidInput, match="cam2world"):
        draw_boxes_in_image(np.zeros((H, W, 3), np.uint8), [], np.zeros((4, 4)), (FX, FY, CX, CY))
    with pytest.raises(InvalidInput, match="rgb: expected dtype uint8"):
        draw_boxes_in_image(np.zeros((H, W, 3)), [], np.eye(4), (FX, FY, CX, CY))


def test_a_long_title_is_made_smaller_to_fit_the_picture() -> None:
    box = LabelledBox("chair", (-0.25, -0.25, 0.0), (0.25, 0.25, 0.8))
    title = "7scenes-redkitchen: centralized, 50 frames, served objects"
    image = render_top_down(gt=[box], predictions=[box], title=title).image_rgb
    inked = np.flatnonzero((image[:28] != BACKGROUND_RGB).any(axis=(0, 2)))  # the title's band
    assert inked.size and inked.max() < image.shape[1] - 10  # its last letters inside, not cut at the border
    short = render_top_down(gt=[box], predictions=[box], title="t").image_rgb
    assert (short[:28] != BACKGROUND_RGB).any()
