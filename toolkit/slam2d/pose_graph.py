"""Sparse SE(2) pose graph solved by Levenberg-Marquardt on scipy.sparse normal equations.

Vertices are planar poses (x, y, theta) in the world frame: scan nodes and submaps alike.
An edge (i, j, z) says "vertex j seen from vertex i is z" with the residual of
Cartographer's sparse pose adjustment (``SpaCostFunction2D``)::

    e = [ R(theta_i)^T (t_j - t_i) - z_t ,  wrap(theta_j - theta_i - z_theta) ]

scaled by sqrt(translation_weight) and sqrt(rotation_weight). Loop-closure edges carry a
robust loss (Huber or Cauchy on the scaled residual norm, applied by iteratively
reweighted least squares) so that a stray wrong closure is outvoted instead of bending
the map (Huber bounds a closure's pull, it does not remove it: a consistent set of wrong
ones, a corridor's doors one spacing off, is kept out by the loop closer's ambiguity test).

Why our own solver rather than ``scipy.optimize.least_squares``: that routine applies one
loss to every residual (we need plain squares on odometry and scan-matching edges and a
robust loss on closures only) and, with a sparse Jacobian, solves the trust-region step
iteratively with LSMR, which is slow on the long chains of a pose graph; a direct sparse
factorisation of the 3V x 3V normal equations (SuperLU, symmetric mode) with analytic
Jacobians takes milliseconds for thousands of vertices. gtsam would do the same but is a
heavy optional dependency for a 2D problem this small.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from toolkit.geometry import wrap_angle

ROBUST_NONE = 0
ROBUST_HUBER = 1
ROBUST_CAUCHY = 2
_ROBUST = {"none": ROBUST_NONE, "huber": ROBUST_HUBER, "cauchy": ROBUST_CAUCHY}


@dataclass
class OptimizationReport:
    iterations: int
    initial_cost: float
    final_cost: float
    seconds: float
    outlier_edges: int  # robust edges whose loss is in its down-weighted regime


class PoseGraph2D:
    """Vertices and edges stored in growable numpy arrays for vectorised solves."""

    def __init__(self) -> None:
        self._poses = np.zeros((64, 3))  # [V, 3]
        self._fixed = np.zeros(64, bool)  # [V]
        self.num_vertices = 0
        self._ei = np.zeros(256, np.int64)
        self._ej = np.zeros(256, np.int64)
        self._z = np.zeros((256, 3))  # [E, 3] measured relative pose
        self._w = np.zeros((256, 3))  # [E, 3] weights (tx, ty, theta)
        self._robust = np.zeros(256, np.int8)
        self._scale = np.ones(256)
        self._kind = np.zeros(256, np.int16)  # caller's tag (intra, odometry, loop, ...)
        self.num_edges = 0

    # ------------------------------------------------------------------ building

    @property
    def poses(self) -> np.ndarray:
        """[V, 3] current estimates (a view: write through ``set_pose``)."""
        return self._poses[: self.num_vertices]

    def add_vertex(self, pose: np.ndarray, fixed: bool = False) -> int:
        if self.num_vertices == len(self._poses):
            self._poses = np.concatenate([self._poses, np.zeros_like(self._poses)])
            self._fixed = np.concatenate([self._fixed, np.zeros_like(self._fixed)])
        v = self.num_vertices
        self._poses[v] = pose
        self._fixed[v] = fixed
        self.num_vertices += 1
        return v

    def set_pose(self, v: int, pose: np.ndarray) -> None:
        self._poses[v] = pose

    def set_fixed(self, v: int, fixed: bool = True) -> None:
        self._fixed[v] = fixed

    def add_edge(
        self,
        i: int,
        j: int,
        z: np.ndarray,
        translation_weight: float,
        rotation_weight: float,
        robust: str = "none",
        robust_scale: float = 1.0,
        kind: int = 0,
    ) -> int:
        """Add the constraint ``between(pose_i, pose_j) == z``; returns the edge index."""
        if self.num_edges == len(self._ei):
            grow = len(self._ei)
            self._ei = np.concatenate([self._ei, np.zeros(grow, np.int64)])
            self._ej = np.concatenate([self._ej, np.zeros(grow, np.int64)])
            self._z = np.concatenate([self._z, np.zeros((grow, 3))])
            self._w = np.concatenate([self._w, np.zeros((grow, 3))])
            self._robust = np.concatenate([self._robust, np.zeros(grow, np.int8)])
            self._scale = np.concatenate([self._scale, np.ones(grow)])
            self._kind = np.concatenate([self._kind, np.zeros(grow, np.int16)])
        e = self.num_edges
        self._ei[e], self._ej[e] = i, j
        self._z[e] = z
        self._w[e] = (translation_weight, translation_weight, rotation_weight)
        self._robust[e] = _ROBUST[robust]
        self._scale[e] = robust_scale
        self._kind[e] = kind
        self.num_edges += 1
        return e

    def edges(self, kind: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(i [E], j [E], z [E, 3]) of all edges or those of one kind."""
        n = self.num_edges
        m = slice(None) if kind is None else self._kind[:n] == kind
        return self._ei[:n][m], self._ej[:n][m], self._z[:n][m]

    # ------------------------------------------------------------------ residuals

    def _residuals(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Unscaled errors [E, 3] and squared scaled norms [E]."""
        n = self.num_edges
        i, j = self._ei[:n], self._ej[:n]
        xi, xj = X[i], X[j]
        c, s = np.cos(xi[:, 2]), np.sin(xi[:, 2])
        dx = xj[:, 0] - xi[:, 0]
        dy = xj[:, 1] - xi[:, 1]
        e = np.empty((n, 3))
        e[:, 0] = c * dx + s * dy - self._z[:n, 0]
        e[:, 1] = -s * dx + c * dy - self._z[:n, 1]
        e[:, 2] = wrap_angle(xj[:, 2] - xi[:, 2] - self._z[:n, 2])
        sq = np.einsum("ek,ek->e", e * self._w[:n], e)
        return e, sq

    def _robust_rho(self, sq: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(rho(s) [E], rho'(s) [E]) of each edge's loss on its squared scaled norm."""
        n = self.num_edges
        kind = self._robust[:n]
        d2 = self._scale[:n] ** 2
        rho = sq.copy()
        drho = np.ones_like(sq)
        hub = (kind == ROBUST_HUBER) & (sq > d2)
        if hub.any():
            r = np.sqrt(sq[hub])
            d = np.sqrt(d2[hub])
            rho[hub] = 2.0 * d * r - d2[hub]
            drho[hub] = d / r
        cau = kind == ROBUST_CAUCHY
        if cau.any():
            rho[cau] = d2[cau] * np.log1p(sq[cau] / d2[cau])
            drho[cau] = 1.0 / (1.0 + sq[cau] / d2[cau])
        return rho, drho

    def cost(self) -> float:
        _, sq = self._residuals(self.poses)
        return float(self._robust_rho(sq)[0].sum())

    def outliers(self) -> np.ndarray:
        """[E] bool: robust edges currently in the down-weighted part of their loss."""
        _, sq = self._residuals(self.poses)
        n = self.num_edges
        return (self._robust[:n] != ROBUST_NONE) & (sq > self._scale[:n] ** 2)

    # ------------------------------------------------------------------ solve

    def optimize(self, max_iterations: int = 20, tolerance: float = 1e-6) -> OptimizationReport:
        """Levenberg-Marquardt with IRLS robust weights; vertices marked fixed stay put."""
        import time

        t0 = time.perf_counter()
        V, n = self.num_vertices, self.num_edges
        X = self.poses.copy()
        if n == 0 or V < 2:
            return OptimizationReport(0, 0.0, 0.0, 0.0, 0)
        fixed = self._fixed[:V].copy()
        if not fixed.any():
            fixed[0] = True  # gauge freedom: pin the first vertex
        var = np.full(V, -1, np.int64)
        var[~fixed] = np.arange(int((~fixed).sum()))
        nv = int((~fixed).sum())
        i, j = self._ei[:n], self._ej[:n]
        w = self._w[:n]
        vi, vj = var[i], var[j]

        # Sparsity pattern of H (3x3 blocks ii, ij, ji, jj per edge), built once.
        bi = np.concatenate([vi, vi, vj, vj])
        bj = np.concatenate([vi, vj, vi, vj])
        ok = (bi >= 0) & (bj >= 0)
        rr = (3 * bi[ok])[:, None, None] + np.arange(3)[None, :, None]
        cc = (3 * bj[ok])[:, None, None] + np.arange(3)[None, None, :]
        rows = np.broadcast_to(rr, (ok.sum(), 3, 3)).ravel()
        cols = np.broadcast_to(cc, (ok.sum(), 3, 3)).ravel()

        e, sq = self._residuals(X)
        rho, drho = self._robust_rho(sq)
        cost0 = cost = float(rho.sum())
        lam = 1e-4
        it = 0
        for _ in range(max_iterations):
            it += 1
            xi, xj = X[i], X[j]
            c, s = np.cos(xi[:, 2]), np.sin(xi[:, 2])
            dx = xj[:, 0] - xi[:, 0]
            dy = xj[:, 1] - xi[:, 1]
            # Jacobians [E, 3(res), 3(var)] w.r.t. vertex i and vertex j.
            Ji = np.zeros((n, 3, 3))
            Ji[:, 0, 0], Ji[:, 0, 1], Ji[:, 0, 2] = -c, -s, -s * dx + c * dy
            Ji[:, 1, 0], Ji[:, 1, 1], Ji[:, 1, 2] = s, -c, -c * dx - s * dy
            Ji[:, 2, 2] = -1.0
            Jj = np.zeros((n, 3, 3))
            Jj[:, 0, 0], Jj[:, 0, 1] = c, s
            Jj[:, 1, 0], Jj[:, 1, 1] = -s, c
            Jj[:, 2, 2] = 1.0
            W = w * drho[:, None]  # [E, 3] IRLS weights
            WJi = Ji * W[:, :, None]
            WJj = Jj * W[:, :, None]
            Hii = np.einsum("eki,ekj->eij", Ji, WJi)
            Hij = np.einsum("eki,ekj->eij", Ji, WJj)
            Hjj = np.einsum("eki,ekj->eij", Jj, WJj)
            gi = np.einsum("eki,ek->ei", WJi, e)
            gj = np.einsum("eki,ek->ei", WJj, e)
            blocks = np.concatenate([Hii, Hij, np.swapaxes(Hij, 1, 2), Hjj])[ok]
            H = sp.csc_matrix((blocks.ravel(), (rows, cols)), shape=(3 * nv, 3 * nv))
            g = np.zeros(3 * nv)
            mi, mj = vi >= 0, vj >= 0
            np.add.at(g, (3 * vi[mi])[:, None] + np.arange(3), gi[mi])
            np.add.at(g, (3 * vj[mj])[:, None] + np.arange(3), gj[mj])
            diag = H.diagonal()
            improved = False
            while lam < 1e8:
                A = H + sp.diags(lam * np.maximum(diag, 1e-9), format="csc")
                try:
                    # The damped normal matrix is symmetric positive definite: SuperLU in
                    # symmetric mode without pivoting (a Cholesky-like LU on a minimum-degree
                    # ordering of A + A^T) is 15-20x faster than spsolve's partial pivoting
                    # on Killian's final graph (12k unknowns: 0.05 s instead of 0.95 s CPU).
                    step = spla.splu(A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                                     options={"SymmetricMode": True}).solve(-g)
                except RuntimeError:
                    lam *= 10.0
                    continue
                if not np.all(np.isfinite(step)):  # no pivoting: guard a near-singular A
                    lam *= 10.0
                    continue
                Xn = X.copy()
                Xn[~fixed] += step.reshape(-1, 3)
                Xn[:, 2] = wrap_angle(Xn[:, 2])
                en, sqn = self._residuals(Xn)
                rhon, drhon = self._robust_rho(sqn)
                cn = float(rhon.sum())
                if cn < cost:
                    X, e, sq, rho, drho = Xn, en, sqn, rhon, drhon
                    rel = (cost - cn) / max(cost, 1e-12)
                    cost = cn
                    lam = max(lam * 0.2, 1e-9)
                    improved = True
                    break
                lam *= 10.0
            if not improved or rel < tolerance or np.abs(step).max() < 1e-9:
                break
        self._poses[:V] = X
        n_out = int(((self._robust[:n] != ROBUST_NONE) & (sq > self._scale[:n] ** 2)).sum())
        return OptimizationReport(it, cost0, cost, time.perf_counter() - t0, n_out)
