"""The albedo layouts of a fit: which pair of linear albedos each sample's prediction uses.

Every model is linear in two albedos (paper eq:fmbrdf: k_s scales the
surface term, k_b = r_k k_s the body term), so sample k of cell i is

    mu_ik = a_s[g_k] S_ik + a_b[g_k] B_ik,

with S, B the unit-albedo intensities behind the sample's polariser
(:class:`~fmbrdf_mi.fit.evaluate.pixel_model.Parts` through the analyser)
and g_k the albedo group of sample k.  A layout says what the groups are:

* **shared** (``layout=None``: mono and joint fits): one pair for every
  sample; a :class:`~fmbrdf_mi.fit.evaluate.models.State` holds two floats;
* **per channel** (:class:`ChannelAlbedos`: colour mosaics): g_k is sample
  k's colour filter; a State holds two arrays (one entry per channel), and
  :class:`ChannelModel` reports each channel's k_s and r_k (``k_s[R]`` ...).

(The free light powers of a joint fit scale whole images and are non-linear
unknowns of the problem: :mod:`fmbrdf_mi.fit.problem.free_power`.)

Per group the albedos are the non-negative weighted least squares of that
group's samples (:func:`nnls2`), and d mu / d log a_s[g] = a_s[g] S on the
group's samples, 0 elsewhere: both in closed form.
"""
from __future__ import annotations

import numpy as np

from fmbrdf_mi.fit.camera.colour_samples import CHANNELS


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


class ChannelAlbedos:
    """One (a_s, a_b) per colour channel: ``channel`` (n,) is the group of each of a cell's n samples."""

    def __init__(self, channel, labels=CHANNELS):
        self.channel = np.asarray(channel, dtype=int)
        self.labels = tuple(labels)
        self.size = len(self.labels)
        self.masks = [self.channel == g for g in range(self.size)]

    def mu(self, S, B, a_s, a_b):
        """(cells, n) predictions from the unit-albedo intensities S, B (cells, n)."""
        return np.asarray(a_s)[self.channel] * S + np.asarray(a_b)[self.channel] * B

    def solve(self, S, B, y, w):
        """Each group's (a_s, a_b) by :func:`nnls2` of its samples: two arrays (size,)."""
        out = [nnls2(S[:, m].ravel(), B[:, m].ravel(), y[:, m].ravel(), w[:, m].ravel()) for m in self.masks]
        return np.array([o[0] for o in out]), np.array([o[1] for o in out])

    def columns(self, S, B, a_s, a_b):
        """d mu / d log a_s[g] for every g, then d mu / d log a_b[g]: 2 size arrays (cells, n)."""
        return ([a_s[g] * S * m for g, m in enumerate(self.masks)]
                + [a_b[g] * B * m for g, m in enumerate(self.masks)])


def floored(a_s, a_b):
    """The albedos with those at 0 raised to 1e-9 of the largest (so that their logs stay finite)."""
    floor = 1e-9 * max(float(np.max(a_s)), float(np.max(a_b)), 1e-300)
    return np.maximum(a_s, floor), np.maximum(a_b, floor)


class ChannelModel:
    """A model whose albedos are per channel (``layout``: :class:`ChannelAlbedos`).

    :meth:`report` gives the shape parameters and, per channel, the model's
    albedo names with the channel in brackets (``k_s[R]``, ``r_k[R]``, ...):
    one flat name per estimated quantity, as :mod:`fmbrdf_mi.fit.uncertainty`
    needs; :meth:`nest` turns them into ``{"k_s": {"R": ..}}``.  Everything
    else is the base model's.
    """

    def __init__(self, base, layout):
        self.base, self.layout = base, layout

    def __getattr__(self, name):  # name, shape, shape_names, param, bsdf_dict, albedo_factor, ...
        return getattr(self.base, name)

    def report(self, shape_values, a_s, a_b):
        a_s, a_b = np.broadcast_to(a_s, (self.layout.size,)), np.broadcast_to(a_b, (self.layout.size,))
        per = [self.base.report(shape_values, a_s[g], a_b[g]) for g in range(self.layout.size)]
        out = {n: per[0][n] for n in self.base.shape_names}
        for key in per[0]:
            if key not in self.base.shape_names:
                out.update({f"{key}[{c}]": per[g][key] for g, c in enumerate(self.layout.labels)})
        return out

    def nest(self, flat):
        """``{"k_s[R]": x, ...}`` -> ``{"k_s": {"R": x, ...}}`` (shape names stay as they are)."""
        out = {}
        for k, v in flat.items():
            if k.endswith("]") and "[" in k:
                name, label = k[:-1].split("[", 1)
                out.setdefault(name, {})[label] = v
            else:
                out[k] = v
        return out


def ls2_groups(S, B, y, w, groups, n_groups):
    """The weighted least squares of I ~ a_s S + a_b B of every group at once, unconstrained: ``groups``
    (same shape as S) the group of each sample.  Returns (a_s, a_b) arrays (n_groups,); a group whose
    two columns are parallel (or empty) gets the minimum-norm solution (its split undetermined)."""
    g = np.asarray(groups).ravel()
    S, B, y, w = (np.asarray(a, dtype=np.float64).ravel() for a in (S, B, y, w))

    def total(v):
        return np.bincount(g, weights=v, minlength=n_groups)

    G = np.empty((n_groups, 2, 2))
    G[:, 0, 0], G[:, 1, 1] = total(w * S * S), total(w * B * B)
    G[:, 0, 1] = G[:, 1, 0] = total(w * S * B)
    b = np.stack([total(w * S * y), total(w * B * y)], 1)
    x = np.einsum("gij,gj->gi", np.linalg.pinv(G, rcond=1e-10, hermitian=True), b)
    return x[:, 0], x[:, 1]


class PixelAlbedos:
    """One (a_s, a_b) per pixel of the object (per pixel and colour channel for colour mosaics): the
    albedo maps of a textured object (issue: textured objects).

    ``groups`` (cells, n): the albedo group of each of a cell's n samples;
    ``n_groups`` how many there are; ``pixels`` (n_groups,) the flat pixel
    index of each group and ``channel_of`` (n_groups,) its colour channel
    (None: mono).  A joint fit of several images of one view gives the same
    group to the same pixel in every image.

    Unlike the shared and per-channel layouts, these albedos are not unknowns
    of the optimiser: they are *eliminated* (variable projection, Golub and
    Pereyra): at every shape point each group's pair is its own weighted least
    squares (``ls2_groups``, closed form), the optimiser sees the shape
    parameters only, and its Jacobian is Kaufman's, (I - P) J_theta, with P
    the projection onto the albedos' columns (block diagonal: one 2 x 2 block
    per group).  At the optimum (I - P) J_theta gives exactly the shape
    parameters' Fisher information with the albedos free (the Schur
    complement), and each group's covariance follows in closed form
    (:meth:`covariance`).  The albedos are *not* held non-negative: they
    are thousands of nuisance parameters of the shape, and clipping the
    poorly determined ones at 0 (k_s away from the highlight) biases the
    shape (measured on a render of a uniform sphere: eta 4 standard errors
    off with the clipping, 1.2 without); an estimate below 0 is a small
    albedo measured with noise, and its standard error says so.
    """

    eliminates = True

    def __init__(self, groups, n_groups, pixels, channel_of=None, labels=None):
        self.groups = np.asarray(groups, dtype=np.int64)
        self.n_groups = int(n_groups)
        self.size = self.n_groups
        self.pixels = np.asarray(pixels, dtype=np.int64)
        self.channel_of = None if channel_of is None else np.asarray(channel_of, dtype=np.int64)
        self.labels = labels
        self._rank = None

    def mu(self, S, B, a_s, a_b):
        """(cells, n) predictions from the unit-albedo intensities S, B (cells, n)."""
        return np.asarray(a_s)[self.groups] * S + np.asarray(a_b)[self.groups] * B

    def solve(self, S, B, y, w):
        """Every group's (a_s, a_b) (``ls2_groups``): two arrays (n_groups,)."""
        return ls2_groups(S, B, y, w, self.groups, self.n_groups)

    def free(self):
        """How many albedos the data spent unknowns on (degrees of freedom): two per group, one where a
        group's columns are parallel (the last :meth:`project`'s ranks; before one: two per group)."""
        return int(2 * self.n_groups if self._rank is None else self._rank.sum())

    def _gram(self, us, ub):
        """Per group the Gram matrix U^T U of its two albedo columns (n_groups, 2, 2)."""
        g = self.groups.ravel()
        G = np.zeros((self.n_groups, 2, 2))
        for i, u in enumerate((us, ub)):
            for j, v in enumerate((us, ub)):
                G[:, i, j] = np.bincount(g, weights=u * v, minlength=self.n_groups)
        return G

    def _blocks(self, us, ub):
        """Per group the pseudo-inverse of the Gram matrix of its two albedo columns (n_groups, 2, 2); the
        groups' ranks are kept for :meth:`free`."""
        G = self._gram(us, ub)
        self._rank = np.linalg.matrix_rank(G, rtol=1e-10, hermitian=True)
        return np.linalg.pinv(G, rcond=1e-10, hermitian=True)

    def project(self, J, us, ub):
        """Kaufman's Jacobian (I - P) J: ``J`` (N, p) the residuals' derivatives with respect to the shape
        unknowns, ``us``, ``ub`` (N,) those with respect to each sample's group's a_s and a_b; P projects
        onto the albedos' columns.  Returns (J_projected, K), K (n_groups, 2, p) = G^+ U^T J per group (the
        albedos' regression on the shape unknowns)."""
        g = self.groups.ravel()
        Gi = self._blocks(us, ub)
        K = np.einsum("gij,gjp->gip", Gi, self._cross(us, ub, J))
        return J - us[:, None] * K[g, 0] - ub[:, None] * K[g, 1], K

    def _cross(self, us, ub, J):
        """U^T J per group (n_groups, 2, p)."""
        g = self.groups.ravel()
        c = np.zeros((self.n_groups, 2, J.shape[1]))
        for i, u in enumerate((us, ub)):
            for k in range(J.shape[1]):
                c[:, i, k] = np.bincount(g, weights=u * J[:, k], minlength=self.n_groups)
        return c

    def incidental(self, us, ub, dcols):
        """The incidental-parameter term C (p, p) of the eliminated albedos' noise in Kaufman's information
        (issue 25; tools/diag_pp_sandwich.py): with U_g = [us, ub] a group's (whitened) albedo columns,
        G_g = U_g^T U_g, M_g = I - U_g G_g^+ U_g^T and A_gj = d U_g / d z_j (``dcols``: p pairs (dus, dub) of
        (N,) arrays),

            C_jk = sum_g tr(A_gj^T M_g A_gk G_g^+)
                 = sum_g [tr(X_gjk G_g^+) - tr(Y_gj^T G_g^+ Y_gk G_g^+)],  X_gjk = A_gj^T A_gk, Y_gj = U_g^T A_gj.

        J^T J evaluated at the estimated albedos is on average H + C (H: the profile score's mean
        derivative), so the shape estimate's covariance is H^-1 J^T J H^-1 with H = J^T J - C (the
        sandwich; Neyman and Scott 1948's incidental parameters, here two per group).  C is positive
        semi-definite.  Sums per group by bincount (no loop over groups)."""
        g = self.groups.ravel()
        p = len(dcols)
        Gi = np.linalg.pinv(self._gram(us, ub), rcond=1e-10, hermitian=True)      # (n_groups, 2, 2)
        A = [np.stack(d, -1) for d in dcols]                                       # p x (N, 2)
        U = np.stack([us, ub], -1)                                                  # (N, 2)

        def total(v):   # (N, 2, 2) -> (n_groups, 2, 2)
            out = np.empty((self.n_groups, 2, 2))
            for a in range(2):
                for b in range(2):
                    out[:, a, b] = np.bincount(g, weights=v[:, a, b], minlength=self.n_groups)
            return out

        Y = [total(U[:, :, None] * Aj[:, None, :]) for Aj in A]                    # U^T A_j per group
        GY = [np.einsum("gab,gbc->gac", Gi, y) for y in Y]                          # G^+ U^T A_j
        C = np.empty((p, p))
        for j in range(p):
            for k in range(j, p):
                X = total(A[j][:, :, None] * A[k][:, None, :])                     # A_j^T A_k per group
                C[j, k] = C[k, j] = (np.einsum("gab,gba->", X, Gi)
                                     - np.einsum("gba,gbc,gca->", Y[j], GY[k], Gi))
        return C

    def covariance(self, us, ub, J, cov_z, scale=1.0):
        """(n_groups, 2, 2) covariance of each group's (a_s, a_b) with the shape unknowns free:
        scale G^-1 + K cov_z K^T, K = G^-1 U^T J (the block inverse of the full information matrix;
        ``J`` (N, p) the residuals' unprojected shape derivatives, ``cov_z`` their covariance, already
        scaled).  A group whose two columns are parallel (G singular to 1e-10: the data fix one
        combination of a_s and a_b, not the split) gets infinite variances."""
        G = self._gram(us, ub)
        det = G[:, 0, 0] * G[:, 1, 1] - G[:, 0, 1] ** 2
        ok = det > 1e-10 * np.maximum(G[:, 0, 0] * G[:, 1, 1], 1e-300)
        Gi = np.zeros_like(G)
        d = np.where(ok, det, 1.0)
        Gi[:, 0, 0], Gi[:, 1, 1] = G[:, 1, 1] / d, G[:, 0, 0] / d
        Gi[:, 0, 1] = Gi[:, 1, 0] = -G[:, 0, 1] / d
        K = np.einsum("gij,gjp->gip", Gi, self._cross(us, ub, J))
        C = scale * Gi + np.einsum("gip,pq,gjq->gij", K, cov_z, K)
        C[~ok] = np.inf
        return C


class PixelModel:
    """A model whose albedos are maps (``layout``: :class:`PixelAlbedos`): :meth:`report` gives the shape
    parameters only (the albedo maps are reported as maps: :func:`fmbrdf_mi.fit.api.fitting.fit`'s
    ``res.maps``); everything else is the base model's."""

    def __init__(self, base, layout):
        self.base, self.layout = base, layout

    def __getattr__(self, name):
        return getattr(self.base, name)

    def report(self, shape_values, a_s, a_b):
        return {n: float(shape_values[n]) for n in self.base.shape_names}
