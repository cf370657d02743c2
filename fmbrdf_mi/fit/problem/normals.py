"""The joint normal refinement's problem (minimised by :mod:`fmbrdf_mi.fit.api.normal_joint`): the fit's
problem with per-pixel normals as extra unknowns and a smoothness prior on them."""
from __future__ import annotations

import math

import numpy as np

from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.evaluate.pixel_model import PixelEvaluator
from fmbrdf_mi.fit.objectives.objective import LikelihoodObjective
from fmbrdf_mi.fit.problem.data import same_noise
from fmbrdf_mi.fit.problem.problem import Problem
from fmbrdf_mi.sensor import samples as SM
from fmbrdf_mi.sensor.noise import NoiseModel

def tangent_bases(n):
    """Two unit tangents (t1, t2), each (N, 3), orthogonal to the unit normals ``n`` (N, 3) and to each other."""
    a = np.where(np.abs(n[:, 2:3]) < 0.9, np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]))
    t1 = np.cross(n, a)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    return t1, np.cross(n, t1)


#: The smoothness priors: stencil coefficients along image rows and columns.
PRIORS = {"curvature": (1.0, -2.0, 1.0), "membrane": (1.0, -1.0)}


def stencils(mask, prior="curvature"):
    """(E, S) pixel indices of the prior's stencils and their coefficients (S,): ``membrane`` first
    differences, ``curvature`` second differences (constant curvature is not pulled flat)."""
    try:
        coef = PRIORS[prior]
    except KeyError:
        raise InputError(f"prior: expected one of {', '.join(PRIORS)}, got {prior!r}") from None
    h, w = mask.shape
    pos = -np.ones((h, w), int)
    ys, xs = np.nonzero(mask)
    pos[ys, xs] = np.arange(len(ys))
    out = []
    for dy, dx in ((0, 1), (1, 0)):
        idx = []
        for s in range(len(coef)):
            y2, x2 = ys + s * dy, xs + s * dx
            ok = (y2 < h) & (x2 < w)
            idx.append(np.where(ok, pos[np.minimum(y2, h - 1), np.minimum(x2, w - 1)], -1))
        idx = np.stack(idx, 1)
        out.append(idx[np.all(idx >= 0, 1)])
    return np.concatenate(out).astype(np.int64), np.array(coef)


class NormalProblem(Problem):
    """The fit's :class:`~fmbrdf_mi.fit.problem.problem.Problem` with every refined pixel's normal as two more
    unknowns and the smoothness prior; rows ordered (image, pixel, sample).  A sample's normal interpolates the
    map bilinearly, corners outside the refined pixels extrapolated linearly (constant extrapolation near the
    silhouette biases the material)."""

    def __init__(self, obs, m, params, lam, prior="curvature"):
        self.K = len(obs)
        self.shape = obs[0].shape
        self.idx = np.flatnonzero(m.ravel())
        self.n = N = len(self.idx)
        smps = [o.samples if o.samples is not None else SM.from_stokes(o.stokes) for o in obs]
        A = smps[0].analyser()
        for k, s in enumerate(smps[1:], 1):
            if not (np.allclose(s.analyser(), A) and np.allclose(s.offsets, smps[0].offsets)):
                raise InputError(f"normal refinement: image {k}'s polariser layout differs from image 0's")
        self._stencil(np.asarray(smps[0].offsets, float))
        vmap = obs[0].view_dirs.reshape(-1, 3)
        self.views = vmap[self.idx] / np.linalg.norm(vmap[self.idx], axis=1, keepdims=True)
        vs = np.einsum("nsq,nsqc->nsc", self.cw, vmap[self.corner]).reshape(-1, 3)
        self.sample_views = np.tile(vs / np.linalg.norm(vs, axis=1, keepdims=True), (self.K, 1))
        self.lights = np.repeat(np.stack([o.light_dir for o in obs]), N * 4, axis=0)
        irr = np.repeat(np.array([o.irradiance for o in obs], float), N * 4)
        y = np.concatenate([s.at(self.idx) for s in smps])                  # (K N, 4), image-major
        noise = same_noise(obs) or NoiseModel(step=smps[0].step)
        ev = PixelEvaluator(params.model, self.sample_views, self.sample_views, self.lights, irr)
        super().__init__(params, ev, LikelihoodObjective(y, A, noise, smps[0].dof))
        self.nmap = None
        self.stencils, self.coef = stencils(m, prior)
        self.lam = float(lam)
        self.set_scale()

    def _stencil(self, offsets):
        h, w = self.shape
        rows, cols = np.divmod(self.idx, w)
        y = rows[:, None] + offsets[None, :, 1]
        x = cols[:, None] + offsets[None, :, 0]
        y0 = np.clip(np.floor(y).astype(int), 0, h - 2)
        x0 = np.clip(np.floor(x).astype(int), 0, w - 2)
        fy, fx = y - y0, x - x0
        self.corner = np.stack([y0 * w + x0, y0 * w + x0 + 1, (y0 + 1) * w + x0, (y0 + 1) * w + x0 + 1], 2)
        self.cw = np.stack([(1 - fy) * (1 - fx), (1 - fy) * fx, fy * (1 - fx), fy * fx], 2)   # (N, 4, 4)
        pos = -np.ones(h * w, int)
        pos[self.idx] = np.arange(len(self.idx))
        # a corner outside the refined pixels: extrapolate
        own = self.idx[:, None, None]
        out = pos[self.corner] < 0
        cy, cx = np.divmod(self.corner, w)
        oy, ox = 2 * rows[:, None, None] - cy, 2 * cols[:, None, None] - cx
        inside = (oy >= 0) & (oy < h) & (ox >= 0) & (ox < w)
        o = np.where(inside, np.clip(oy, 0, h - 1) * w + np.clip(ox, 0, w - 1), 0)
        lin = out & inside & (pos[o] >= 0)
        a = np.where(out, own, self.corner)
        b = np.where(lin, o, own)
        self.ncorner = np.concatenate([a, b], 2)                                # (N, 4, 8) flat map indices
        self.nw = np.concatenate([np.where(lin, 2.0, 1.0) * self.cw, np.where(lin, -self.cw, 0.0)], 2)
        self.cpix = pos[self.ncorner]                                           # unknown index of every term

    def set_scale(self):
        """c = mean S0^2 / variance from the current variances, so lam c is the prior's weight in chi^2 units."""
        s = self.obj.y.reshape(self.K, self.n, 4).sum(axis=2).mean(axis=1) / 2.0      # mean S0 per image
        v = self.obj.var.reshape(self.K, self.n, 4).mean(axis=(1, 2))
        self.w_prior = self.lam * float(np.mean(s ** 2 / v))

    def full(self, base, n):
        """The flat (H W, 3) normal map: ``base`` with the refined pixels set to ``n``."""
        out = base.reshape(-1, 3).copy()
        out[self.idx] = n
        return out

    def sample_normals(self, nmap):
        """(N, 4, 3) unit normals at the samples' points and the interpolated vectors' lengths (N, 4)."""
        v = np.einsum("nsq,nsqc->nsc", self.nw, nmap[self.ncorner])
        ln = np.linalg.norm(v, axis=2)
        return v / ln[..., None], ln

    def _set(self, ns):
        self.ev.set_geometry(np.tile(ns.reshape(-1, 3), (self.K, 1)), self.sample_views, self.lights)

    def parts_at(self, st, nmap, jac=False):
        """The model's parts at the material ``st`` and the flat normal map ``nmap`` (one BSDF evaluation)."""
        self._set(self.sample_normals(nmap)[0])
        self.n_evals += 1
        return self.ev.parts(st.shape, self.names if jac else ())

    def parts(self, st, jac=False):
        return self.parts_at(st, self.nmap, jac)

    def prior(self, n):
        d = sum(c * n[self.stencils[:, s]] for s, c in enumerate(self.coef))
        return math.sqrt(self.w_prior) * np.asarray(d).ravel()

    def energy(self, st, nmap):
        parts = self.parts_at(st, nmap)
        r = self.obj.residuals(parts, st)
        rp = self.prior(nmap[self.idx])
        return float(r @ r), float(rp @ rp), parts

    def linearise(self, st, nmap, h=1e-3):
        """r (m,), J_m (m, p), the normal Jacobian as (pixels (m, Q), values (m, Q, 2)), tangents, z."""
        parts = self.parts_at(st, nmap, jac=True)
        z = self.to_z(st)
        r, Jm = self.residuals_and_jacobian(parts, st, z)
        ns, ln = self.sample_normals(nmap)
        ta, tb = tangent_bases(ns.reshape(-1, 3))
        g = np.zeros((len(r), 2))     # d r / d (tangent step of the row's own sample normal)
        for j, t in enumerate((ta, tb)):
            rr = []
            for d in (h, -h):
                nn = ns.reshape(-1, 3) + d * t
                self._set(nn / np.linalg.norm(nn, axis=1, keepdims=True))
                rr.append(self.obj.residuals(self.ev.parts(st.shape), st))
            g[:, j] = (rr[0] - rr[1]) / (2 * h)
        g[~np.isfinite(g)] = 0.0
        n = nmap[self.idx]
        t1, t2 = tangent_bases(n)
        # chain rule: d n_s / d u_q = (w_q / |m_s|) (I - n_s n_s^T) t1_q; the sample tangents are orthogonal
        # to n_s, so d r / d u_q = (w_q / |m_s|) (g_a T_a + g_b T_b) . t1_q
        N, K = self.n, self.K
        grad = (g[:, :1] * np.tile(ta, (K, 1)) + g[:, 1:] * np.tile(tb, (K, 1))).reshape(K, N, 4, 3)
        q = np.where(self.cpix >= 0, self.cpix, 0)                           # (N, 4 samples, Q terms)
        scale = self.nw / ln[..., None]                                      # (N, 4, Q)
        val = np.stack([np.einsum("knsc,nsqc->knsq", grad, t1[q]), np.einsum("knsc,nsqc->knsq", grad, t2[q])], -1)
        val = val * scale[None, ..., None]
        Q = self.cpix.shape[2]
        pix = np.broadcast_to(self.cpix[None], (K, N, 4, Q)).reshape(-1, Q)
        return r, Jm, (pix, val.reshape(-1, Q, 2)), (t1, t2), z

    def prior_gradient(self, gn, t, n):
        """Add the prior's gradient (w coef_s (sum_s' coef_s' n_s') on pixel s's tangents) to ``gn`` in place."""
        if not len(self.stencils):
            return gn
        d = self.w_prior * sum(c * n[self.stencils[:, s]] for s, c in enumerate(self.coef))    # (E, 3)
        k = self.stencils.T.ravel()                                              # place-major, as s loops
        dd = np.tile(d, (len(self.coef), 1))
        g = np.repeat(np.asarray(self.coef, float), len(self.stencils))[:, None] * np.stack(
            [np.sum(t[0][k] * dd, 1), np.sum(t[1][k] * dd, 1)], 1)
        idx, vals = np.concatenate([np.arange(len(gn)), k]), np.concatenate([gn, g])
        gn[...] = np.stack([np.bincount(idx, weights=vals[:, a], minlength=len(gn)) for a in range(2)], 1)
        return gn
