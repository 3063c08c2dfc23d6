"""Local refinement steps for ICP, as plug-ins: point-to-point, point-to-plane, plane-to-plane (GICP).

Transforms follow :mod:`vrnet_ext.geometry.transforms` (``T_target_source``, y = R x + t, float64 4x4).

Each step is built once per pair (:meth:`prepare` computes what it needs of the fixed clouds:
normals, covariances) and then asked, once per ICP iteration, for the next transform given the
current one and the correspondences (source index, target index) within reach:

* ``point_to_point``: the weighted Kabsch solution on the pairs (closed form, absolute);
* ``point_to_plane``: one Gauss-Newton step on sum_i (n_i . (R x_i + t - y_i))^2 with the target
  normals n_i (Chen & Medioni);
* ``gicp``: one Gauss-Newton step on sum_i r_i^T (C_y + R C_x R^T)^-1 r_i, r_i = R x_i + t - y_i,
  with each point's covariance from its ``neighbours`` nearest points, flattened to a plane
  (eigenvalues 1, 1, 1e-3 along the normal; Segal, Haehnel & Thrun 2009).

Gauss-Newton steps perturb on the left, T <- exp(xi) T with xi = (omega, v): the residual's
Jacobian at the moved point p is [-[p]_x | I].
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from vrnet_ext import ops
from vrnet_ext.geometry.transforms import apply
from vrnet_ext.geometry.lie import skew
from vrnet_ext.names import ICP_STEPS

PLANE_FLATNESS = 1e-3  # GICP: the smallest covariance eigenvalue, relative to the others


def se3_exp(xi: torch.Tensor) -> torch.Tensor:
    """(6,) twist (omega, v) -> (4, 4) rigid transform (Rodrigues; exact for any angle)."""
    omega, v = xi[:3], xi[3:]
    angle = omega.norm()
    K = skew(omega[None])[0]
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device)
    if float(angle) < 1e-12:
        R, V = eye + K, eye + 0.5 * K
    else:
        a, b = torch.sin(angle) / angle, (1 - torch.cos(angle)) / angle ** 2
        c = (angle - torch.sin(angle)) / angle ** 3
        R, V = eye + a * K + b * K @ K, eye + b * K + c * K @ K
    T = torch.eye(4, dtype=xi.dtype, device=xi.device)
    T[:3, :3], T[:3, 3] = R, V @ v
    return T


def plane_covariances(points: torch.Tensor, neighbours: int) -> torch.Tensor:
    """points (N, 3) -> (N, 3, 3) GICP's plane covariances: the covariance of each point with its
    nearest ``neighbours`` keeps its eigenvectors and gets eigenvalues (PLANE_FLATNESS, 1, 1), i.e.
    ``I - (1 - PLANE_FLATNESS) n n^T`` with n the normal (smallest eigenvector, ``ops.normals``)."""
    return flat_covariances(ops.normals(points, neighbours))


def flat_covariances(normals: torch.Tensor) -> torch.Tensor:
    """normals (N, 3) -> (N, 3, 3) ``I - (1 - PLANE_FLATNESS) n n^T`` (:func:`plane_covariances`)."""
    eye = torch.eye(3, dtype=normals.dtype, device=normals.device)
    return eye - (1.0 - PLANE_FLATNESS) * normals[:, :, None] * normals[:, None, :]


def symmetric_inverse(M: torch.Tensor) -> torch.Tensor:
    """(P, 3, 3) symmetric invertible matrices -> their inverses, by the adjugate (elementwise over
    P; the batched LAPACK call costs ~4 us per 3x3 matrix)."""
    a, b, c = M[:, 0, 0], M[:, 0, 1], M[:, 0, 2]
    d, e, f = M[:, 1, 1], M[:, 1, 2], M[:, 2, 2]
    A, B, C = d * f - e * e, c * e - b * f, b * e - c * d
    D, E, F = a * f - c * c, b * c - a * e, a * d - b * b
    inverse = torch.stack([A, B, C, B, D, E, C, E, F], dim=-1).view(-1, 3, 3)
    return inverse / (a * A + b * B + c * C)[:, None, None]


GRAM_ROWS = 256  # rows per partial product of the normal equations (fixed_order_product)


def fixed_order_product(left: torch.Tensor, right: torch.Tensor) -> torch.Tensor:
    """left (R, a), right (R, b) -> left^T right (a, b) for b > 1, summed over blocks of
    :data:`GRAM_ROWS` rows in one order whatever the thread count: one long matrix product is split
    across threads by the BLAS library (Intel's MKL splits the sum over rows beyond ~2,000), and its
    last bits would change with the number of threads (a matrix-vector product, b = 1, splits even
    short sums: use torch's sum there)."""
    pad = (-left.shape[0]) % GRAM_ROWS
    if pad:
        left, right = F.pad(left, (0, 0, 0, pad)), F.pad(right, (0, 0, 0, pad))
    blocks = left.shape[0] // GRAM_ROWS
    return torch.bmm(left.reshape(blocks, GRAM_ROWS, -1).transpose(1, 2), right.reshape(blocks, GRAM_ROWS, -1)).sum(0)


def gauss_newton_step(J: torch.Tensor, residual: torch.Tensor, weights: torch.Tensor, T: torch.Tensor,
                      information: torch.Tensor | None = None) -> torch.Tensor:
    """J (P, m, 6), residual (P, m), weights (P,), optional information matrices (P, m, m) (identity
    when None) -> exp(xi) T, xi minimising sum_p w_p (r_p + J_p xi)^T Info_p (r_p + J_p xi)."""
    weighted = J * weights[:, None, None]
    informed = J if information is None else information @ J  # Info J, (P, m, 6)
    H = fixed_order_product(weighted.reshape(-1, 6), informed.reshape(-1, 6))
    b = (informed * (residual * weights[:, None])[..., None]).reshape(-1, 6).sum(0)  # torch's sums keep one order
    xi = -torch.linalg.solve(H + 1e-12 * torch.eye(6, dtype=H.dtype, device=H.device), b)
    return se3_exp(xi) @ T


class IcpStep:
    """Base: ``prepare(src, tgt)`` once, ``step(T, src_idx, tgt_idx, weights)`` per iteration."""

    name = "base"

    def prepare(self, src: torch.Tensor, tgt: torch.Tensor) -> None:
        self.src, self.tgt = src, tgt

    def step(self, T: torch.Tensor, src_idx: torch.Tensor, tgt_idx: torch.Tensor,
             weights: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError


class PointToPoint(IcpStep):
    """ICP's step by weighted Procrustes between the matched points (Besl-McKay)."""

    name = "point_to_point"

    def step(self, T, src_idx, tgt_idx, weights):
        R, t = ops.kabsch(self.src[None, src_idx], self.tgt[None, tgt_idx], weights[None])
        new = torch.eye(4, dtype=T.dtype, device=T.device)
        new[:3, :3], new[:3, 3] = R[0], t[0]
        return new


class PointToPlane(IcpStep):
    """ICP's Gauss-Newton step on distances along the target's normals (from ``neighbours`` points)."""

    name = "point_to_plane"

    def __init__(self, neighbours: int = 20) -> None:
        self.neighbours = neighbours

    def prepare(self, src, tgt):
        super().prepare(src, tgt)
        self.tgt_normals = ops.normals(tgt, self.neighbours)  # the compiled op; their sign does not matter here

    def step(self, T, src_idx, tgt_idx, weights):
        moved = apply(T, self.src[src_idx])
        normals = self.tgt_normals[tgt_idx]
        residual = ((moved - self.tgt[tgt_idx]) * normals).sum(-1, keepdim=True)  # (P, 1)
        J = torch.cat([torch.linalg.cross(moved, normals), normals], -1)[:, None]  # (P, 1, 6)
        return gauss_newton_step(J, residual, weights, T)


class Gicp(IcpStep):
    """Generalized ICP's Gauss-Newton step: residuals weighted by the inverse of both points' plane
    covariances (from ``neighbours`` points), the source's rotated into the target frame."""

    name = "gicp"

    def __init__(self, neighbours: int = 20) -> None:
        self.neighbours = neighbours

    def prepare(self, src, tgt):
        super().prepare(src, tgt)
        self.src_cov = plane_covariances(src, self.neighbours)
        self.tgt_normals = ops.normals(tgt, self.neighbours)  # kept: the degeneracy check reads them too
        self.tgt_cov = flat_covariances(self.tgt_normals)

    def step(self, T, src_idx, tgt_idx, weights):
        R = T[:3, :3]
        moved = apply(T, self.src[src_idx])
        residual = moved - self.tgt[tgt_idx]  # (P, 3)
        information = symmetric_inverse(self.tgt_cov[tgt_idx] + R @ self.src_cov[src_idx] @ R.T)
        J = torch.cat([-skew(moved), torch.eye(3, dtype=T.dtype, device=T.device).expand(len(moved), 3, 3)], -1)
        return gauss_newton_step(J, residual, weights, T, information)


def make_icp_step(name: str, neighbours: int = 20) -> IcpStep:
    """The ICP step called ``name`` (one of ICP_STEPS)."""
    if name == "point_to_point":
        return PointToPoint()
    if name == "point_to_plane":
        return PointToPlane(neighbours)
    if name == "gicp":
        return Gicp(neighbours)
    raise ValueError(f"step must be one of {ICP_STEPS}, got {name!r}")
