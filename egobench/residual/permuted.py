"""`frame_slopes` of velocity-driven regressors under the placebos' permuted velocities, from tables.

A motion-driven cause's regressors are polynomials in each pixel's image velocity (vx, vy) with
coefficient maps from the frame's own prediction (gradients, Hessian, row times): regressor k =
sum_j c_kj * vx^a_j * vy^b_j (`GeometricCause.velocity_basis`). Its placebos pair frame i's
prediction with frame perm[i]'s velocity. Every moment `frame_slopes` needs is then a sum over pixels
of a map of frame i times a monomial of frame g's velocity, for all (i, g) at once one [F, P] x [P, F]
product per map; a placebo reads F entries of each table instead of re-forming [F, H, W, 3] arrays
(the same sums in another order: t agrees to ~1e-12 relative).
"""

from __future__ import annotations

import numpy as np

from egobench.residual.estimation import masked_moments, normal_equations_from_moments, slopes_from_normal_equations

#: One regressor: [(coefficient map [F, H, W, C], power of vx, power of vy)], summed.
Basis = list[list[tuple[np.ndarray, int, int]]]


def _monomial(vx: np.ndarray, vy: np.ndarray, a: int, b: int) -> np.ndarray:
    """vx^a vy^b [F, P] (a, b >= 0)."""
    out = np.ones_like(vx)
    for _ in range(a):
        out = out * vx
    for _ in range(b):
        out = out * vy
    return out


class PermutedVelocitySlopes:
    """`frame_slopes(regressors, p, r, mask)` for regressors built with a permutation of the frames'
    velocities. basis: the regressors' `Basis`; velocity [F, H, W, 2] px/s; predicted, residual
    [F, H, W, C]; mask [F, H, W, C] bool."""

    def __init__(self, basis: Basis, velocity: np.ndarray, predicted: np.ndarray, residual: np.ndarray,
                 mask: np.ndarray) -> None:
        F = velocity.shape[0]
        self.k = len(basis)
        m = mask.astype(np.float64)
        p, y = predicted.astype(np.float64), residual.astype(np.float64)
        vx, vy = (velocity[..., c].reshape(F, -1).astype(np.float64) for c in (0, 1))
        mono = {}

        def table(weight: np.ndarray, a: int, b: int) -> np.ndarray:
            """[F, F]: entry (i, g) = sum over frame i's pixels of weight[i] (summed over channels) x
            frame g's vx^a vy^b."""
            if (a, b) not in mono:
                mono[a, b] = _monomial(vx, vy, a, b)
            return weight.sum(axis=-1).reshape(F, -1) @ mono[a, b].T

        def moment(k: int, w: np.ndarray | float) -> np.ndarray:  # sum m x_k w
            return sum(table(m * c * w, a, b) for c, a, b in basis[k])

        self.lin_x = [moment(k, 1.0) for k in range(self.k)]  # sum m x_k
        self.xp = [moment(k, p) for k in range(self.k)]  # sum m x_k p
        self.xy = [moment(k, y) for k in range(self.k)]  # sum m x_k y
        self.xx = {(k, l): sum(table(m * c * d, a + e, b + f) for c, a, b in basis[k] for d, e, f in basis[l])
                   for k in range(self.k) for l in range(k, self.k)}  # sum m x_k x_l
        self.n = m.reshape(F, -1).sum(axis=1)
        self.lin_py, self.S_py = masked_moments([p.reshape(F, -1), y.reshape(F, -1)], m.reshape(F, -1))  # fixed

    def slopes(self, perm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(est [F, k], info [F, k]) as `frame_slopes` with frame i's regressors built from frame
        perm[i]'s velocity (perm [F] ints)."""
        k, rows = self.k, np.arange(self.n.size)
        lin = np.concatenate([np.stack([t[rows, perm] for t in self.lin_x], axis=1), self.lin_py], axis=1)
        S = np.empty((self.n.size, k + 2, k + 2))
        for (a, b), t in self.xx.items():
            S[:, a, b] = S[:, b, a] = t[rows, perm]
        for a in range(k):
            S[:, a, k] = S[:, k, a] = self.xp[a][rows, perm]
            S[:, a, k + 1] = S[:, k + 1, a] = self.xy[a][rows, perm]
        S[:, k:, k:] = self.S_py
        return slopes_from_normal_equations(*normal_equations_from_moments(lin, S, self.n, k), self.n, k)
