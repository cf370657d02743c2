"""The normal equations of the joint material + normals refinement (:mod:`fmbrdf_mi.fit.api.normal_joint`).

Unknowns: p material values and two tangent-plane values per pixel.  H_nn = J_n^T J_n + w P
(:class:`NormalBlock`, sparse: a sample's normal interpolates a few pixels) is solved by block-Jacobi
preconditioned conjugate gradients, the full Gauss-Newton system by the Schur complement (:func:`solve_step`).
"""
from __future__ import annotations

import copy

import numpy as np


#: Pixel lists whose 2Q x 2Q products :meth:`NormalBlock._assemble` forms at a time.
CHUNK = 1 << 13


def _sums(idx, w, n):
    """(n, C) sums of the rows of ``w`` (k, C) by ``idx`` (k,), each in the rows' order."""
    k, C = w.shape
    flat = (idx[:, None] * C + np.arange(C)).ravel()
    out = np.bincount(flat, weights=np.ascontiguousarray(w, dtype=float).ravel(), minlength=n * C)
    return out.reshape(n, C)


def data_products(pix, val, Jm, r, N):
    """H_mm, H_mn (p, N, 2), g_m, g_n (N, 2) of the data rows: ``pix`` (m, Q) the pixels each row depends on
    (-1: fixed), ``val`` (m, Q, 2) its tangent derivatives, ``Jm`` (m, p) the material columns."""
    p = Jm.shape[1]
    row, slot = np.nonzero((pix >= 0) & np.any(val != 0, axis=2))
    q, v = pix[row, slot], val[row, slot]
    # one column at a time: the same sums in the same order, one column's terms in memory
    Hmn = np.empty((p, N, 2))
    for b in range(p):
        jb = Jm[row, b]
        for a in range(2):
            Hmn[b, :, a] = np.bincount(q, weights=v[:, a] * jb, minlength=N)
    gn = _sums(q, v * r[row][:, None], N)
    return Jm.T @ Jm, Hmn, Jm.T @ r, gn


def _pairs(pix, stencils, N, cache=None):
    """The pixel pairs coupled by H_nn (its sparsity pattern), the last kept in the caller's dict ``cache``.

    A dict: ``G`` distinct pixel lists; ``groups``: (lists, their rows) per row count; ``dsel``: the valid
    (G, Q, Q) term pairs (None: all); ``inv``: the pair index of each valid term pair, each diagonal, each
    stencil pair; ``rows``, ``pos``: each pair's pixel and place in the (N, ``qmax``) neighbour list ``nbr``.
    """
    c = (cache or {}).get("key")
    if c is not None and c[0] == N and np.array_equal(c[1], pix) and np.array_equal(c[2], stencils):
        return cache["value"]
    m, Q = pix.shape
    u, g = np.unique(pix, axis=0, return_inverse=True)
    g = g.ravel()
    order = np.argsort(g, kind="stable")
    cnt = np.bincount(g, minlength=len(u))
    first = np.cumsum(cnt) - cnt
    groups = []
    for c in np.unique(cnt):
        gs = np.nonzero(cnt == c)[0]
        groups.append((gs, order[first[gs][:, None] + np.arange(c)]))
    dsel = ((u[:, :, None] >= 0) & (u[:, None, :] >= 0)).ravel()
    ar = np.arange(N)
    keys = [(u[:, :, None] * N + u[:, None, :]).ravel()[dsel], ar * N + ar]
    if len(stencils):
        keys.append((stencils[:, :, None] * N + stencils[:, None, :]).ravel())
    keys, inv = np.unique(np.concatenate(keys), return_inverse=True)
    rows, cols = keys // N, keys % N
    pos = np.arange(len(keys)) - np.searchsorted(rows, ar)[rows]
    qmax = int(pos.max()) + 1
    nbr = np.zeros((N, qmax), np.int64)
    nbr[rows, pos] = cols
    if dsel.all():
        dsel = None
    value = {"G": len(u), "groups": groups, "dsel": dsel, "inv": inv.ravel(), "rows": rows, "pos": pos,
             "qmax": qmax, "nbr": nbr}
    if cache is not None:
        cache.update(key=(N, pix.copy(), stencils.copy()), value=value)
    return value


class NormalBlock:
    """H_nn = J_n^T J_n + w P (+ damping mu diag) as an operator on (N, 2, R) arrays, stored as 2 x 2 blocks
    in a padded neighbour list; the prior's residuals are sqrt(w) sum_s coef_s n_{stencil_s}, ``t1``, ``t2``
    each pixel's tangent basis, ``cache`` the sparsity pattern kept for the next linearisation."""

    def __init__(self, pix, val, stencils, coef, t1, t2, w, mu=0.0, cache=None):
        self.N = N = len(t1)
        ok = pix >= 0
        self.q = pix if ok.all() else np.where(ok, pix, 0)
        self.v = val if ok.all() else np.where(ok[..., None], val, 0.0)
        self.st, self.coef = stencils, np.asarray(coef, float)
        self.t1, self.t2, self.w = t1, t2, float(w)
        csum = _sums(stencils.ravel(), np.tile(self.coef ** 2, len(stencils))[:, None], N)[:, 0]
        nonzero = np.any(self.v != 0, axis=2)
        row, slot = np.nonzero(ok & nonzero)
        vs = self.v[row, slot]
        diag = _sums(self.q[row, slot], (vs[:, :, None] * vs[:, None, :]).reshape(-1, 4), N).reshape(N, 2, 2)
        del row, slot, vs
        diag[:, [0, 1], [0, 1]] += (self.w * csum)[:, None]      # the tangent bases are orthonormal
        self._diag = diag
        self._assemble(ok, nonzero, cache)
        self._damp(mu)

    def damped(self, mu):
        """The same H_nn with damping ``mu``, sharing the undamped assembly."""
        out = copy.copy(self)
        out._damp(mu)
        return out

    def _damp(self, mu):
        """Add the ridge mu diag(H_nn) (+ a tiny constant) to the diagonal blocks, summed as a damped assembly
        would (bit-identical)."""
        diag, on = self._diag.copy(), (slice(None), [0, 1], [0, 1])     # on: the diagonal of each 2 x 2 block
        # the tiny constant: a pixel with neither data nor neighbours keeps the system regular
        self.ridge = mu * np.maximum(diag[on], 1e-12) + 1e-12 * max(float(diag[on].max()), 1e-300)
        diag[on] += self.ridge
        self.pre = np.linalg.inv(diag)
        N, dg = self.N, self._dg
        ridge = np.stack([self.ridge[:, 0], np.zeros(N), np.zeros(N), self.ridge[:, 1]], 1)
        blocks = _sums(dg["idx"], np.concatenate([dg["data"], ridge, dg["prior"]]), N)
        B = self.B0.copy()
        B[np.arange(N), :, 2 * dg["pos"]] = blocks.reshape(N, 2, 2)[:, :, 0]
        B[np.arange(N), :, 2 * dg["pos"] + 1] = blocks.reshape(N, 2, 2)[:, :, 1]
        self.B = B

    def _assemble(self, ok, nonzero, cache):
        """The undamped 2 x 2 blocks B_ij of H_nn: data rows add v_a v_b^T, prior stencils w c_s c_s' T_s^T T_s'
        (T = [t1 t2]), each summed in the order data, ridge, prior."""
        N, (m, Q) = self.N, self.q.shape
        prior = bool(len(self.st) and self.w)
        sp = _pairs(np.where(ok, self.q, -1), self.st if prior else self.st[:0], N, cache)
        V = self.v.reshape(m, 2 * Q)
        G = sp["G"]
        used = np.empty((G, Q), bool)
        for gs, rs in sp["groups"]:
            used[gs] = np.any(nonzero[rs], axis=1)
        valid = np.ones(G * Q * Q, bool) if sp["dsel"] is None else sp["dsel"]
        keep = valid & (used[:, :, None] & used[:, None, :]).ravel()
        P, inv = len(sp["rows"]), sp["inv"]
        nd = int(valid.sum())
        # W_g = sum of list g's V_r V_r^T, a chunk of lists at a time
        nk = int(np.count_nonzero(keep))
        Wk, pair, done, at0 = np.empty((nk, 4)), np.empty(nk, np.int64), 0, 0
        for g0 in range(0, G, CHUNK):
            g1 = min(g0 + CHUNK, G)
            W = np.empty((g1 - g0, 2 * Q, 2 * Q))
            for gs, rs in sp["groups"]:
                i0, i1 = np.searchsorted(gs, (g0, g1))
                Vg = V[rs[i0:i1]]
                W[gs[i0:i1] - g0] = np.matmul(Vg.transpose(0, 2, 1), Vg)
            v, k = valid[g0 * Q * Q:g1 * Q * Q], keep[g0 * Q * Q:g1 * Q * Q]
            at = done + np.cumsum(v)[k] - 1
            done += int(np.count_nonzero(v))
            g, a, b = np.unravel_index(np.flatnonzero(k), (g1 - g0, Q, Q))
            Wk[at0:at0 + len(g)] = W.reshape(g1 - g0, Q, 2, Q, 2)[g, a, :, b, :].reshape(-1, 4)
            pair[at0:at0 + len(g)] = inv[at]
            at0 += len(g)
        data = _sums(pair, Wk, P)
        pinv, pv = inv[nd + N:], np.zeros((0, 4))                   # the stencil pairs (none without the prior)
        if prior:
            T = np.stack([self.t1, self.t2], 1)[self.st]
            cc = self.w * self.coef[:, None] * self.coef[None, :]
            TT = np.matmul(T[:, :, None], T[:, None].transpose(0, 1, 2, 4, 3))
            pv = (cc[None, :, :, None, None] * TT).reshape(-1, 4)
        blocks = _sums(np.concatenate([np.arange(P), pinv]), np.concatenate([data, pv]), P)
        B = np.zeros((N, sp["qmax"], 2, 2))
        B[sp["rows"], sp["pos"]] = blocks.reshape(P, 2, 2)
        self.nbr = sp["nbr"]
        self.B0 = np.ascontiguousarray(B.transpose(0, 2, 1, 3).reshape(N, 2, -1))  # [B_i,j1 B_i,j2 ...]
        dpair = inv[nd:nd + N]                                   # the diagonal pairs, for _damp
        on = np.zeros(P, np.int64) - 1
        on[dpair] = np.arange(N)
        sel = on[pinv] >= 0
        self._dg = {"idx": np.concatenate([np.arange(N), np.arange(N), on[pinv][sel]]), "data": data[dpair],
                    "prior": pv[sel], "pos": sp["pos"][dpair]}

    def data_product(self, x):
        """J_n x (data rows only), x (N, 2, R) -> (m, R)."""
        return np.einsum("mqa,mqar->mr", self.v, x[self.q])

    def apply(self, x, gather=None):
        """H_nn x for x (N, 2, R); ``gather``: a reused (N, qmax, 2, R) buffer (a new one per iteration costs
        page faults on a large frame)."""
        N, R = x.shape[0], x.shape[2]
        xg = np.take(x, self.nbr, axis=0) if gather is None else np.take(x, self.nbr, axis=0, out=gather, mode="clip")
        return np.matmul(self.B, xg.reshape(N, -1, R))

    def precondition(self, r):
        """The block-Jacobi preconditioner applied to r (N, 2, R)."""
        P = self.pre
        z = np.empty_like(r)
        np.multiply(P[:, 0, 0, None], r[:, 0], out=z[:, 0])
        z[:, 0] += P[:, 0, 1, None] * r[:, 1]
        np.multiply(P[:, 1, 0, None], r[:, 0], out=z[:, 1])
        z[:, 1] += P[:, 1, 1, None] * r[:, 1]
        return z

    def solve(self, b, rtol=1e-10, max_iter=5000):
        """x with H_nn x = b, b (N, 2, R), by preconditioned conjugate gradients on all columns at once."""
        x = np.zeros_like(b)
        r = b.copy()
        z = self.precondition(r)
        p = z.copy()
        rz = np.einsum("nar,nar->r", r, z)
        bn = np.sqrt(np.einsum("nar,nar->r", b, b))
        bn[bn == 0] = 1.0
        gather, step = np.empty(self.nbr.shape + b.shape[1:]), np.empty_like(b)
        for _ in range(max_iter):
            Ap = self.apply(p, gather)
            pAp = np.einsum("nar,nar->r", p, Ap)
            alpha = np.where(pAp > 0, rz / np.where(pAp > 0, pAp, 1.0), 0.0)
            x += np.multiply(alpha, p, out=step)
            r -= np.multiply(alpha, Ap, out=step)
            if np.all(np.sqrt(np.einsum("nar,nar->r", r, r)) <= rtol * bn):
                break
            z = self.precondition(r)
            rz_new = np.einsum("nar,nar->r", r, z)
            beta = np.where(rz > 0, rz_new / np.where(rz > 0, rz, 1.0), 0.0)
            p *= beta           # p = z + beta p, in place
            p += z
            rz = rz_new
        return x


def solve_step(Hmm, Hmn, Hnn, gm, gn, mu):
    """The damped Gauss-Newton step (dm (p,), dn (N, 2)) by the Schur complement; ``Hnn`` damped by ``mu``."""
    p = len(gm)
    rhs = np.concatenate([Hmn.transpose(1, 2, 0), gn[:, :, None]], axis=2)
    X = Hnn.solve(rhs)
    Hmn2 = Hmn.reshape(p, -1)
    S = Hmm + np.diag(mu * np.maximum(np.diag(Hmm), 1e-12)) - Hmn2 @ X[:, :, :p].reshape(-1, p)
    dm = np.linalg.solve(S, -gm + Hmn2 @ X[:, :, p].ravel())
    dn = Hnn.solve((-gn - np.einsum("pna,p->na", Hmn, dm))[:, :, None])[:, :, 0]
    return dm, dn


def material_covariance(Hmm, Hmn, Hnn, Jm):
    """Covariance of the material (p x p) with the normals free: the sandwich [H^-1 F H^-1]_mm, F = J^T J of
    the data rows only (the prior is a regulariser, not information); ``Hnn`` undamped.  S = H_mm - H_mn
    H_nn^-1 H_nm is the Schur complement, the material's information with the normals free."""
    p = len(Hmm)
    S = Hmm - Hmn.reshape(p, -1) @ Hnn.solve(np.ascontiguousarray(Hmn.transpose(1, 2, 0))).reshape(-1, p)
    Si = np.linalg.inv(0.5 * (S + S.T))
    Yn = -Hnn.solve(np.einsum("pna,pq->naq", Hmn, Si))
    JY = Jm @ Si + Hnn.data_product(Yn)
    C = JY.T @ JY
    return 0.5 * (C + C.T)
