"""Shape features: the closed-form 3x3 eigen-decomposition against LAPACK and by hand."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.enrichment import neighbourhood_matrix, shape_features, symmetric_eigen3
from pipeline.woodleaf import neighbourhood_max, smooth


def _entries(a: np.ndarray):
    return a[:, 0, 0], a[:, 1, 1], a[:, 2, 2], a[:, 0, 1], a[:, 0, 2], a[:, 1, 2]


def _check_against_eigh(a: np.ndarray) -> None:
    w, v = np.linalg.eigh(a)
    (l3, l2, l1), small, large = symmetric_eigen3(*_entries(a))
    scale = max(1.0, float(np.abs(w).max(initial=0.0)))
    # ~1e-12 of the largest eigenvalue; ~1e-8 where two (nearly) coincide (arccos near ±1)
    np.testing.assert_allclose(np.column_stack([l3, l2, l1]), w, atol=1e-7 * scale)
    np.testing.assert_allclose(np.linalg.norm(small, axis=1), 1.0)
    np.testing.assert_allclose(np.linalg.norm(large, axis=1), 1.0)
    # eigenvectors of the end eigenvalues, where they are well separated, up to sign
    gap_low, gap_high = w[:, 1] - w[:, 0], w[:, 2] - w[:, 1]
    sep_low, sep_high = gap_low > 1e-6 * scale, gap_high > 1e-6 * scale
    np.testing.assert_allclose(np.abs((small * v[:, :, 0]).sum(1))[sep_low], 1.0, atol=1e-6)
    np.testing.assert_allclose(np.abs((large * v[:, :, 2]).sum(1))[sep_high], 1.0, atol=1e-6)
    # and A v = λ v for them
    np.testing.assert_allclose(np.einsum("kij,kj->ki", a, large), large * l1[:, None], atol=1e-8 * scale)
    np.testing.assert_allclose(np.einsum("kij,kj->ki", a, small), small * l3[:, None], atol=1e-8 * scale)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([1e-4, 1.0, 100.0]))
def test_symmetric_eigen3_agrees_with_lapack(seed, scale):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(200, 3, 3)) * rng.uniform(0.01, 1.0, (200, 1, 3))
    _check_against_eigh(scale * x @ x.transpose(0, 2, 1))  # covariance-like (positive semi-definite)


def test_symmetric_eigen3_by_hand():
    diag = np.zeros((1, 3, 3))
    diag[0] = np.diag([2.0, 5.0, 3.0])
    (l3, l2, l1), small, large = symmetric_eigen3(*_entries(diag))
    np.testing.assert_allclose([l3[0], l2[0], l1[0]], [2.0, 3.0, 5.0])
    np.testing.assert_allclose(np.abs(small[0]), [1.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(np.abs(large[0]), [0.0, 1.0, 0.0], atol=1e-12)
    # rank one: points on a vertical line; the principal axis is z
    line = np.zeros((1, 3, 3))
    line[0, 2, 2] = 4.0
    (l3, l2, l1), _, large = symmetric_eigen3(*_entries(line))
    np.testing.assert_allclose([l3[0], l2[0], l1[0]], [0.0, 0.0, 4.0], atol=1e-7)  # a double eigenvalue
    np.testing.assert_allclose(np.abs(large[0]), [0.0, 0.0, 1.0], atol=1e-12)
    # a single point: no spread at all, unit x and z axes as LAPACK gives them
    (l3, l2, l1), small, large = symmetric_eigen3(*_entries(np.zeros((1, 3, 3))))
    assert l3[0] == l2[0] == l1[0] == 0.0
    np.testing.assert_array_equal(small[0], [1.0, 0.0, 0.0])
    np.testing.assert_array_equal(large[0], [0.0, 0.0, 1.0])


def test_shape_features_of_a_line_a_plane_and_a_blob():
    rng = np.random.default_rng(3)
    t = np.linspace(0.0, 1.0, 60)
    line = np.column_stack([np.zeros_like(t), np.zeros_like(t), t])  # a vertical stem
    g = np.linspace(0.0, 1.0, 12)
    plane = np.column_stack([np.repeat(g, 12), np.tile(g, 12), np.zeros(144)]) + [5.0, 0.0, 0.0]  # a flat face
    blob = rng.normal(size=(150, 3)) * 0.3 + [0.0, 5.0, 0.0]  # foliage
    f = shape_features(np.vstack([line, plane, blob]), radius=0.4)
    i_line, i_plane, i_blob = 30, 60 + 66, 60 + 144 + 75
    assert f.linearity[i_line] > 0.99 and f.verticality[i_line] > 0.99
    assert f.planarity[i_plane] > 0.9 and f.scattering[i_plane] < 1e-9
    np.testing.assert_allclose(np.abs(f.normal[i_plane]), [0.0, 0.0, 1.0], atol=1e-9)
    assert f.scattering[i_blob] > 0.2


@settings(max_examples=30, deadline=None)
@given(m=st.integers(1, 400), seed=st.integers(0, 2**31 - 1))
def test_the_int8_neighbourhood_matrix_gives_the_floats_of_a_float_one(m, seed):
    """The neighbourhood matrix holds int8 ones (a quarter of a float64 matrix's bytes per
    entry): every product, sum and maximum taken over it gives the floats a float64
    matrix of the same entries gives."""
    rng = np.random.default_rng(seed)
    nodes = rng.random((m, 3)) * rng.uniform(0.2, 2.0)
    a = neighbourhood_matrix(nodes, radius=0.15)
    assert a.dtype == np.int8 and np.all(a.data == 1) and np.all(a.diagonal() == 1)
    f = a.astype(np.float64)
    values = rng.random(m)
    np.testing.assert_array_equal(smooth(values, a), smooth(values, f))
    np.testing.assert_array_equal(neighbourhood_max(values, a), neighbourhood_max(values, f))
    got, want = shape_features(nodes, radius=0.15, adjacency=a), shape_features(nodes, radius=0.15, adjacency=f)
    for name in ("linearity", "planarity", "scattering", "verticality", "neighbours", "normal"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
