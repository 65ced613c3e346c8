"""Local shape features of graph nodes (the paper's enrichment, after Poux & Billen 2019).

Eigenvalue features of the neighbourhood covariance tell a branch (linear), a surface
(planar: boxes, vehicles, walls) and foliage (scattered) apart.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse

from pipeline.graph import node_pairs, pairs_within, symmetric_csr


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
    candidates: tuple[np.ndarray, np.ndarray] | None = None,
) -> sparse.csr_matrix:
    """(m, m) 0/1 matrix of node pairs within ``radius`` [m], diagonal included.

    ``candidates``: optional ``node_pairs(nodes, r)`` with ``r >= radius``.
    """
    m = nodes.shape[0]
    pairs, _ = node_pairs(nodes, radius) if candidates is None else pairs_within(candidates, radius)
    return symmetric_csr(pairs, np.ones(pairs.shape[0]), m, diagonal=np.ones(m))


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
    s = a @ cols
    n = s[:, 0]
    mu = s[:, 1:4] / n[:, None]
    cov = np.empty((m, 3, 3))
    cov[:, 0, 0] = s[:, 4] / n - mu[:, 0] ** 2
    cov[:, 1, 1] = s[:, 5] / n - mu[:, 1] ** 2
    cov[:, 2, 2] = s[:, 6] / n - mu[:, 2] ** 2
    cov[:, 0, 1] = cov[:, 1, 0] = s[:, 7] / n - mu[:, 0] * mu[:, 1]
    cov[:, 0, 2] = cov[:, 2, 0] = s[:, 8] / n - mu[:, 0] * mu[:, 2]
    cov[:, 1, 2] = cov[:, 2, 1] = s[:, 9] / n - mu[:, 1] * mu[:, 2]
    w, v = np.linalg.eigh(cov) if m else (np.zeros((0, 3)), np.zeros((0, 3, 3)))
    w = np.clip(w, 0.0, None)
    l3, l2, l1 = w[:, 0], w[:, 1], w[:, 2]
    few = n < 4
    safe = np.where(l1 > 1e-12, l1, 1.0)
    lin = np.where(few, 0.0, (l1 - l2) / safe)
    pla = np.where(few, 0.0, (l2 - l3) / safe)
    sca = np.where(few, 1.0, l3 / safe)
    vert = np.abs(v[:, 2, 2]) if m else np.zeros(0)
    normal = v[:, :, 0] if m else np.zeros((0, 3))
    return ShapeFeatures(lin, pla, sca, vert, n, normal)
