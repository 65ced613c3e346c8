"""The report's map: matplotlib axes over the points composed into one image; colours where the points are, markers."""

from __future__ import annotations

import io

import numpy as np
from PIL import Image

from service.reports.mapimage import OTHER, PALETTE, point_image, render_map_png


def _image(png: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)


def test_point_image_puts_each_point_in_its_pixel_and_leaves_the_rest_white():
    # a 4 x 2 m box at 1 px per metre: (0.5, 1.5) is column 0 of the top row, (3.5, 0.5)
    # column 3 of the bottom row; two points in one pixel cover more than one
    xy = np.array([[0.5, 1.5], [3.5, 0.5], [3.6, 0.4]])
    img = point_image(xy, np.array([0, 5, 5]), np.zeros(2), np.array([4.0, 2.0]), 4, 2)
    assert img.shape == (2, 4, 3)
    assert np.allclose(img[0, 0], 1.0 - 0.7 * (1.0 - OTHER))
    assert np.allclose(img[1, 3], 1.0 - (1.0 - 0.1**2) * (1.0 - PALETTE[35 % len(PALETTE)]), atol=1e-6)
    assert (img.min(axis=2) < 1.0).sum() == 2  # white elsewhere


def test_points_are_drawn_in_their_tree_colour_and_others_grey():
    rng = np.random.default_rng(0)
    # two dense clusters: tree 3 on the left, untreed points on the right
    left = rng.normal((2.0, 5.0), 0.05, (2000, 2))
    right = rng.normal((8.0, 5.0), 0.05, (2000, 2))
    xy = np.vstack([left, right, [[0.0, 0.0], [10.0, 10.0]]])
    tree_id = np.r_[np.full(2000, 3), np.zeros(2002, int)]
    img = _image(render_map_png(xy, tree_id, np.zeros((0, 2)), np.zeros(0, int), title="t"))
    assert img.shape[1] == 1000 and img.shape[0] == 1080  # 10 in wide, square data, 0.8 in for the texts
    tree_rgb = np.round(PALETTE[(3 * 7) % len(PALETTE)] * 255).astype(int)
    grey = np.round(OTHER * 255).astype(int)
    h, w, _ = img.shape
    left_half, right_half = img[:, : w // 2].reshape(-1, 3), img[:, w // 2 :].reshape(-1, 3)
    assert (np.abs(left_half - tree_rgb).max(axis=1) <= 3).sum() > 100
    assert (np.abs(right_half - tree_rgb).max(axis=1) <= 3).sum() == 0
    assert (np.abs(right_half - grey).max(axis=1) <= 3).sum() > 100


def test_a_trunk_is_a_white_disc_in_a_black_ring():
    xy = np.array([[0.0, 0.0], [10.0, 10.0]])
    img = _image(render_map_png(xy, np.zeros(2, int), np.array([[5.0, 5.0]]), np.array([7]), title="t"))
    h, w, _ = img.shape
    centre = img[h // 2 - 40 : h // 2 + 40, w // 2 - 40 : w // 2 + 40]
    dark = (centre.max(axis=2) < 80).sum()
    assert 15 < dark < 400  # the ring and the number "7", not a filled blot


def test_empty_block_and_formula_like_title_render():
    for title in ("", r"row_$1_$2 — $\frac{a$.laz"):
        png = render_map_png(np.zeros((0, 2)), np.zeros(0, int), np.zeros((0, 2)), np.zeros(0, int), title=title)
        assert png[:8] == b"\x89PNG\r\n\x1a\n"
