"""The bilinear design of per-pixel albedos (``albedo="per-pixel-bilinear"``) and the banded algebra of
coupled albedo pairs.

A super-pixel's polariser samples sit at different points and see different albedos, which one pair per
super-pixel would read as polarisation; so each sample interpolates the pixel centres' albedos
(:func:`bilinear_weights`).  Coupled pairs make G = A^T A banded (:func:`normal_band`, :class:`BandCholesky`).
"""
from __future__ import annotations

import numpy as np

#: The ``albedo`` option's values whose albedos are maps (one pair per pixel).
PER_PIXEL_LAYOUTS = ("per-pixel", "per-pixel-bilinear")

#: The ridges tried, in turn, on the Jacobi-scaled normal matrix when it is singular to rounding (e.g. a
#: sphere's centre, where surface and body are both unpolarised).
RIDGE = (1e-12, 1e-10, 1e-8)


def bilinear_weights(rows, cols, offsets, present):
    """Each sample's albedo as a combination of pixel centres: (corners (cells, n, 4, 2) (row, col),
    weights (cells, n, 4) summing to 1; an unused corner has weight 0).

    ``offsets`` (n, 2): each sample's (dx right, dy down) from its cell's centre, in cells; ``present(r, c)``:
    whether pixel (r, c) is fitted.  Per axis: interpolation, else linear extrapolation, else constant; a
    missing diagonal corner is the plane through the other three, so a linear albedo is exact."""
    rows, cols = np.asarray(rows, np.int64), np.asarray(cols, np.int64)
    off = np.asarray(offsets, dtype=np.float64)
    cells, n = len(rows), len(off)
    dx, dy = off[:, 0][None, :], off[:, 1][None, :]
    sx, sy = np.sign(dx).astype(np.int64), np.sign(dy).astype(np.int64)
    ax, ay = np.abs(dx), np.abs(dy)
    r0, c0 = np.broadcast_to(rows[:, None], (cells, n)), np.broadcast_to(cols[:, None], (cells, n))

    def stencil(fwd, back, s, a):
        """One axis: (neighbour step, own weight, neighbour weight)."""
        inter, extra = fwd & (s != 0), ~fwd & back & (s != 0)
        step = np.where(inter, s, np.where(extra, -s, 0))
        w_own = np.where(inter, 1 - a, np.where(extra, 1 + a, 1.0))
        return step, w_own, 1.0 - w_own

    kx, ox, nx = stencil(present(r0, c0 + sx), present(r0, c0 - sx), sx, ax)
    ky, oy, ny = stencil(present(r0 + sy, c0), present(r0 - sy, c0), sy, ay)
    w_o, w_h, w_v, w_d = ox * oy, nx * oy, ox * ny, nx * ny
    has_d = present(r0 + ky, c0 + kx) | (kx == 0) | (ky == 0)
    plane = ~has_d                                                   # a_d := a_h + a_v - a_own
    w_h, w_v, w_o = w_h + plane * w_d, w_v + plane * w_d, w_o - plane * w_d
    w_d = np.where(plane, 0.0, w_d)
    idx = np.stack([np.stack([r0, c0], -1), np.stack([r0, c0 + kx], -1), np.stack([r0 + ky, c0], -1),
                    np.stack([r0 + ky, c0 + kx], -1)], 2)
    wt = np.stack([w_o, w_h, w_v, w_d], 2)
    # unused corners point at the own pixel (always present)
    idx = np.where((wt != 0)[..., None], idx, np.stack([r0, c0], -1)[:, :, None, :])
    return idx, wt


def stack_rows(A, R):
    """The design A with the rows R (no wider) appended, R padded with zero values."""
    (ca, va), (cr, vr) = A, R
    k = ca.shape[1] - cr.shape[1]
    return (np.concatenate([ca, np.concatenate([cr, np.repeat(cr[:, :1], k, 1)], 1)]),
            np.concatenate([va, np.concatenate([vr, np.zeros((len(vr), k))], 1)]))


def normal_band(A, n):
    """(band (n, b + 1) with band[i, d] = (A^T A)[i, i - d], b the half bandwidth)."""
    cols, vals = A
    i = np.repeat(cols[:, :, None], cols.shape[1], 2)
    j = np.repeat(cols[:, None, :], cols.shape[1], 1)
    v = vals[:, :, None] * vals[:, None, :]
    low = i >= j
    i, j, v = i[low], j[low], v[low]
    keep = v != 0
    i, j, v = i[keep], j[keep], v[keep]
    b = int(np.max(i - j)) if i.size else 0
    band = np.bincount(i * (b + 1) + (i - j), weights=v, minlength=n * (b + 1)).reshape(n, b + 1)
    return band, b


class BandCholesky:
    """Cholesky factor of a banded G (lower band ``band``), Jacobi-scaled: G = D^1/2 Gs D^1/2 (a zero
    diagonal: unknown set to 0), Gs + ``ridge`` I = L L^T, L block lower bidiagonal.  LinAlgError where not
    positive definite."""

    def __init__(self, band, b, ridge=0.0):
        band = np.array(band, dtype=np.float64)
        n = band.shape[0]
        self.n = n
        d = band[:, 0].copy()
        #: pairs (unknowns 2g, 2g + 1) of which an unknown has no signal
        self.undetermined = np.any(d.reshape(-1, 2) <= 0, axis=1) if n % 2 == 0 else None
        self.scale = 1.0 / np.sqrt(np.where(d > 0, d, 1.0))
        for k in range(b + 1):
            i = np.arange(k, n)
            band[i, k] *= self.scale[i] * self.scale[i - k]
        band[:, 0] = 1.0 + ridge
        s = max(int(b), 1)
        self.edges = list(range(0, n, s)) + [n]
        self.Linv, self.M = [], []         # L_k^-1, M_k = Gs_{k+1,k} L_k^-T
        prev = None
        for k in range(len(self.edges) - 1):
            D = self._block(band, b, k, k)
            if prev is not None:
                D = D - prev @ prev.T
            L = np.linalg.cholesky(D)
            Li = np.linalg.inv(L)
            self.Linv.append(Li)
            if k + 2 < len(self.edges):
                prev = self._block(band, b, k + 1, k) @ Li.T
                self.M.append(prev)

    def _block(self, band, b, kr, kc):
        """Dense block (kr, kc) of G (kr >= kc) from the lower band."""
        r0, r1 = self.edges[kr], self.edges[kr + 1]
        c0, c1 = self.edges[kc], self.edges[kc + 1]
        I, Jc = np.arange(r0, r1)[:, None], np.arange(c0, c1)[None, :]
        lo, hi = np.maximum(I, Jc), np.minimum(I, Jc)      # symmetric
        dd = lo - hi
        ok = dd <= b
        return np.where(ok, band[lo, np.where(ok, dd, 0)], 0.0)

    def solve(self, r):
        """G^-1 r for r (n,) or (n, p) (with the ridge)."""
        sc = self.scale if np.ndim(r) == 1 else self.scale[:, None]
        r = sc * np.asarray(r, dtype=np.float64)
        e = self.edges
        K = len(e) - 1
        y = []
        for k in range(K):
            v = r[e[k]:e[k + 1]]
            y.append(self.Linv[k] @ (v - self.M[k - 1] @ y[-1] if k else v))
        x = [None] * K
        for k in range(K - 1, -1, -1):
            x[k] = self.Linv[k].T @ (y[k] - self.M[k].T @ x[k + 1] if k + 1 < K else y[k])
        return sc * np.concatenate(x)

    def diagonal_blocks(self):
        """The 2 x 2 diagonal blocks (n / 2, 2, 2) of G^-1 (n even)."""
        Z = self.inverse_band(1)
        out = np.empty((self.n // 2, 2, 2))
        out[:, 0, 0], out[:, 1, 1] = Z[0::2, 0], Z[1::2, 0]
        out[:, 0, 1] = out[:, 1, 0] = Z[1::2, 1]
        return out

    def inverse_band(self, bw):
        """The lower band (n, bw + 1) of G^-1 by Takahashi's selected inversion from the last block up:
        Z_{k+1,k} = -Z_{k+1,k+1} M_k L_k^-1, Z_kk = L_k^-T (L_k^-1 - M_k^T Z_{k+1,k})."""
        e = self.edges
        K = len(e) - 1
        s = max(e[1] - e[0], 1) if K else 1
        if bw > s:
            raise ValueError(f"inverse_band: bandwidth {bw} above the factor's {s}")
        out = np.zeros((self.n, bw + 1))

        def fill(k, strip, c0):     # block k's rows of the band from Z's strip at column c0
            rows = np.arange(e[k], e[k + 1])
            for d in range(bw + 1):
                j = rows - d
                ok = j >= c0
                out[rows[ok], d] = strip[rows[ok] - e[k], j[ok] - c0]

        Z = None
        for k in range(K - 1, -1, -1):
            Li = self.Linv[k]
            if Z is None:
                Z = Li.T @ Li
            else:                   # Z is Z_{k+1,k+1}: fill row block k + 1 from [Z_{k+1,k} | Z_{k+1,k+1}]
                Zlow = -(Z @ self.M[k]) @ Li
                fill(k + 1, np.concatenate([Zlow, Z], 1), e[k])
                Z = Li.T @ (Li - self.M[k].T @ Zlow)
        if K:
            fill(0, Z, 0)
        sc = self.scale
        for d in range(bw + 1):
            i = np.arange(d, self.n)
            out[i, d] *= sc[i] * sc[i - d]
        return out
