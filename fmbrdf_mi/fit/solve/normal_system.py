"""The normal equations of the joint material + normals refinement (:mod:`fmbrdf_mi.fit.api.normal_joint`).

Unknowns: p material values and two tangent-plane values per pixel.  With
J = [J_m | J_n] the Jacobian of the residuals r (data rows, then the
smoothness prior's rows), the Gauss-Newton system of (1/2) r.r is

    [H_mm  H_mn] [dm]     [g_m]
    [H_nm  H_nn] [dn] = - [g_n]

* H_mm = J_m^T J_m (p x p, dense: p is 6 for the FMBRDF);
* J_n: a polariser sample of pixel i is modelled at its own point, whose
  normal is the bilinear interpolation of the normal map there, so its row
  depends on the normals of at most 4 pixels (i and 3 neighbours; only i
  for samples at the centre; on the region's border a corner outside it is
  extrapolated from i and the pixel opposite, so a row lists Q = 8 terms,
  repeated pixels summed; -1 in ``pix`` marks a corner held fixed): kept as (pixel, value)
  lists, never as a matrix;
* H_nn = J_n^T J_n + w P: the data's part couples 8-neighbours, P is the
  prior's (first or second differences along rows and columns, projected
  on each pixel's tangent plane), w the prior's weight.

H_nn is never formed: :class:`NormalBlock` applies it (O(pixels) per
product) and solves with it by conjugate gradients preconditioned by its
2 x 2 diagonal blocks (the data's own block + the prior's, a multiple of I:
the tangent bases are orthonormal),
several right-hand sides at once.  The full system is solved by the Schur
complement onto the material, S = H_mm - H_mn H_nn^-1 H_nm (the
bundle-adjustment reduction): p + 1 solves with H_nn, then a p x p one.
The material's covariance (:func:`material_covariance`) is the sandwich of
the penalised likelihood, with the normals free.  NumPy only: no
sparse-matrix library.
"""
from __future__ import annotations

import numpy as np


def data_products(pix, val, Jm, r, N):
    """H_mm, H_mn (p, N, 2), g_m, g_n (N, 2) of the data rows.

    ``pix`` (m, Q): the unknown pixels each residual row depends on (-1: a
    fixed pixel), ``val`` (m, Q, 2) the row's derivatives with respect to
    their two tangent unknowns, ``Jm`` (m, p) the material columns, ``r`` (m,).
    """
    p = Jm.shape[1]
    ok = pix >= 0
    q = np.where(ok, pix, 0)
    v = np.where(ok[..., None], val, 0.0)
    Hmn = np.zeros((N, 2, p))
    np.add.at(Hmn, q.ravel(), (v[:, :, :, None] * Jm[:, None, None, :]).reshape(-1, 2, p))
    gn = np.zeros((N, 2))
    np.add.at(gn, q.ravel(), (v * r[:, None, None]).reshape(-1, 2))
    return Jm.T @ Jm, np.ascontiguousarray(Hmn.transpose(2, 0, 1)), Jm.T @ r, gn


class NormalBlock:
    """H_nn = J_n^T J_n (data) + w P (prior) (+ damping mu diag) as an operator on (N, 2, R) arrays.

    ``pix``, ``val``: the data rows' dependence on the unknown normals
    (:func:`data_products`); ``stencils`` (E, S) pixel indices and ``coef``
    (S,): the prior's residuals sqrt(w) sum_s coef_s n_{stencil_s} (first
    differences: (1, -1); second: (1, -2, 1)); ``t1``, ``t2`` (N, 3): each
    pixel's tangent basis; ``w``: the prior's weight.
    """

    def __init__(self, pix, val, stencils, coef, t1, t2, w, mu=0.0):
        self.N = len(t1)
        ok = pix >= 0
        self.q = np.where(ok, pix, 0)
        self.v = np.where(ok[..., None], val, 0.0)
        self.st, self.coef = stencils, np.asarray(coef, float)
        self.t1, self.t2, self.w = t1, t2, float(w)
        self.csum = np.zeros(self.N)
        if len(stencils):
            np.add.at(self.csum, stencils.ravel(), np.tile(self.coef ** 2, len(stencils)))
        diag = np.zeros((self.N, 2, 2))
        np.add.at(diag, self.q.ravel(), np.einsum("mqa,mqb->mqab", self.v, self.v).reshape(-1, 2, 2))
        diag[:, 0, 0] += self.w * self.csum      # the tangent bases are orthonormal
        diag[:, 1, 1] += self.w * self.csum
        d = np.stack([diag[:, 0, 0], diag[:, 1, 1]], 1)
        # Marquardt damping on the diagonal of H_nn; a tiny ridge keeps a pixel with neither data nor
        # neighbours from making the system singular
        self.ridge = mu * np.maximum(d, 1e-12) + 1e-12 * max(float(d.max()), 1e-300)
        diag[:, 0, 0] += self.ridge[:, 0]
        diag[:, 1, 1] += self.ridge[:, 1]
        self.pre = np.linalg.inv(diag)

    def data_product(self, x):
        """J_n x (data rows only), x (N, 2, R) -> (m, R)."""
        return np.einsum("mqa,mqar->mr", self.v, x[self.q])

    def apply(self, x):
        """H_nn x for x (N, 2, R)."""
        jx = np.einsum("mqa,mqar->mr", self.v, x[self.q])                       # J_n x, (m, R)
        y = np.zeros_like(x)
        np.add.at(y, self.q.ravel(), (self.v[:, :, :, None] * jx[:, None, None, :]).reshape(-1, 2, x.shape[2]))
        y += self.ridge[:, :, None] * x
        if len(self.st) and self.w:
            # the prior's residual change: sum_s coef_s (tangent displacement of pixel s), a 3-vector
            d = 0.0
            for s, c in enumerate(self.coef):
                k = self.st[:, s]
                d = d + c * (self.t1[k][:, :, None] * x[k, 0][:, None, :]
                             + self.t2[k][:, :, None] * x[k, 1][:, None, :])
            d = self.w * d                                                   # (E, 3, R)
            for s, c in enumerate(self.coef):
                k = self.st[:, s]
                g = np.stack([np.einsum("ec,ecr->er", self.t1[k], d), np.einsum("ec,ecr->er", self.t2[k], d)], 1)
                np.add.at(y, k, c * g)
        return y

    def solve(self, b, rtol=1e-10, max_iter=5000):
        """x with H_nn x = b, b (N, 2, R): preconditioned conjugate gradients, column by column in parallel."""
        x = np.zeros_like(b)
        r = b.copy()
        z = np.einsum("nab,nbr->nar", self.pre, r)
        p = z.copy()
        rz = np.einsum("nar,nar->r", r, z)
        bn = np.sqrt(np.einsum("nar,nar->r", b, b))
        bn[bn == 0] = 1.0
        for _ in range(max_iter):
            Ap = self.apply(p)
            pAp = np.einsum("nar,nar->r", p, Ap)
            alpha = np.where(pAp > 0, rz / np.where(pAp > 0, pAp, 1.0), 0.0)
            x += alpha * p
            r -= alpha * Ap
            if np.all(np.sqrt(np.einsum("nar,nar->r", r, r)) <= rtol * bn):
                break
            z = np.einsum("nab,nbr->nar", self.pre, r)
            rz_new = np.einsum("nar,nar->r", r, z)
            beta = np.where(rz > 0, rz_new / np.where(rz > 0, rz, 1.0), 0.0)
            p = z + beta * p
            rz = rz_new
        return x


def solve_step(Hmm, Hmn, Hnn, gm, gn, mu):
    """The damped Gauss-Newton step (dm (p,), dn (N, 2)) by the Schur complement onto the material.

    ``Hmn`` (p, N, 2); ``Hnn`` a :class:`NormalBlock` built with damping ``mu``; ``gn`` (N, 2).
    """
    p = len(gm)
    rhs = np.concatenate([Hmn.transpose(1, 2, 0), gn[:, :, None]], axis=2)      # (N, 2, p + 1)
    X = Hnn.solve(rhs)
    Hmn2 = Hmn.reshape(p, -1)
    S = Hmm + np.diag(mu * np.maximum(np.diag(Hmm), 1e-12)) - Hmn2 @ X[:, :, :p].reshape(-1, p)
    dm = np.linalg.solve(S, -gm + Hmn2 @ X[:, :, p].ravel())
    dn = Hnn.solve((-gn - np.einsum("pna,p->na", Hmn, dm))[:, :, None])[:, :, 0]
    return dm, dn


def schur(Hmm, Hmn, Hnn):
    """H_mm - H_mn H_nn^-1 H_nm (undamped ``Hnn``): the material's information with the normals free."""
    p = len(Hmm)
    X = Hnn.solve(np.ascontiguousarray(Hmn.transpose(1, 2, 0)))
    S = Hmm - Hmn.reshape(p, -1) @ X.reshape(-1, p)
    return 0.5 * (S + S.T)


def material_covariance(Hmm, Hmn, Hnn, Jm):
    """Covariance of the material (p x p, in the unknowns' units) with the normals free: the sandwich
    [H^-1 F H^-1]_mm of the penalised likelihood, F = J^T J of the data rows only (``Hnn`` undamped).

    The prior is a regulariser, not information about the data: counting it
    in the covariance (the inverse Schur complement alone) understates the
    material's spread when it constrains the normals.  The material rows of
    H^-1 are Y_m = S^-1 and Y_n = -H_nn^-1 H_nm S^-1; then C = (J Y)^T (J Y).
    """
    Si = np.linalg.inv(schur(Hmm, Hmn, Hnn))
    Yn = -Hnn.solve(np.einsum("pna,pq->naq", Hmn, Si))                        # (N, 2, p)
    JY = Jm @ Si + Hnn.data_product(Yn)
    C = JY.T @ JY
    return 0.5 * (C + C.T)
