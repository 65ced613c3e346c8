"""Trunk-detection kernels checked by hand."""

import numpy as np
import pytest

from pipeline.trunks import FOOT_ANNULUS, FOOT_RADIUS, foot_ratio


def _ground(rng, n=20000, half=2.0):
    return rng.uniform(-half, half, (n, 2))


def test_a_trunk_standing_in_the_ground_layer_has_a_foot():
    # bark points of a 0.12 m-radius trunk on top of uniform ground: the disc around
    # the trunk is denser than the ring around it
    rng = np.random.default_rng(0)
    ground = _ground(rng)
    a = rng.uniform(0, 2 * np.pi, 400)
    bark = 0.12 * np.column_stack([np.cos(a), np.sin(a)])
    r = foot_ratio(np.array([[0.0, 0.0], [1.2, 1.2]]), np.concatenate([ground, bark]))
    assert r[0] > 2.0
    assert r[1] == pytest.approx(1.0, abs=0.25)  # plain ground: no foot


def test_foot_ratio_by_hand():
    # 10 points inside the disc, 0 in the annulus: (10/(pi r^2) + 1) / (0 + 1)
    pts = np.zeros((10, 2))
    r = foot_ratio(np.zeros((1, 2)), pts)
    assert r[0] == pytest.approx(10 / (np.pi * FOOT_RADIUS**2) + 1.0)
    # the same count spread over the annulus only
    a = np.linspace(0, 2 * np.pi, 10, endpoint=False)
    ring = 0.5 * (FOOT_RADIUS + FOOT_ANNULUS) * np.column_stack([np.cos(a), np.sin(a)])
    r = foot_ratio(np.zeros((1, 2)), ring)
    assert r[0] == pytest.approx(1.0 / (10 / (np.pi * (FOOT_ANNULUS**2 - FOOT_RADIUS**2)) + 1.0))


def test_no_ground_layer_points_means_no_evidence():
    assert foot_ratio(np.zeros((3, 2)), None).tolist() == [1.0, 1.0, 1.0]
    assert foot_ratio(np.zeros((2, 2)), np.zeros((0, 2))).tolist() == [1.0, 1.0]
    assert foot_ratio(np.zeros((0, 2)), np.zeros((5, 2))).shape == (0,)
