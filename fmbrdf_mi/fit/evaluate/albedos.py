"""The albedo layouts of a fit: each a sparse design A(theta) of the albedos.

Every model is linear in two albedos (paper eq:fmbrdf: k_s scales the
surface term, k_b = r_k k_s the body term), so with S_k, B_k the unit-albedo
intensities of sample k behind its polariser
(:class:`~fmbrdf_mi.fit.evaluate.pixel_model.Parts` through the analyser),
which depend on the shape parameters theta,

    mu_k = sum_c w_kc (a_s[g_kc] S_k + a_b[g_kc] B_k) = (A(theta) a)_k,

a = (a_s[0], a_b[0], a_s[1], ...) the 2 n_groups albedos and A(theta) a sparse
design: row k has w_kc S_k at a_s[g_kc] and w_kc B_k at a_b[g_kc], for the
sample's corners c (its groups g_kc and their weights w_kc).  A layout is
its design, i.e. its corners; :class:`AlbedoLayout` owns the algebra:

* **per channel** (:class:`ChannelAlbedos`, colour mosaics) and **per
  material** (:class:`~fmbrdf_mi.fit.evaluate.materials.MaterialAlbedos`):
  one corner of weight 1, the sample's colour channel or material;
* **per pixel** (:class:`PixelAlbedos`, ``albedo="per-pixel"``): one corner
  of weight 1, the sample's pixel (per pixel and channel for colour mosaics);
* **per pixel, bilinear** (``albedo="per-pixel-bilinear"``): up to four
  corners, the pixel centres around the sample's point with their bilinear
  weights (:func:`~fmbrdf_mi.fit.evaluate.bilinear_albedos.bilinear_weights`);
* the maps' **smoothness prior**
  (:class:`~fmbrdf_mi.fit.evaluate.albedo_prior.SmoothPrior`): rows appended
  to the design, with data 0.

A single shared pair needs no layout (``layout=None``).

The albedos of a design are eliminated by variable projection (Golub and
Pereyra): a = A^+ y at every shape point, the optimiser seeing Kaufman's
Jacobian (I - P) J_theta, P = A (A^T A)^-1 A^T (:meth:`AlbedoLayout.project`).
The few albedos of :class:`GroupAlbedos` (channels, materials) are instead
unknowns of the optimiser (their logs in z), re-solved non-negatively in
closed form (:func:`nnls2`) at trial points.
"""
from __future__ import annotations

import numpy as np

from fmbrdf_mi.fit.evaluate.bilinear_albedos import RIDGE, BandCholesky, normal_band, stack_rows
from fmbrdf_mi.sensor.mosaic import COLOURS


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


def floored(a_s, a_b):
    """The albedos with those at 0 raised to 1e-9 of the largest (so that their logs stay finite)."""
    floor = 1e-9 * max(float(np.max(a_s)), float(np.max(a_b)), 1e-300)
    return np.maximum(a_s, floor), np.maximum(a_b, floor)


class PairBlocks:
    """The normal matrix G = A^T A of a design with one corner of weight 1 per sample: block diagonal, one
    2 x 2 block per group (``blocks`` (n_groups, 2, 2)), pseudo-inverted in closed form (parallel columns give
    the minimum-norm pair and one degree of freedom).  The same interface as
    :class:`~fmbrdf_mi.fit.evaluate.bilinear_albedos.BandCholesky`: :meth:`solve`, :meth:`diagonal_blocks`,
    ``undetermined``."""

    def __init__(self, blocks):
        self.inverse = np.linalg.pinv(blocks, rcond=1e-10, hermitian=True)
        #: each block's rank: the albedos the data spent unknowns on
        self.rank = np.linalg.matrix_rank(blocks, rtol=1e-10, hermitian=True)
        det = blocks[:, 0, 0] * blocks[:, 1, 1] - blocks[:, 0, 1] ** 2
        #: pairs whose columns are parallel (det at most 1e-10 of G_ss G_bb) or empty
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
    """Per group the 2 x 2 block X^T Y (n_groups, 2, 2) of two designs of one corner per sample (the same
    groups: columns 2g, 2g + 1 of each row)."""
    g = X[0][:, 0] // 2
    out = np.empty((n_groups, 2, 2))
    for a in range(2):
        for b in range(2):
            out[:, a, b] = np.bincount(g, weights=X[1][:, a] * Y[1][:, b], minlength=n_groups)
    return out


#: Why the incidental-parameter sandwich is not reported with the albedo maps' smoothness prior
#: (fit.json's uncertainty method).
PRIOR_INCIDENTAL = ("the incidental-parameter sandwich is not computed with the albedo smoothness prior (the "
                    "posterior covariance of the penalised likelihood is reported)")


class AlbedoLayout:
    """The albedos of a fit as the sparse design A(theta) of the module docstring, and their elimination.

    ``groups``: each sample's own group, an int array broadcastable to (cells, n); ``n_groups``: how many
    albedo pairs; ``corner_groups``, ``corner_weights`` (groups' shape + (c,)): the design's corners (default:
    one corner of weight 1, the own group); ``name``: the ``albedo`` option's value; ``labels``: each group's
    label where the groups are named (None otherwise); ``prior``: the smoothness prior
    (:class:`~fmbrdf_mi.fit.evaluate.albedo_prior.SmoothPrior`), whose rows R are appended to the design
    (data 0; None: none).  Subclasses supply the design, this class its algebra.

    At every shape point the albedos are the least squares a = (A^T A + R^T R)^-1 A^T y (:meth:`solve`),
    the optimiser's Jacobian is Kaufman's, (I - P) J_theta (:meth:`project`), and at the optimum each pair's
    covariance is the diagonal block of the full information's inverse (:meth:`covariance`).  The normal
    matrix G = A^T A (+ R^T R) is factored once per point and has one of two structures:

    * **block diagonal** (``coupled`` False: one corner per sample, no prior): :class:`PairBlocks`; the
      incidental-parameter term is exact;
    * **banded** (``coupled`` True: bilinear corners, or the prior's rows): row-major pixels make G banded
      (:class:`~fmbrdf_mi.fit.evaluate.bilinear_albedos.BandCholesky`, with
      :data:`~fmbrdf_mi.fit.evaluate.bilinear_albedos.RIDGE` where singular to rounding); each pair's block
      of G^-1 is its selected inverse, and the incidental-parameter term a Monte Carlo estimate (none with
      the prior: :data:`PRIOR_INCIDENTAL`).

    The albedos are not held non-negative: clipping the poorly determined ones at 0 (k_s away from the
    highlight) biases the shape, while a negative estimate is a small albedo measured with noise.
    """

    #: Whether the albedos are eliminated by variable projection (False: unknowns of the optimiser,
    #: :class:`GroupAlbedos`).
    eliminates = True

    #: Monte Carlo draws of the coupled :meth:`incidental`: about INCIDENTAL_DRAWS[1] / pairs, at least [0], at
    #: most [2].  One draw's relative spread on a diagonal entry of C is about sqrt(6 / pairs), so fewer draws
    #: suffice for larger maps; each draw costs (1 + p) banded solves.
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
        self.labels = None if labels is None else tuple(labels)
        self.prior = prior
        #: one corner of weight 1 per sample: A's columns of different groups never share a row
        self.one_corner = self.corner_groups.shape[-1] == 1 and bool(np.all(self.corner_weights == 1.0))
        self._single = np.ascontiguousarray(self.corner_groups[..., 0]) if self.one_corner else None
        #: whether the pairs are coupled (G banded) or not (G block diagonal)
        self.coupled = not self.one_corner or prior is not None
        lo, k, hi = self.INCIDENTAL_DRAWS
        self.incidental_draws = int(np.clip(np.ceil(k / max(self.n_groups, 1)), lo, hi))
        self._factor = None             # (key columns, factor of G) at the last columns
        self._incidental_last = None    # (draws, seed, count), the columns, C of the last incidental

    # ---- the design
    def interpolate(self, a):
        """Each sample's combination sum_c w_c a[g_c] of the per-group ``a`` (n_groups,): groups' shape."""
        a = np.asarray(a, dtype=np.float64)
        if self.one_corner:
            return a[self._single]
        return np.einsum("...c,...c->...", self.corner_weights, a[self.corner_groups])

    def mu(self, S, B, a_s, a_b):
        """(cells, n) predictions A a from the unit-albedo intensities S, B (cells, n)."""
        return self.interpolate(a_s) * S + self.interpolate(a_b) * B

    def design(self, us, ub):
        """A as (columns (N, 2c), values (N, 2c)): each sample's non-zeros, unknowns interleaved (a_s[g] at 2g,
        a_b[g] at 2g + 1), from its (whitened) unit-albedo columns ``us``, ``ub`` (N,), samples in the order
        of (cells, n) raveled."""
        us, ub = (np.asarray(u, dtype=np.float64).ravel() for u in (us, ub))
        c = self.corner_groups.shape[-1]
        g, w = self.corner_groups.reshape(-1, c), self.corner_weights.reshape(-1, c)
        if len(g) != len(us):       # groups given per sample of a cell (n,): the same for every cell
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
        n = 2 * self.n_groups
        if v.ndim == 1:
            return np.bincount(cols.ravel(), weights=(vals * v[:, None]).ravel(), minlength=n)
        return np.stack([np.bincount(cols.ravel(), weights=(vals * v[:, k, None]).ravel(), minlength=n)
                         for k in range(v.shape[1])], 1)

    # ---- the prior's rows
    def prior_residuals(self, a_s, a_b):
        """The prior's residual rows (2E,) at the albedos (empty without a prior)."""
        return np.zeros(0) if self.prior is None else self.prior.residuals(a_s, a_b)

    def penalty(self, a_s, a_b):
        """The prior's term of chi^2 (0 without a prior)."""
        return 0.0 if self.prior is None else self.prior.penalty(a_s, a_b)

    # ---- the factored normal matrix
    def _factorised(self, us, ub):
        """(A, factor of G) at the columns ``us``, ``ub``: A the design, the factor the last one when the columns
        match those it came from to a relative 1e-12 (the solve's S sqrt(w) and the Jacobian's -S / sd differ
        in rounding and sign), else a new one of A^T A (+ R^T R)."""
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
            for ridge in (0.0,) + RIDGE:       # G singular to rounding (parallel columns): the ridge
                try:
                    fac = BandCholesky(*band, ridge=ridge)
                    break
                except np.linalg.LinAlgError:
                    if ridge == RIDGE[-1]:
                        raise
        self._factor = (key, fac)
        return A, fac

    # ---- solve, project, covariance, incidental term
    def solve(self, S, B, y, w):
        """Every group's (a_s, a_b), the weighted least squares of all samples at once (penalised by the
        prior's rows): two arrays (n_groups,)."""
        sw = np.sqrt(np.asarray(w, dtype=np.float64)).ravel()
        A, fac = self._factorised(np.asarray(S, float).ravel() * sw, np.asarray(B, float).ravel() * sw)
        x = fac.solve(self.t_at(A, np.asarray(y, float).ravel() * sw))
        return x[0::2].copy(), x[1::2].copy()

    def free(self):
        """How many albedos the data spent unknowns on: two per group, one where a block diagonal G's group
        has parallel columns (at the last factored point); with the prior the dimension of its null space
        (:meth:`~fmbrdf_mi.fit.evaluate.albedo_prior.SmoothPrior.null_dims`), since the expected penalised
        chi^2 is then N - p - that."""
        if self.prior is not None:
            return self.prior.null_dims()
        if self._factor is not None and not self.coupled:
            return int(self._factor[1].rank.sum())
        return 2 * self.n_groups

    def project(self, J, us, ub):
        """Kaufman's Jacobian (I - P) J: ``J`` (N, p) the residuals' derivatives with respect to the shape
        unknowns, ``us``, ``ub`` (N,) those with respect to each sample's unit albedos (the design's columns
        before the corner weights); P = A G^-1 A^T projects onto the albedos' columns.  Returns (J_projected,
        K), K (n_groups, 2, p) = G^-1 A^T J (the albedos' regression on the shape unknowns).  With the prior
        its rows R (which do not depend on the shape: their J rows are 0) are in G, and the projected
        Jacobian has the rows -R K appended: (N + 2E, p)."""
        p = J.shape[1]
        A, fac = self._factorised(us, ub)
        extra = 0 if self.prior is None else self.prior.n_rows
        if not p:
            return np.zeros((J.shape[0] + extra, 0)), np.zeros((self.n_groups, 2, 0))
        K = fac.solve(self.t_at(A, J))
        Jp = J - self.at(A, K)
        if self.prior is not None:
            Jp = np.concatenate([Jp, -self.prior.apply(K)])
        return Jp, K.reshape(self.n_groups, 2, p)

    def covariance(self, us, ub, J, cov_z, scale=1.0):
        """(n_groups, 2, 2) covariance of each group's (a_s, a_b) with the shape unknowns free: the diagonal
        blocks of scale G^-1 + K cov_z K^T, K = G^-1 A^T J (the block inverse of the full information matrix;
        ``J`` (N, p) the residuals' unprojected shape derivatives, ``cov_z`` their covariance, already
        scaled).  A pair the data do not determine (the factor's ``undetermined``: parallel columns, or no
        signal) gets infinite variances."""
        A, fac = self._factorised(us, ub)
        C = scale * fac.diagonal_blocks()
        if J.shape[1]:
            K = fac.solve(self.t_at(A, J)).reshape(self.n_groups, 2, J.shape[1])
            C = C + np.einsum("gip,pq,gjq->gij", K, cov_z, K)
        C[fac.undetermined] = np.inf
        return C

    def effective_parameters(self, us, ub):
        """tr(A (A^T A + R^T R)^-1 A^T): the albedos' effective number of parameters (the trace of the hat
        matrix; the rank of A without a prior), from G^-1's entries within G's band."""
        A, fac = self._factorised(us, ub)
        if not self.coupled:
            return float(fac.rank.sum())
        band, b = normal_band(A, 2 * self.n_groups)
        Z = fac.inverse_band(b)
        return float(np.sum(Z[:, 0] * band[:, 0]) + 2.0 * np.sum(Z[:, 1:] * band[:, 1:]))

    @property
    def incidental_reason(self):
        """Why :meth:`incidental` gives None (with the prior), else None."""
        return None if self.prior is None else PRIOR_INCIDENTAL

    @property
    def incidental_method(self):
        """How C is computed, where the uncertainty method names it (the coupled pairs' estimate), else None."""
        if self.coupled and self.prior is None:
            return (f"C estimated by Monte Carlo over {self.incidental_draws} noise draws (the albedo pairs are "
                    "coupled)")
        return None

    def incidental(self, us, ub, dcols, draws=None, seed=0):
        """The incidental-parameter term C (p, p) of the eliminated albedos' noise in Kaufman's information,
        or None with the prior (:attr:`incidental_reason`).  With A the design at the whitened unit-albedo
        columns ``us``, ``ub`` (N,), A_j the design at their derivatives ``dcols`` (p pairs (dus, dub) of (N,)
        arrays: d A / d z_j, the corner weights being fixed) and P = A G^-1 A^T,

            C_jk = tr(G^-1 A_j^T (I - P) A_k) = tr(G^-1 A_j^T A_k) - tr(G^-1 A_j^T A G^-1 A^T A_k).

        J^T J at the estimated albedos is on average H + C (Neyman and Scott's incidental parameters), which
        ``fmbrdf_mi.fit.uncertainty.incidental_sandwich`` corrects.  C is positive semi-definite.

        Block diagonal G: exact, by the sums per group of the second form.  Banded G: G^-1 is not banded, so C
        is the mean of v_j^T v_k over ``draws`` (default ``incidental_draws``) draws,
        v_j = (I - P) A_j G^-1 A^T e, e ~ N(0, I_N) from the generator seeded ``seed``.  Deterministic for the
        same columns; the last result is cached because the covariance and the maps ask at the same point."""
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
            Y = [pair_sums(A, a, n) for a in Aj]                        # A^T A_j per group
            GY = [Gi @ y for y in Y]
            C = np.empty((p, p))
            for j in range(p):
                for k in range(j, p):
                    C[j, k] = C[k, j] = (np.einsum("gab,gba->", pair_sums(Aj[j], Aj[k], n), Gi)
                                         - np.einsum("gba,gbc,gca->", Y[j], GY[k], Gi))
        else:
            m = int(draws or self.incidental_draws)
            e = np.random.default_rng(seed).standard_normal((A[0].shape[0], m))
            b = fac.solve(self.t_at(A, e))                           # (2 n_groups, m), covariance G^-1
            V = []
            for a in Aj:
                v = self.at(a, b)                                    # A_j b (N, m)
                V.append(v - self.at(A, fac.solve(self.t_at(A, v))))
            V = np.stack(V, 1)                                       # (N, p, m)
            C = np.einsum("njd,nkd->jk", V, V) / m
        self._incidental_last = ((draws, seed, len(args)), [a.copy() for a in args], C)
        return C.copy()


class GroupAlbedos(AlbedoLayout):
    """A few albedo pairs that are unknowns of the optimiser (their logs in z): one corner of weight 1 per
    sample, its group; each group's pair is solved non-negatively (:func:`nnls2`)."""

    eliminates = False

    def __init__(self, name, groups, n_groups, labels):
        super().__init__(groups, n_groups, name=name, labels=labels)
        self.masks = [self.groups == g for g in range(self.n_groups)]

    def solve(self, S, B, y, w):
        """Each group's (a_s, a_b) by :func:`nnls2` of its samples: two arrays (n_groups,)."""
        S, B, y, w = (np.asarray(a) for a in (S, B, y, w))
        out = [nnls2(*(a[np.broadcast_to(m, a.shape)] for a in (S, B, y, w))) for m in self.masks]
        return np.array([o[0] for o in out]), np.array([o[1] for o in out])

    def columns(self, S, B, a_s, a_b):
        """d mu / d log a_s[g] for every g, then d mu / d log a_b[g]: 2 n_groups arrays (cells, n)."""
        return ([a_s[g] * S * m for g, m in enumerate(self.masks)]
                + [a_b[g] * B * m for g, m in enumerate(self.masks)])


class ChannelAlbedos(GroupAlbedos):
    """One (a_s, a_b) per colour channel: ``channel`` (n,) is the group of each of a cell's n samples."""

    def __init__(self, channel, labels=COLOURS):
        super().__init__("per-channel", channel, len(labels), labels)


class PixelAlbedos(AlbedoLayout):
    """Albedo maps: one (a_s, a_b) per fitted pixel (per pixel and colour channel: ``channel_of`` (n_groups,),
    ``labels``), the same pixel in every image of a joint fit sharing it.

    ``groups`` (cells, n): each sample's own pixel's group; ``pixels`` (n_groups,) the flat pixel index of
    each group; the corners default to the own group (``albedo="per-pixel"``), or are the bilinear
    interpolation between pixel centres (``albedo="per-pixel-bilinear"``,
    :func:`~fmbrdf_mi.fit.problem.data.bilinear_layout`).  The rest is :class:`AlbedoLayout`'s."""

    def __init__(self, groups, n_groups, pixels, *, corner_groups=None, corner_weights=None, name="per-pixel",
                 prior=None, channel_of=None, labels=None):
        super().__init__(groups, n_groups, corner_groups=corner_groups, corner_weights=corner_weights, name=name,
                         labels=labels, prior=prior)
        self.pixels = np.asarray(pixels, dtype=np.int64)
        self.channel_of = None if channel_of is None else np.asarray(channel_of, dtype=np.int64)

    def maps(self, S, B, a_s, a_b, cov, factor, split_rel):
        """The maps of every group: a dict of arrays (n_groups,): ``k_s``, ``k_b`` (the model's reported
        albedos: ``factor`` times a_s, a_b), ``k_s_se``, ``k_b_se`` (from ``cov`` (n_groups, 2, 2), the pairs'
        :meth:`covariance`), ``correlation`` of the two, and ``identified``: False where the standard error of
        the surface's or the body's contribution to the pixel's brightness (a_s mean S, a_b mean B over the
        group's own samples; ``S``, ``B`` (cells, n) the unit-albedo intensities) exceeds ``split_rel`` of the
        pixel's mean predicted brightness, or where the group has no signal."""
        f = float(factor)
        a_s, a_b = np.asarray(a_s, float), np.asarray(a_b, float)
        se_s, se_b = np.sqrt(np.clip(cov[:, 0, 0], 0, None)), np.sqrt(np.clip(cov[:, 1, 1], 0, None))
        with np.errstate(invalid="ignore", divide="ignore"):
            corr = np.where(np.isfinite(se_s * se_b) & (se_s * se_b > 0), cov[:, 0, 1] / (se_s * se_b), np.nan)
        g = self.groups.ravel()
        n = np.maximum(np.bincount(g, minlength=self.n_groups), 1)

        def mean(v):
            return np.bincount(g, weights=np.abs(v).ravel(), minlength=self.n_groups) / n

        mean_s, mean_b, total = mean(S), mean(B), mean(self.mu(S, B, a_s, a_b))
        ident = (total > 0) & (se_s * mean_s <= split_rel * total) & (se_b * mean_b <= split_rel * total)
        return {"k_s": f * a_s, "k_b": f * a_b, "k_s_se": f * se_s, "k_b_se": f * se_b,
                "correlation": np.clip(corr, -1.0, 1.0), "identified": ident}
