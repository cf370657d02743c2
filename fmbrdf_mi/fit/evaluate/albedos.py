"""The albedo layouts of a likelihood fit: each a sparse design A(theta) of the albedos.

Every model is linear in its albedos (paper: s_s + s_b): mu_k = sum_c w_kc (a_s[g_kc] S_k + a_b[g_kc] B_k)
= (A(theta) a)_k over sample k's corners c.  :class:`AlbedoLayout` eliminates the albedos by variable
projection, one pair per channel or material (:class:`GroupAlbedos`) or per pixel (:class:`PixelAlbedos`).
"""
from __future__ import annotations

import numpy as np

from fmbrdf_mi.fit.evaluate.bilinear_albedos import RIDGE, BandCholesky, normal_band, stack_rows


def nnls2(S, B, I, w=None):
    """Non-negative weighted least squares of I ~ a_s S + a_b B; returns (a_s, a_b), both > 0."""
    w = np.ones_like(I) if w is None else w
    A = np.array([[np.sum(w * S * S), np.sum(w * S * B)], [np.sum(w * S * B), np.sum(w * B * B)]])
    b = np.array([np.sum(w * S * I), np.sum(w * B * I)])
    cands = []
    try:
        x = np.linalg.solve(A, b)
        if np.all(x >= 0):
            cands.append(x)
    except np.linalg.LinAlgError:
        pass
    if A[0, 0] > 0:
        cands.append(np.array([max(b[0] / A[0, 0], 0.0), 0.0]))
    if A[1, 1] > 0:
        cands.append(np.array([0.0, max(b[1] / A[1, 1], 0.0)]))
    if not cands:
        return 1e-6, 1e-6
    best = min(cands, key=lambda x: float(x @ A @ x - 2 * x @ b))
    floor = 1e-6 * max(best.max(), 1e-12)
    return float(max(best[0], floor)), float(max(best[1], floor))


class PairBlocks:
    """G = A^T A of a one-corner design, one pseudo-inverted 2 x 2 block per group; the interface of
    :class:`~fmbrdf_mi.fit.evaluate.bilinear_albedos.BandCholesky`."""

    def __init__(self, blocks):
        # NumPy's pinv(rcond=1e-10, hermitian=True) and matrix_rank from one eigh (|eigenvalues| descending)
        w, U = np.linalg.eigh(blocks)
        o = np.where((np.abs(w[:, 0]) > np.abs(w[:, 1]))[:, None], [0, 1], [1, 0])
        w, U = np.take_along_axis(w, o, 1), np.take_along_axis(U, o[:, None, :], 2)
        large = np.abs(w) > 1e-10 * np.abs(w).max(1, keepdims=True)
        #: each block's rank
        self.rank = large.sum(1)
        s_inv = np.divide(1.0, np.abs(w), out=np.zeros_like(w), where=large)
        self.inverse = (U * np.sign(w)[:, None, :]) @ (s_inv[:, :, None] * U.transpose(0, 2, 1))
        det = blocks[:, 0, 0] * blocks[:, 1, 1] - blocks[:, 0, 1] ** 2
        #: pairs whose columns are parallel or empty
        self.undetermined = ~(det > 1e-10 * np.maximum(blocks[:, 0, 0] * blocks[:, 1, 1], 1e-300))

    def solve(self, r):
        """G^+ r for r (2 n_groups,) or (2 n_groups, p)."""
        r = np.asarray(r, dtype=np.float64)
        x = np.einsum("gij,gj...->gi...", self.inverse, r.reshape((len(self.inverse), 2) + r.shape[1:]))
        return x.reshape(r.shape)

    def diagonal_blocks(self):
        """The 2 x 2 diagonal blocks of G^+ (n_groups, 2, 2)."""
        return self.inverse


def pair_sums(X, Y, n_groups):
    """Per group the 2 x 2 block X^T Y (n_groups, 2, 2) of two one-corner designs on the same groups."""
    g = X[0][:, 0] // 2
    out = np.empty((n_groups, 2, 2))
    for a, b in ((0, 0), (0, 1), (1, 0), (1, 1)):
        out[:, a, b] = (out[:, b, a] if X is Y and b < a
                        else np.bincount(g, weights=X[1][:, a] * Y[1][:, b], minlength=n_groups))
    return out


class AlbedoLayout:
    """The sparse design A(theta) of the albedos and their elimination; ``corner_groups``, ``corner_weights``
    (groups' shape + (c,)) default to each sample's own group, weight 1.  The albedos are not held
    non-negative: clipping poorly determined ones at 0 biases the shape.
    """

    #: Monte Carlo draws of the coupled :meth:`incidental`: [1] / pairs, clipped to [[0], [2]] (a draw's
    #: relative spread on C's diagonal falls as 1 / sqrt(pairs)).
    INCIDENTAL_DRAWS = (8, 60000, 512)

    def __init__(self, groups, n_groups, *, corner_groups=None, corner_weights=None, name="per-pixel",
                 labels=None, prior=None):
        self.name = name
        self.groups = np.asarray(groups, dtype=np.int64)
        self.n_groups = int(n_groups)
        self.corner_groups = (self.groups[..., None] if corner_groups is None
                              else np.asarray(corner_groups, dtype=np.int64).reshape(self.groups.shape + (-1,)))
        self.corner_weights = (np.ones(self.corner_groups.shape) if corner_weights is None
                               else np.asarray(corner_weights, dtype=np.float64).reshape(self.corner_groups.shape))
        used = np.any(self.corner_weights != 0, axis=tuple(range(self.groups.ndim)))
        if not used.all():
            self.corner_groups, self.corner_weights = (np.ascontiguousarray(a[..., used])
                                                       for a in (self.corner_groups, self.corner_weights))
        self.labels = None if labels is None else tuple(labels)
        self.prior = prior
        #: G banded (True) or block diagonal (one corner of weight 1, no prior)
        self.coupled = (prior is not None or self.corner_groups.shape[-1] > 1
                        or not bool(np.all(self.corner_weights == 1.0)))
        lo, k, hi = self.INCIDENTAL_DRAWS
        self.incidental_draws = int(np.clip(np.ceil(k / max(self.n_groups, 1)), lo, hi))
        #: why :meth:`incidental` gives None (with the prior), else None
        self.incidental_reason = None if prior is None else (
            "the incidental-parameter sandwich is not computed with the albedo smoothness prior (the posterior "
            "covariance of the penalised likelihood is reported)")
        self._factor = None             # (key columns, factor of G) at the last columns
        self._incidental_last = None

    def sample_albedos(self, a_s, a_b):
        """Each sample's albedos sum_c w_c a[g_c] (cells, n), of the surface and of the body: the predictions
        A a are s S + b B from the unit-albedo intensities S, B (cells, n)."""
        return tuple(np.einsum("...c,...c->...", self.corner_weights, np.asarray(a, float)[self.corner_groups])
                     for a in (a_s, a_b))

    def design(self, us, ub):
        """A as (columns (N, 2c), values (N, 2c)) from the unit-albedo columns ``us``, ``ub`` (N,); a_s[g] is
        unknown 2g, a_b[g] 2g + 1."""
        us, ub = (np.asarray(u, dtype=np.float64).ravel() for u in (us, ub))
        c = self.corner_groups.shape[-1]
        g, w = self.corner_groups.reshape(-1, c), self.corner_weights.reshape(-1, c)
        if len(g) != len(us):       # groups given per sample of a cell: the same for every cell
            g, w = np.tile(g, (len(us) // len(g), 1)), np.tile(w, (len(us) // len(w), 1))
        return (np.concatenate([2 * g, 2 * g + 1], 1), np.concatenate([w * us[:, None], w * ub[:, None]], 1))

    def at(self, A, x):
        """A x: (N,) or (N, p) for x (2 n_groups,) or (2 n_groups, p)."""
        cols, vals = A
        return np.einsum("rc,rc...->r...", vals, np.asarray(x, dtype=np.float64)[cols])

    def t_at(self, A, v):
        """A^T v: (2 n_groups,) or (2 n_groups, p) for v (N,) or (N, p)."""
        cols, vals = A
        v = np.asarray(v, dtype=np.float64)
        return np.stack([np.bincount(cols.ravel(), weights=(vals * u[:, None]).ravel(), minlength=2 * self.n_groups)
                         for u in v.reshape(len(v), -1).T], 1).reshape((-1,) + v.shape[1:])

    def _factorised(self, us, ub):
        """(A, factor of G) at the columns ``us``, ``ub``; reuses the last factor when |columns| match (the
        solve's and the Jacobian's columns differ in rounding and sign)."""
        key = (np.abs(np.asarray(us, float).ravel()), np.abs(np.asarray(ub, float).ravel()))
        A = self.design(us, ub)
        f = self._factor
        if f is not None and all(a.shape == b.shape and np.allclose(a, b, rtol=1e-12, atol=0.0)
                                 for a, b in zip(key, f[0])):
            return A, f[1]
        if not self.coupled:
            fac = PairBlocks(pair_sums(A, A, self.n_groups))
        else:
            band = normal_band(A if self.prior is None else stack_rows(A, self.prior.rows()), 2 * self.n_groups)
            for ridge in (0.0,) + RIDGE:       # G singular to rounding (parallel columns)
                try:
                    fac = BandCholesky(*band, ridge=ridge)
                    break
                except np.linalg.LinAlgError:
                    if ridge == RIDGE[-1]:
                        raise
        self._factor = (key, fac)
        return A, fac

    def solve(self, S, B, y, w):
        """Every group's (a_s, a_b) by (penalised) weighted least squares: two arrays (n_groups,)."""
        sw = np.sqrt(np.asarray(w, dtype=np.float64)).ravel()
        A, fac = self._factorised(np.asarray(S, float).ravel() * sw, np.asarray(B, float).ravel() * sw)
        x = fac.solve(self.t_at(A, np.asarray(y, float).ravel() * sw))
        return x[0::2].copy(), x[1::2].copy()

    def free(self):
        """Albedos the data spent unknowns on; with the prior its null space's dimension."""
        if self.prior is not None:
            return self.prior.null_dims()
        if self._factor is not None and not self.coupled:
            return int(self._factor[1].rank.sum())
        return 2 * self.n_groups

    def project(self, J, us, ub):
        """(Kaufman's Jacobian (I - P) J, K = G^-1 A^T J (n_groups, 2, p)), P = A G^-1 A^T; with the prior the
        rows -R K are appended."""
        p = J.shape[1]
        A, fac = self._factorised(us, ub)
        extra = 0 if self.prior is None else self.prior.n_rows
        if not p:
            return np.zeros((J.shape[0] + extra, 0)), np.zeros((self.n_groups, 2, 0))
        K = fac.solve(self.t_at(A, J))
        Jp = self.at(A, K)
        np.subtract(J, Jp, out=Jp)
        if self.prior is not None:
            Jp = np.concatenate([Jp, -self.prior.apply(K)])
        return Jp, K.reshape(self.n_groups, 2, p)

    def covariance(self, us, ub, J, cov_z, scale=1.0):
        """(n_groups, 2, 2) covariance of each (a_s, a_b) with the shape free: diagonal blocks of scale G^-1 +
        K cov_z K^T (``J`` unprojected, ``cov_z`` scaled); undetermined pairs get inf."""
        A, fac = self._factorised(us, ub)
        C = scale * fac.diagonal_blocks()
        if J.shape[1]:
            K = fac.solve(self.t_at(A, J)).reshape(self.n_groups, 2, J.shape[1])
            C = C + np.einsum("gip,pq,gjq->gij", K, cov_z, K)
        C[fac.undetermined] = np.inf
        return C

    def effective_parameters(self, us, ub):
        """tr(A (A^T A + R^T R)^-1 A^T): the albedos' effective number of parameters."""
        A, fac = self._factorised(us, ub)
        if not self.coupled:
            return float(fac.rank.sum())
        band, b = normal_band(A, 2 * self.n_groups)
        Z = fac.inverse_band(b)
        return float(np.sum(Z[:, 0] * band[:, 0]) + 2.0 * np.sum(Z[:, 1:] * band[:, 1:]))

    @property
    def incidental_method(self):
        """How C is computed, for the uncertainty method (coupled pairs), else None."""
        if self.coupled and self.prior is None:
            return f"C estimated by Monte Carlo over {self.incidental_draws} noise draws (the albedo pairs are coupled)"

    def incidental(self, us, ub, dcols, draws=None, seed=0):
        """The incidental-parameter term C_jk = tr(G^-1 A_j^T (I - P) A_k) (p, p) in Kaufman's information (J^T J
        is on average H + C, Neyman and Scott), or None with the prior; ``dcols``: p pairs d(us, ub) / d z_j.
        Exact for block diagonal G, Monte Carlo over ``draws`` noise draws for banded G."""
        if self.prior is not None:
            return None
        p = len(dcols)
        if not p:
            return np.zeros((0, 0))
        args = [np.asarray(c, dtype=np.float64).ravel() for c in (us, ub, *(c for pair in dcols for c in pair))]
        last = self._incidental_last
        if (last is not None and last[0] == (draws, seed, len(args))
                and all(np.array_equal(a, b) for a, b in zip(args, last[1]))):
            return last[2].copy()
        A, fac = self._factorised(us, ub)
        Aj = [self.design(dus, dub) for dus, dub in dcols]
        if not self.coupled:
            Gi, n = fac.inverse, self.n_groups
            Y = [pair_sums(A, a, n) for a in Aj]
            GY = [Gi @ y for y in Y]
            C = np.empty((p, p))
            for j in range(p):
                for k in range(j, p):
                    C[j, k] = C[k, j] = (np.einsum("gab,gba->", pair_sums(Aj[j], Aj[k], n), Gi)
                                         - np.einsum("gba,gbc,gca->", Y[j], GY[k], Gi))
        else:
            m = int(draws or self.incidental_draws)
            e = np.random.default_rng(seed).standard_normal((A[0].shape[0], m))
            b = fac.solve(self.t_at(A, e))                           # covariance G^-1
            V = np.stack([v - self.at(A, fac.solve(self.t_at(A, v))) for v in (self.at(a, b) for a in Aj)], 1)
            C = np.einsum("njd,nkd->jk", V, V) / m
        self._incidental_last = ((draws, seed, len(args)), [a.copy() for a in args], C)
        return C.copy()


class GroupAlbedos(AlbedoLayout):
    """A few albedo pairs, one per label (``per-channel`` or ``per-material``)."""

    def __init__(self, name, groups, labels):
        super().__init__(groups, len(labels), name=name, labels=labels)

    def joint_covariance(self, us, ub, J, cov_z, scale=1.0):
        """The covariance of (z, a_s[0], a_b[0], a_s[1], ...) with the albedos eliminated (``J`` unprojected,
        ``cov_z`` scaled); the albedos' response to z is -K."""
        A, fac = self._factorised(us, ub)
        p, n = J.shape[1], 2 * self.n_groups
        K = fac.solve(self.t_at(A, J))
        out = np.empty((p + n, p + n))
        out[:p, :p], out[:p, p:] = cov_z, -cov_z @ K.T
        out[p:, :p], out[p:, p:] = out[:p, p:].T, scale * fac.solve(np.eye(n)) + K @ cov_z @ K.T
        return out


class PixelAlbedos(AlbedoLayout):
    """Albedo maps: one (a_s, a_b) per fitted pixel (and ``channel_of``), shared by a joint fit's images;
    ``pixels``: each group's flat pixel index."""

    def __init__(self, groups, n_groups, pixels, *, corner_groups=None, corner_weights=None, name="per-pixel",
                 prior=None, channel_of=None, labels=None):
        super().__init__(groups, n_groups, corner_groups=corner_groups, corner_weights=corner_weights, name=name,
                         labels=labels, prior=prior)
        self.pixels = np.asarray(pixels, dtype=np.int64)
        self.channel_of = None if channel_of is None else np.asarray(channel_of, dtype=np.int64)

    def maps(self, a_s, a_b, cov, factor, split_rel):
        """The maps (n_groups,): ``k_s``, ``k_b`` (``factor`` x albedo), their ``_se`` from ``cov``
        (:meth:`~AlbedoLayout.covariance`), ``correlation``, ``identified`` (both SE <= ``split_rel`` x albedo)."""
        f = float(factor)
        a_s, a_b = np.asarray(a_s, float), np.asarray(a_b, float)
        se_s, se_b = np.sqrt(np.clip(cov[:, 0, 0], 0, None)), np.sqrt(np.clip(cov[:, 1, 1], 0, None))
        with np.errstate(invalid="ignore", divide="ignore"):
            corr = np.where(np.isfinite(se_s * se_b) & (se_s * se_b > 0), cov[:, 0, 1] / (se_s * se_b), np.nan)
            ident = (se_s <= split_rel * a_s) & (se_b <= split_rel * a_b)
        return {"k_s": f * a_s, "k_b": f * a_b, "k_s_se": f * se_s, "k_b_se": f * se_b,
                "correlation": np.clip(corr, -1.0, 1.0), "identified": ident}
