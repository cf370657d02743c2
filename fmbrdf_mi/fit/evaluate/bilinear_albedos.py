"""Per-pixel albedos interpolated bilinearly between the super-pixel centres (``albedo="per-pixel-bilinear"``).

The per-pixel layout :class:`~fmbrdf_mi.fit.evaluate.albedos.PixelAlbedos`
gives the four raw samples of a super-pixel one (a_s, a_b) pair.  A camera
sees a *continuous* texture: its four polariser samples sit at four different
points (a quarter super-pixel off the centre, :mod:`fmbrdf_mi.fit.camera.samples`)
and see four different albedos, which one pair per super-pixel reads as
polarisation (measured: tools/bench_textured_bilinear.py).  Here the
unknowns are still one pair per fitted pixel, but they are the albedos *at
the pixel's centre*, and sample k of cell i predicts

    mu_ik = (sum_g w_ikg a_s[g]) S_ik + (sum_g w_ikg a_b[g]) B_ik,

w_ikg the bilinear interpolation weights of the sample's point (its raw
pixel's centre) between the up to four pixel centres around it (a raw
mosaic's sample at offset (+-1/4, +-1/4): 9/16 its own pixel, 3/16 each
edge neighbour, 1/16 the diagonal one).  For an albedo bilinear between the
centres the weighted value equals its mean over the raw pixel (the raw
pixel lies inside one interpolation square), so a linear gradient across a
super-pixel is modelled exactly.

**At the mask's edge** (a neighbour that is not fitted in any image: off
the object, excluded, or not selected): along each axis the sample's value
is interpolated towards the neighbour on its side; that one missing, it is
extrapolated linearly from the neighbour on the other side; both missing,
the albedo is held constant along that axis.  The 2-D weights are the
products of the two axes' (a weight can then be negative), and an off-axis
corner that is missing is taken as the plane through the other three
(a_h + a_v - a_own).  A linear texture is thus modelled exactly at every
sample of a pixel with a neighbour on at least one side in each direction;
a lone pixel predicts with its own pair, as in
:class:`~fmbrdf_mi.fit.evaluate.albedos.PixelAlbedos`.
Samples without an offset (angle images, Stokes images) use their own
pixel's pair only: the layout is then the per-pixel one.

**The solve.**  The albedos are eliminated (variable projection) as in
:class:`~fmbrdf_mi.fit.evaluate.albedos.PixelAlbedos`, but the pairs are
now coupled through their neighbours: at every shape point they are one
sparse weighted least squares, the normal equations G x = A^T y (A (N, 2 n_groups):
the whitened columns d mu / d a; unknowns interleaved a_s[0], a_b[0], a_s[1], ...)
factored once (:class:`BandCholesky`: the pixels in row-major order make G
banded, half bandwidth b about twice the object's width in pixels; NumPy
only) and the factor reused for
Kaufman's projected Jacobian (I - A G^-1 A^T) J at the same point.  The
albedos are not held non-negative (as in the per-pixel layout).  An unknown
without signal (its diagonal of G zero: a pixel without light) is set to 0;
where G is singular otherwise (a pair whose columns are parallel) its
Jacobi-scaled G (unit diagonal) gets a ridge, the smallest of 1e-12, 1e-10,
1e-8 that makes it positive definite (:data:`RIDGE`): the near-null
directions are then solved to about the minimum norm, as the per-pixel
layout's pseudo-inverse does, and their standard errors are large.  The
pixels at the sphere's centre, where surface and body are both unpolarised,
are such directions (measured on renders).

**Uncertainty.**  Each pair's covariance is the 2 x 2 diagonal block of the
full information matrix's inverse, scale G^-1 + K C_z K^T with K = G^-1 A^T J;
the diagonal blocks of G^-1 are computed exactly by the selected inverse of
G's banded Cholesky factor (Takahashi's recursion, O(n b^2)).  The incidental-parameter term
of :meth:`~fmbrdf_mi.fit.evaluate.albedos.PixelAlbedos.incidental`,
C_jk = tr(G^-1 A_j^T (I - P) A_k) (A_j = d A / d z_j), needs the full G^-1
here (the pairs are coupled), so it is estimated by Monte Carlo
(:meth:`CoupledPixelAlbedos.incidental_term`): positive semi-definite, from a fixed
seed (a fit is repeatable), to about 1 % (:attr:`CoupledPixelAlbedos.INCIDENTAL_DRAWS`).  Without it the shape
errors were 1.25-2.2x too small with three lights (128^2, model-exact data:
tools/bench_textured_bilinear.py).  With the smoothness prior it is not computed
(:data:`PRIOR_INCIDENTAL`).
"""
from __future__ import annotations

import numpy as np

#: The ``albedo`` option's values whose albedos are maps (one pair per pixel): this layout's and the
#: per-pixel one's (:class:`~fmbrdf_mi.fit.evaluate.albedos.PixelAlbedos`).
PER_PIXEL_LAYOUTS = ("per-pixel", "per-pixel-bilinear")

#: The ridges tried, in turn, on the Jacobi-scaled normal matrix (unit diagonal) when it is singular to
#: rounding (module docstring).
RIDGE = (1e-12, 1e-10, 1e-8)

#: Why the incidental-parameter sandwich is not reported with the albedo maps' smoothness prior
#: (:mod:`fmbrdf_mi.fit.evaluate.albedo_prior`; fit.json's uncertainty method): the errors are the posterior
#: ones, from the penalised information.
PRIOR_INCIDENTAL = ("the incidental-parameter sandwich is not computed with the albedo smoothness prior (the "
                    "posterior covariance of the penalised likelihood is reported)")


def bilinear_weights(rows, cols, offsets, present):
    """The interpolation of each sample's albedo from pixel centres: (corners (cells, n, 4, 2), weights
    (cells, n, 4)): each corner's pixel (row, col) and weight (0 for an unused corner, which then points at
    the sample's own pixel; the weights sum to 1).

    ``rows``, ``cols`` (cells,): each cell's pixel; ``offsets`` (n, 2): each sample's (dx right, dy down)
    from its cell's centre, in cells (|d| < 1/2 ... 1); ``present(r, c)`` -> bool array: whether pixel
    (r, c) has albedos (fitted; False off the image).  The rule at missing neighbours: module docstring.
    Per axis the sample's value is interpolated towards the neighbour on its side, or, that one missing,
    extrapolated linearly from the opposite neighbour, or, both missing, held constant; the 2-D weights are
    the product of the two axes', and a missing off-axis corner is the plane through the other three."""
    rows, cols = np.asarray(rows, np.int64), np.asarray(cols, np.int64)
    off = np.asarray(offsets, dtype=np.float64)
    cells, n = len(rows), len(off)
    dx, dy = off[:, 0][None, :], off[:, 1][None, :]                 # (1, n)
    sx, sy = np.sign(dx).astype(np.int64), np.sign(dy).astype(np.int64)
    ax, ay = np.abs(dx), np.abs(dy)
    r0, c0 = np.broadcast_to(rows[:, None], (cells, n)), np.broadcast_to(cols[:, None], (cells, n))

    def stencil(fwd, back, s, a):
        """One axis: (neighbour step, own weight, neighbour weight): interpolation towards a present
        neighbour, else linear extrapolation from the opposite one, else constant."""
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
                    np.stack([r0 + ky, c0 + kx], -1)], 2)            # (cells, n, 4, 2) (row, col)
    wt = np.stack([w_o, w_h, w_v, w_d], 2)
    # unused corners (weight 0) point at the own pixel (always present): their index stays valid
    idx = np.where((wt != 0)[..., None], idx, np.stack([r0, c0], -1)[:, :, None, :])
    return idx, wt


class CoupledPixelAlbedos:
    """One (a_s, a_b) per fitted pixel (per pixel and channel: ``channel_of``, ``labels`` as in
    :class:`~fmbrdf_mi.fit.evaluate.albedos.PixelAlbedos`), the pairs coupled and solved as one banded least
    squares (module docstring): each sample's albedos the combination ``corner_weights`` of the pairs
    ``corner_groups`` (bilinear interpolation: :class:`BilinearPixelAlbedos`; one corner of weight 1: the
    per-pixel layout), and with ``prior`` (:class:`~fmbrdf_mi.fit.evaluate.albedo_prior.SmoothPrior`) the
    prior's rows appended to the least squares (the normal matrix G + Lambda; the residuals and Kaufman's
    Jacobian get the prior's rows too).

    ``groups`` (cells, n): each sample's own pixel's group (for the maps, the split rule and the images per
    pixel); ``corner_groups``, ``corner_weights`` (cells, n, c): the groups and weights of each sample's
    combination; ``n_groups``; ``pixels`` (n_groups,) the flat pixel index of each group; ``name``: the
    ``albedo`` option's value it implements."""

    eliminates = True

    #: Monte Carlo draws of :meth:`incidental_term`: about INCIDENTAL_DRAWS[1] / pairs, at least [0], at most
    #: [2].  Each draw's estimate of a diagonal entry of C is a sum over all the pixels, its relative spread
    #: about sqrt(6 / pairs) (measured: tests/fit/test_bilinear_albedos.py), so the mean over the draws is
    #: good to about 1 % from ~120 pixels up (1.8 % at 36), at a cost of (1 + p) x draws banded solves.
    INCIDENTAL_DRAWS = (8, 60000, 512)

    def __init__(self, groups, corner_groups, corner_weights, n_groups, pixels, *, name="per-pixel-bilinear",
                 prior=None, channel_of=None, labels=None):
        self.groups = np.asarray(groups, dtype=np.int64)
        self.n_groups = int(n_groups)
        self.size = self.n_groups
        self.pixels = np.asarray(pixels, dtype=np.int64)
        self.channel_of = None if channel_of is None else np.asarray(channel_of, dtype=np.int64)
        self.labels = labels
        self.name = name
        self.prior = prior
        self.corner_groups = np.asarray(corner_groups, dtype=np.int64).reshape(self.groups.size, -1)
        self.corner_weights = np.asarray(corner_weights, dtype=np.float64).reshape(self.groups.size, -1)
        self.incidental_reason = PRIOR_INCIDENTAL
        lo, k, hi = self.INCIDENTAL_DRAWS
        self.incidental_draws = int(np.clip(np.ceil(k / max(self.n_groups, 1)), lo, hi))
        #: appended to the uncertainty method where the sandwich is reported
        self.incidental_method = (f"C estimated by Monte Carlo over {self.incidental_draws} noise draws "
                                  "(the albedo pairs are coupled)")
        self._factor = None    # (key columns, BandCholesky) of the last normal matrix
        self._incidental_last = None    # (draws, seed, count), the columns, C of the last incidental_term

    # ---- predictions
    def interpolate(self, a):
        """Each sample's interpolated value of the per-group ``a`` (n_groups,): (N,)."""
        return np.einsum("rc,rc->r", self.corner_weights, np.asarray(a, dtype=np.float64)[self.corner_groups])

    def mu(self, S, B, a_s, a_b):
        """(cells, n) predictions from the unit-albedo intensities S, B (cells, n)."""
        S, B = np.asarray(S), np.asarray(B)
        return self.interpolate(a_s).reshape(S.shape) * S + self.interpolate(a_b).reshape(B.shape) * B

    # ---- the sparse least squares
    def design(self, us, ub):
        """A as (columns (N, 8), values (N, 8)): each sample's non-zeros of d (whitened prediction) / d a,
        unknowns interleaved (a_s[g] at 2g, a_b[g] at 2g + 1), from its whitened unit-albedo columns ``us``,
        ``ub`` (N,)."""
        g, w = self.corner_groups, self.corner_weights
        us, ub = (np.asarray(u, dtype=np.float64).ravel() for u in (us, ub))
        return (np.concatenate([2 * g, 2 * g + 1], 1),
                np.concatenate([w * us[:, None], w * ub[:, None]], 1))

    def at(self, A, x):
        """A x: (N,) or (N, p) for x (2 n_groups,) or (2 n_groups, p)."""
        cols, vals = A
        x = np.asarray(x, dtype=np.float64)
        return np.einsum("rc,rc...->r...", vals, x[cols])

    def t_at(self, A, v):
        """A^T v: (2 n_groups,) or (2 n_groups, p) for v (N,) or (N, p)."""
        cols, vals = A
        v = np.asarray(v, dtype=np.float64)
        n = 2 * self.n_groups
        if v.ndim == 1:
            return np.bincount(cols.ravel(), weights=(vals * v[:, None]).ravel(), minlength=n)
        return np.stack([np.bincount(cols.ravel(), weights=(vals * v[:, k, None]).ravel(), minlength=n)
                         for k in range(v.shape[1])], 1)

    def _factorised(self, us, ub):
        """(A, factor) at the columns ``us``, ``ub``: the last factor when the columns are those it came
        from (to a relative 1e-12: the solve's S sqrt(w) and the Jacobian's -S / sd differ in rounding),
        else a new one (:class:`BandCholesky` of A^T A (+ Lambda, the prior's) with the ridge).  A: the
        data's design (the prior's rows are :attr:`prior`'s)."""
        key = (np.abs(np.asarray(us, float).ravel()), np.abs(np.asarray(ub, float).ravel()))
        A = self.design(us, ub)
        f = self._factor
        if f is not None and all(a.shape == b.shape and np.allclose(a, b, rtol=1e-12, atol=0.0)
                                 for a, b in zip(key, f[0])):
            return A, f[1]
        band = normal_band(A if self.prior is None else stack_rows(A, self.prior.rows()), 2 * self.n_groups)
        for ridge in (0.0,) + RIDGE:       # G singular (columns parallel to rounding): the ridge (module docstring)
            try:
                fac = BandCholesky(*band, ridge=ridge)
                break
            except np.linalg.LinAlgError:
                if ridge == RIDGE[-1]:
                    raise
        self._factor = (key, fac)
        return A, fac

    def solve(self, S, B, y, w):
        """Every group's (a_s, a_b), the weighted least squares of all samples at once (penalised by the
        prior, whose rows' data are 0): two arrays (n_groups,)."""
        sw = np.sqrt(np.asarray(w, dtype=np.float64)).ravel()
        A, fac = self._factorised(np.asarray(S, float).ravel() * sw, np.asarray(B, float).ravel() * sw)
        x = fac.solve(self.t_at(A, np.asarray(y, float).ravel() * sw))
        return x[0::2].copy(), x[1::2].copy()

    def free(self):
        """Degrees of freedom spent on the albedos: two per group (the ridge keeps every pair determined);
        with the prior, the dimension of its null space (2 per connected set of pixels and channel: the
        expected penalised chi^2 at the optimum is N - p - that when the maps follow the prior, module
        docstring of :mod:`fmbrdf_mi.fit.evaluate.albedo_prior`)."""
        return 2 * self.n_groups if self.prior is None else self.prior.null_dims()

    def prior_residuals(self, a_s, a_b):
        """The prior's residual rows (2E,) at the albedos (empty without a prior)."""
        return np.zeros(0) if self.prior is None else self.prior.residuals(a_s, a_b)

    def project(self, J, us, ub):
        """Kaufman's Jacobian (I - P) J, P = A G^-1 A^T the projection onto the albedos' columns (``us``,
        ``ub`` (N,): each sample's whitened unit-albedo columns; ``J`` (N, p)).  Returns (J_projected, K),
        K (n_groups, 2, p) = G^-1 A^T J (the albedos' regression on the shape unknowns).  With the prior the
        least squares is augmented by its rows R (which do not depend on the shape: their J rows are 0), G is
        A^T A + R^T R, and the projected Jacobian has the rows -R K appended: (N + 2E, p)."""
        A, fac = self._factorised(us, ub)
        p = J.shape[1]
        extra = 0 if self.prior is None else self.prior.n_rows
        if not p:
            return np.zeros((J.shape[0] + extra, 0)), np.zeros((self.n_groups, 2, 0))
        K = fac.solve(self.t_at(A, J))
        Jp = J - self.at(A, K)
        if self.prior is not None:
            Jp = np.concatenate([Jp, -self.prior.apply(K)])
        return Jp, K.reshape(self.n_groups, 2, p)

    def effective_parameters(self, us, ub):
        """tr(A (A^T A + Lambda)^-1 A^T) = tr((G + Lambda)^-1 G): the albedos' effective number of parameters
        (the trace of the hat matrix; 2 n_groups without a prior), from the inverse's entries within G's band
        (:meth:`BandCholesky.inverse_band`)."""
        A, fac = self._factorised(us, ub)
        band, b = normal_band(A, 2 * self.n_groups)
        Z = fac.inverse_band(b)
        return float(np.sum(Z[:, 0] * band[:, 0]) + 2.0 * np.sum(Z[:, 1:] * band[:, 1:]))

    # ---- the covariance
    @property
    def incidental(self):
        """The incidental-parameter term (:meth:`incidental_term`), or None with the smoothness prior (not
        computed there: ``incidental_reason``)."""
        return self.incidental_term if self.prior is None else None

    def incidental_term(self, us, ub, dcols, draws=None, seed=0):
        """The incidental-parameter term C (p, p) of the eliminated albedos' noise in Kaufman's information,
        as :meth:`~fmbrdf_mi.fit.evaluate.albedos.PixelAlbedos.incidental` defines it for uncoupled pairs:

            C_jk = tr(G^-1 A_j^T (I - P) A_k),   P = A G^-1 A^T,

        A the design at the whitened unit-albedo columns ``us``, ``ub`` (N,) and A_j the design at their
        derivatives ``dcols`` (p pairs (dus, dub) of (N,) arrays: d A / d z_j, the interpolation weights
        being fixed).  G^-1 is not banded, so C is estimated by Monte Carlo: with e ~ N(0, I_N) and
        b = G^-1 A^T e (covariance G^-1, the albedos' noise; in a direction G does not determine -- the
        ridge's -- its variance goes to 0, as the per-pixel layout's pseudo-inverse drops it), the
        columns v_j = (I - P) A_j b have E[v_j^T v_k] = C_jk.  The mean of v^T v over ``draws`` (default
        ``incidental_draws``) draws from the generator seeded ``seed``: positive semi-definite, the
        same at every call with the same columns (the last result is kept: the covariance and the maps ask
        for it at the same point)."""
        p = len(dcols)
        if not p:
            return np.zeros((0, 0))
        args = [np.asarray(c, dtype=np.float64).ravel() for c in (us, ub, *(c for pair in dcols for c in pair))]
        last = self._incidental_last
        if (last is not None and last[0] == (draws, seed, len(args))
                and all(np.array_equal(a, b) for a, b in zip(args, last[1]))):
            return last[2].copy()
        A, fac = self._factorised(us, ub)
        N = A[0].shape[0]
        m = int(draws or self.incidental_draws)
        e = np.random.default_rng(seed).standard_normal((N, m))
        b = fac.solve(self.t_at(A, e))                           # (2 n_groups, m), covariance G^-1
        V = []
        for dus, dub in dcols:
            v = self.at(self.design(dus, dub), b)                # A_j b (N, m)
            V.append(v - self.at(A, fac.solve(self.t_at(A, v))))
        V = np.stack(V, 1)                                       # (N, p, m)
        C = np.einsum("njd,nkd->jk", V, V) / m
        self._incidental_last = ((draws, seed, len(args)), [a.copy() for a in args], C)
        return C.copy()

    def covariance(self, us, ub, J, cov_z, scale=1.0):
        """(n_groups, 2, 2) covariance of each group's (a_s, a_b) with the shape unknowns free: the diagonal
        blocks of scale G^-1 + K cov_z K^T, K = G^-1 A^T J (``J`` (N, p) unprojected, ``cov_z`` already
        scaled); the blocks of G^-1 by :meth:`BandCholesky.diagonal_blocks`.  A pair without signal (its
        diagonal of A^T A zero) gets infinite variances."""
        A, fac = self._factorised(us, ub)
        C = scale * fac.diagonal_blocks()
        if J.shape[1]:
            K = fac.solve(self.t_at(A, J)).reshape(self.n_groups, 2, J.shape[1])
            C = C + np.einsum("gip,pq,gjq->gij", K, cov_z, K)
        C[np.any(fac.raw_diagonal.reshape(self.n_groups, 2) <= 0, axis=1)] = np.inf
        return C


class BilinearPixelAlbedos(CoupledPixelAlbedos):
    """One (a_s, a_b) per fitted pixel, at its centre; each sample's albedos interpolated bilinearly between
    the pixel centres around its point (module docstring).  Mono captures (one group per pixel).

    ``groups`` (cells, n): each sample's own pixel's group (for the maps, the split rule and the images per
    pixel, as in :class:`~fmbrdf_mi.fit.evaluate.albedos.PixelAlbedos`); ``corner_groups``,
    ``corner_weights`` (cells, n, 4): the groups and weights of each sample's interpolation; ``n_groups``;
    ``pixels`` (n_groups,) the flat pixel index of each group; ``prior``: the albedo maps' smoothness prior
    (None: none)."""

    def __init__(self, groups, corner_groups, corner_weights, n_groups, pixels, prior=None):
        super().__init__(groups, corner_groups, corner_weights, n_groups, pixels, name="per-pixel-bilinear",
                         prior=prior)


def stack_rows(A, R):
    """The design A (columns (N, c), values (N, c)) with the rows R (columns (M, d), values (M, d)) appended,
    the narrower padded with zero values (at a valid column)."""
    (ca, va), (cr, vr) = A, R
    c = max(ca.shape[1], cr.shape[1])

    def pad(cols, vals):
        k = c - cols.shape[1]
        if not k:
            return cols, vals
        return (np.concatenate([cols, np.repeat(cols[:, :1], k, 1)], 1),
                np.concatenate([vals, np.zeros((len(vals), k))], 1))

    (ca, va), (cr, vr) = pad(ca, va), pad(cr, vr)
    return np.concatenate([ca, cr]), np.concatenate([va, vr])


def normal_band(A, n):
    """The lower band of A^T A (A: :meth:`BilinearPixelAlbedos.design`, n unknowns): (band (n, b + 1) with
    band[i, d] = (A^T A)[i, i - d], b) , b the half bandwidth."""
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
    """Cholesky factor of a symmetric positive semi-definite banded matrix G (lower band ``band`` (n, b + 1),
    half bandwidth ``b``), Jacobi-scaled: G = D^1/2 Gs D^1/2 with Gs of unit diagonal (an unknown whose
    diagonal is 0: Gs_ii = 1, D_ii = 1), and Gs + ``ridge`` I = L L^T factored as a block-tridiagonal matrix
    with blocks of size max(b, 1): L block lower bidiagonal, diagonal blocks L_k, sub-diagonal blocks M_k.
    Dense NumPy per block: O(n b^2) time.  LinAlgError where Gs + ridge I is not positive definite."""

    def __init__(self, band, b, ridge=0.0):
        band = np.array(band, dtype=np.float64)
        n = band.shape[0]
        self.n = n
        self.raw_diagonal = band[:, 0].copy()
        d = band[:, 0]
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
        lo, hi = np.maximum(I, Jc), np.minimum(I, Jc)      # symmetric: the entry (max, min) of the lower band
        dd = lo - hi
        ok = dd <= b
        return np.where(ok, band[lo, np.where(ok, dd, 0)], 0.0)

    def solve(self, r):
        """G^-1 r for r (n,) or (n, p) (with the ridge: D^-1/2 (Gs + ridge I)^-1 D^-1/2 r)."""
        r = np.asarray(r, dtype=np.float64)
        sc = self.scale if r.ndim == 1 else self.scale[:, None]
        return sc * self._solve(sc * r)

    def _solve(self, r):
        e = self.edges
        K = len(e) - 1
        y = [None] * K
        for k in range(K):
            v = r[e[k]:e[k + 1]]
            if k:
                v = v - self.M[k - 1] @ y[k - 1]
            y[k] = self.Linv[k] @ v
        x = [None] * K
        for k in range(K - 1, -1, -1):
            v = y[k]
            if k + 1 < K:
                v = v - self.M[k].T @ x[k + 1]
            x[k] = self.Linv[k].T @ v
        return np.concatenate(x)

    def diagonal_blocks(self):
        """The 2 x 2 diagonal blocks (n / 2, 2, 2) of G^-1 (n even; blocks of size b even or 1 ... any: each
        2 x 2 block lies in one factor block when the factor's blocks have even sizes, else it is assembled
        from the full diagonal block of the inverse).  Selected inversion (Takahashi) on the block-bidiagonal
        factor: Z_KK = L_K^-T L_K^-1, and from the last block up

            Z_{k+1,k} = -Z_{k+1,k+1} M_k L_k^-1,   Z_kk = L_k^-T (L_k^-1 - M_k^T Z_{k+1,k}),

        which needs only the diagonal blocks of Z (of Gs; G's are D^-1/2 Z D^-1/2).  O(n b^2)."""
        e = self.edges
        diag = np.empty(self.n)
        off = np.zeros(self.n)               # Z[i, i + 1]
        for k, Z, Zlow, _ in self._selected_inverse():
            if Zlow is not None:
                off[e[k + 1] - 1] = Zlow[0, -1]          # Z[e_{k+1}, e_{k+1} - 1]
            diag[e[k]:e[k + 1]] = np.diag(Z)
            off[e[k]:e[k + 1] - 1] = np.diag(Z, 1)
        sc = self.scale
        out = np.empty((self.n // 2, 2, 2))
        out[:, 0, 0], out[:, 1, 1] = diag[0::2] * sc[0::2] ** 2, diag[1::2] * sc[1::2] ** 2
        out[:, 0, 1] = out[:, 1, 0] = off[0::2] * sc[0::2] * sc[1::2]
        return out

    def inverse_band(self, bw):
        """The lower band (n, bw + 1) of G^-1 (Z[i, i - d] at [i, d]; 0 where i - d < 0), bw at most the
        factor's half bandwidth: the same selected inversion as :meth:`diagonal_blocks`, keeping each block
        row's Z_{k,k-1} and Z_kk (an entry within the band lies in one of them).  O(n b^2)."""
        e = self.edges
        K = len(e) - 1
        s = max(e[1] - e[0], 1) if K else 1
        if bw > s:
            raise ValueError(f"inverse_band: bandwidth {bw} above the factor's {s}")
        out = np.zeros((self.n, bw + 1))
        Z = None
        for k, Z, Zlow, Znext in self._selected_inverse():
            if Zlow is not None:        # Z_{k+1,k}: row block k + 1's left part
                self._fill(out, k + 1, Zlow, Znext, bw)
        if K:
            self._fill(out, 0, None, Z, bw)
        sc = self.scale
        for d in range(bw + 1):
            i = np.arange(d, self.n)
            out[i, d] *= sc[i] * sc[i - d]
        return out

    def _selected_inverse(self):
        """Takahashi's recursion on the block-bidiagonal factor, from the last block up (:meth:`diagonal_blocks`):
        yields (k, Z_kk, Z_{k+1,k} or None for the last block, Z_{k+1,k+1} or None), Z = Gs^-1."""
        Znext = None
        for k in range(len(self.edges) - 2, -1, -1):
            Li = self.Linv[k]
            if Znext is None:
                Z, Zlow = Li.T @ Li, None
            else:
                Zlow = -(Znext @ self.M[k]) @ Li
                Z = Li.T @ (Li - self.M[k].T @ Zlow)
            yield k, Z, Zlow, Znext
            Znext = Z

    def _fill(self, out, k, Zleft, Zkk, bw):
        """Rows of block k of the band from [Z_{k,k-1} | Z_kk] (Zleft None: block 0)."""
        e = self.edges
        r0, r1 = e[k], e[k + 1]
        c0 = r0 if Zleft is None else e[k - 1]
        strip = Zkk if Zleft is None else np.concatenate([Zleft, Zkk], 1)
        rows = np.arange(r0, r1)
        for d in range(bw + 1):
            j = rows - d
            ok = j >= c0
            out[rows[ok], d] = strip[rows[ok] - r0, j[ok] - c0]
