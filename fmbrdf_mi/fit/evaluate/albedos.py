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
