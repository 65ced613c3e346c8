"""Local shape features of graph nodes (the paper's enrichment, after Poux & Billen 2019).

Eigenvalue features of the neighbourhood covariance tell a branch (linear), a surface
(planar: boxes, vehicles, walls) and foliage (scattered) apart.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse

from pipeline.graph import NodePairs, node_pairs, symmetric_csr
from pipeline.rowpasses import sparse_product

#: fewest nodes (the node included) whose spread gives shape features: fewer leave the
#: covariance degenerate, and such nodes count as fully scattered
MIN_NEIGHBOURS = 4


@dataclass(frozen=True)
class ShapeFeatures:
    """Per-node features, all (m,) float64.

    linearity (λ1-λ2)/λ1, planarity (λ2-λ3)/λ1, scattering λ3/λ1, verticality
    |z of the principal axis|, neighbours (count within the radius); and ``normal``,
    (m, 3) the unit axis of least spread (a surface's normal, sign arbitrary).
    """

    linearity: np.ndarray
    planarity: np.ndarray
    scattering: np.ndarray
    verticality: np.ndarray
    neighbours: np.ndarray
    normal: np.ndarray

    def matrix(self) -> np.ndarray:
        """(m, 5) feature matrix, columns in field order."""
        return np.column_stack([self.linearity, self.planarity, self.scattering, self.verticality, np.log1p(self.neighbours)])


def neighbourhood_matrix(
    nodes: np.ndarray,
    *,
    radius: float,
    candidates: NodePairs | None = None,
) -> sparse.csr_matrix:
    """(m, m) 0/1 matrix of node pairs within ``radius`` [m], diagonal included, int8.

    ``candidates``: optional ``node_pairs(nodes, r)`` with ``r >= radius``.
    """
    # int8 ones, not float64: the matrix is held through the node analysis, and at a
    # stand-density tile's peak its float64 ones were 16 of every 24 bytes it took; its
    # products with float arrays give the same floats (scipy upcasts the ones to 1.0)
    m = nodes.shape[0]
    found = node_pairs(nodes, radius) if candidates is None else candidates.within(radius)
    return symmetric_csr(found, np.ones(len(found), np.int8), m, diagonal=np.ones(m, np.int8))


def shape_features(nodes: np.ndarray, *, radius: float, adjacency: sparse.csr_matrix | None = None) -> ShapeFeatures:
    """Eigenvalue features of each node's neighbourhood.

    Parameters
    ----------
    nodes : (m, 3) float64 [m]
    radius : float [m] — neighbourhood radius
    adjacency : optional precomputed ``neighbourhood_matrix(nodes, radius=radius)``

    Returns
    -------
    ShapeFeatures
    """
    # Strategy: neighbourhood sums of x, y, z and their products via one sparse product,
    # then batched 3x3 eigen-decompositions.
    m = nodes.shape[0]
    a = adjacency if adjacency is not None else neighbourhood_matrix(nodes, radius=radius)
    c = nodes - nodes.mean(axis=0) if m else nodes
    x, y, z = c[:, 0], c[:, 1], c[:, 2]
    cols = np.column_stack([np.ones(m), x, y, z, x * x, y * y, z * z, x * y, x * z, y * z])
    s = sparse_product(a, cols)
    n = s[:, 0]
    mu = s[:, 1:4] / n[:, None]
    cov = (
        s[:, 4] / n - mu[:, 0] ** 2,
        s[:, 5] / n - mu[:, 1] ** 2,
        s[:, 6] / n - mu[:, 2] ** 2,
        s[:, 7] / n - mu[:, 0] * mu[:, 1],
        s[:, 8] / n - mu[:, 0] * mu[:, 2],
        s[:, 9] / n - mu[:, 1] * mu[:, 2],
    )
    (l3, l2, l1), normal, axis = symmetric_eigen3(*cov)
    l3, l2, l1 = np.clip(l3, 0.0, None), np.clip(l2, 0.0, None), np.clip(l1, 0.0, None)
    few = n < MIN_NEIGHBOURS
    safe = np.where(l1 > 1e-12, l1, 1.0)
    lin = np.where(few, 0.0, (l1 - l2) / safe)
    pla = np.where(few, 0.0, (l2 - l3) / safe)
    sca = np.where(few, 1.0, l3 / safe)
    return ShapeFeatures(lin, pla, sca, np.abs(axis[:, 2]), n, normal)


def symmetric_eigen3(a00, a11, a22, a01, a02, a12):
    """Eigen-decomposition of many symmetric 3x3 matrices, in closed form.

    Parameters
    ----------
    a00, a11, a22, a01, a02, a12 : (m,) float64 — the six distinct entries of each matrix

    Returns
    -------
    (l3, l2, l1) : three (m,) arrays, the eigenvalues in ascending order
    smallest : (m, 3) unit eigenvector of l3 (a surface's normal)
    largest : (m, 3) unit eigenvector of l1 (the principal axis)
        A matrix with equal eigenvalues (e.g. all zero) gets the unit x and z vectors.
    """
    # Strategy: the trigonometric solution of the characteristic cubic (Smith 1961) for
    # the eigenvalues; each eigenvector is the longest cross product of two rows of
    # A - λI (orthogonal to every row). Faster than numpy's batched eigh (one LAPACK call
    # per 3x3 matrix), and its eigenvalues agree with eigh's far below any feature
    # threshold (to ~1e-8 of the largest where two nearly coincide).
    q = (a00 + a11 + a22) / 3.0
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p = np.sqrt((b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * (a01 * a01 + a02 * a02 + a12 * a12)) / 6.0)
    ps = np.where(p > 0.0, p, 1.0)
    det = b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02) + a02 * (a01 * a12 - b11 * a02)
    phi = np.arccos(np.clip(det / (2.0 * ps**3), -1.0, 1.0)) / 3.0
    l1 = q + 2.0 * p * np.cos(phi)
    l3 = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    l2 = 3.0 * q - l1 - l3

    def eigenvector(lam: np.ndarray, fallback: int) -> np.ndarray:
        rows = ((a00 - lam, a01, a02), (a01, a11 - lam, a12), (a02, a12, a22 - lam))
        best = np.zeros((lam.shape[0], 3))
        best_len = np.full(lam.shape[0], -1.0)
        for i, j in ((0, 1), (0, 2), (1, 2)):
            u, v = rows[i], rows[j]
            c = np.column_stack([u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]])
            length = c[:, 0] ** 2 + c[:, 1] ** 2 + c[:, 2] ** 2
            longer = length > best_len
            best[longer], best_len[longer] = c[longer], length[longer]
        norm = np.sqrt(best_len)
        out = best / np.where(norm > 0.0, norm, 1.0)[:, None]
        out[norm <= 0.0] = np.eye(3)[fallback]
        return out

    return (l3, l2, l1), eigenvector(l3, 0), eigenvector(l1, 2)
