"""Rows from the canopy where the trunks are hidden (pipeline.canopy, pipeline.rows)."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.canopy import CELL, canopy_cells, cell_centres
from pipeline.rows import find_rows


def hedgerows(n_rows=4, per_row=12, s=1.0, r=3.5, hidden=(3,), seed=0):
    """Trunks of a hedgerow block (rows along x, ``hidden`` rows without any trunk found)
    and its canopy cells: a 1.5 m wide wall over every row."""
    rng = np.random.default_rng(seed)
    trunks, row = [], []
    for i in range(n_rows):
        if i + 1 in hidden:
            continue
        for j in range(per_row):
            trunks.append([j * s + rng.normal(0, 0.03), i * r + rng.normal(0, 0.03)])
            row.append(i + 1)
    x, y = np.meshgrid(np.arange(-0.4, (per_row - 1) * s + 0.4, 0.05), np.arange(-0.75, 0.75, 0.05))
    wall = np.c_[x.ravel(), y.ravel()]
    canopy = np.concatenate([wall + [0, i * r] for i in range(n_rows)])
    return np.asarray(trunks), np.asarray(row), canopy


def test_canopy_cells_are_the_occupied_cells_above_the_height():
    xy = np.array([[0.1, 0.1], [0.2, 0.05], [0.3, 0.1], [1.0, 1.0]])
    cells = canopy_cells(xy, np.array([2.0, 2.0, 0.5, 1.5]))
    assert cells.tolist() == [[0, 0], [4, 4]]  # the low point at 0.3 m leaves its cell empty
    np.testing.assert_allclose(cell_centres(cells, origin=(100.0, 200.0)), [[100.125, 200.125], [101.125, 201.125]])
    assert CELL == 0.25


def test_a_row_with_every_trunk_hidden_keeps_the_numbers_of_the_rows_after_it():
    trunks, row, canopy = hedgerows()
    cells = cell_centres(canopy_cells(canopy, np.full(len(canopy), 2.0)))
    blind = find_rows(trunks)
    assert blind.row.max() == 3 and (blind.row[row == 4] == 3).all()  # without the canopy row 4 is called 3
    lay = find_rows(trunks, canopy=cells)
    assert lay.row.tolist() == row.tolist()
    assert lay.rows["row"].tolist() == [1, 2, 3, 4]
    assert lay.rows["n_trees"].tolist() == [12, 12, 0, 12]
    line = lay.lines[2]
    assert abs(line[:, 1].mean() - 7.0) < 0.15 and line[0, 0] < line[-1, 0]  # along y = 7, west to east
    assert 10.0 < lay.rows["length_m"][2] < 12.5
    assert len(lay.gaps["row"]) == 0


def test_a_vehicle_in_an_alley_is_no_row():
    trunks, row, canopy = hedgerows(hidden=())
    x, y = np.meshgrid(np.arange(4.0, 7.0, 0.05), np.arange(4.8, 5.8, 0.05))  # 3 m x 1 m, in the alley
    cells = cell_centres(canopy_cells(np.r_[canopy, np.c_[x.ravel(), y.ravel()]], np.full(len(canopy) + x.size, 2.0)))
    lay = find_rows(trunks, canopy=cells)
    assert lay.row.tolist() == row.tolist()
    assert lay.rows["n_trees"].tolist() == [12, 12, 12, 12]


def test_the_canopy_changes_nothing_where_every_row_has_trunks():
    trunks, _, canopy = hedgerows(hidden=(), n_rows=3)
    cells = cell_centres(canopy_cells(canopy, np.full(len(canopy), 2.0)))
    a, b = find_rows(trunks), find_rows(trunks, canopy=cells)
    assert a.row.tolist() == b.row.tolist() and a.position.tolist() == b.position.tolist()
    assert len(b.lines) == len(a.lines)


@pytest.mark.parametrize("angle", [25.0, 118.0])
def test_a_hidden_row_of_a_rotated_block(angle):
    trunks, row, canopy = hedgerows(n_rows=5, hidden=(2,))
    a = np.radians(angle)
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    cells = cell_centres(canopy_cells(canopy @ rot.T, np.full(len(canopy), 2.0)))
    lay = find_rows(trunks @ rot.T + [300.0, 700.0], canopy=cells + [300.0, 700.0])
    assert lay.rows["n_trees"].tolist() in ([12, 0, 12, 12, 12], [12, 12, 12, 0, 12])  # numbered from either side
    assert len(np.unique(lay.row)) == 4 and len(lay.rows["row"]) == 5
    az = lay.rows["azimuth_deg"]  # the hidden row's line runs the way the others' positions do
    assert np.ptp(az) < 1.0, az


def test_a_fence_wire_beside_the_block_is_no_row():
    trunks, row, canopy = hedgerows(hidden=())
    x = np.arange(-1.0, 12.0, 0.05)
    wire = np.c_[np.r_[x, x], np.r_[np.full(260, -2.6), np.full(260, -2.45)]]  # a fence along the block's edge
    cells = cell_centres(canopy_cells(np.r_[canopy, wire], np.full(len(canopy) + len(wire), 2.0)))
    lay = find_rows(trunks, canopy=cells)
    assert lay.rows["n_trees"].tolist() == [12, 12, 12, 12]


def test_a_fence_running_on_past_the_rows_is_no_row():
    trunks, row, canopy = hedgerows(hidden=())
    x, y = np.meshgrid(np.arange(-6.0, 17.0, 0.05), np.arange(-2.8, -2.0, 0.05))  # thick, dense, but 6 m past each end
    fence = np.c_[x.ravel(), y.ravel()]
    cells = cell_centres(canopy_cells(np.r_[canopy, fence], np.full(len(canopy) + len(fence), 2.0)))
    lay = find_rows(trunks, canopy=cells)
    assert lay.rows["n_trees"].tolist() == [12, 12, 12, 12]


def test_offset_and_among_give_the_cells_of_the_points_shifted_and_picked():
    rng = np.random.default_rng(3)
    xy = rng.uniform(-20, 20, (5000, 2))
    height = rng.uniform(0, 3, 5000)
    among = rng.uniform(size=5000) < 0.6
    origin = np.array([512_000.13, 6_950_000.37])
    want = canopy_cells(xy[among] + origin, height[among])
    got = canopy_cells(xy, height, offset=origin, among=among)
    np.testing.assert_array_equal(got, want)
    assert 0 < len(got) < len(canopy_cells(xy + origin, height))
