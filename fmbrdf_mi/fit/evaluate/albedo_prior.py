"""A Gaussian smoothness prior on per-pixel albedo maps (``FitOptions.albedo_smooth``, ``--albedo-smooth``).

penalty = sum over 4-neighbour pairs (same channel) of ((k_s,i - k_s,j) / tau_s)^2 + ((k_b,i - k_b,j) / tau_b)^2,
added to chi^2 as design rows with data 0 so the albedos stay eliminated; improper (each connected
component keeps its mean free).
"""
from __future__ import annotations

import numpy as np


def neighbour_pairs(pixels, width, channel_of=None):
    """(E, 2) group indices (i, j), i < j, of right or down neighbours of the same channel."""
    pixels = np.asarray(pixels, dtype=np.int64)
    ch = np.zeros(len(pixels), np.int64) if channel_of is None else np.asarray(channel_of, dtype=np.int64)
    C = int(ch.max()) + 1 if len(ch) else 1
    group = np.full((int(pixels.max(initial=0)) + width + 1) * C, -1)     # (pixel, channel) -> group
    group[pixels * C + ch] = np.arange(len(pixels))
    out = []
    for step, ok in ((1, pixels % width != width - 1), (width, np.ones(len(pixels), bool))):
        j = group[(pixels + step) * C + ch]
        hit = ok & (j >= 0)
        out.append(np.stack([np.flatnonzero(hit), j[hit]], 1))
    pairs = np.sort(np.concatenate(out), axis=1)
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]


def components(n, pairs):
    """The number of connected components of n nodes joined by ``pairs`` (E, 2) (isolated nodes count)."""
    label = np.arange(n)
    if len(pairs):
        i, j = pairs[:, 0], pairs[:, 1]
        while True:            # min-label propagation with pointer jumping
            m = np.minimum(label[i], label[j])
            new = label.copy()
            np.minimum.at(new, i, m)
            np.minimum.at(new, j, m)
            new = new[new]
            if np.array_equal(new, label):
                break
            label = new
    return int(len(np.unique(label)))


class SmoothPrior:
    """The prior on ``n_groups`` interleaved albedo pairs; ``tau``: (tau_s, tau_b) in the maps' units or one
    number; a row is factor (a_i - a_j) / tau."""

    def __init__(self, pairs, n_groups, tau, factor=1.0):
        self.pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        self.n_groups = int(n_groups)
        self.tau = tuple(float(t) for t in np.broadcast_to(np.asarray(tau, dtype=np.float64), (2,)))
        self.factor = float(factor)
        self.weights = (self.factor / self.tau[0], self.factor / self.tau[1])
        self.n_rows = 2 * len(self.pairs)
        self._null = None

    def rows(self):
        """The design rows (columns (2E, 2), values (2E, 2)): the E k_s differences, then the k_b ones."""
        i, j = self.pairs[:, 0], self.pairs[:, 1]
        ws, wb = self.weights
        cols = np.concatenate([np.stack([2 * i, 2 * j], 1), np.stack([2 * i + 1, 2 * j + 1], 1)])
        vals = np.concatenate([np.tile([ws, -ws], (len(i), 1)), np.tile([wb, -wb], (len(i), 1))])
        return cols, vals.astype(np.float64)

    def residuals(self, a_s, a_b):
        """The residuals (2E,) (or (2E, p)): the a_s rows, then the a_b rows."""
        a_s, a_b = np.asarray(a_s, dtype=np.float64), np.asarray(a_b, dtype=np.float64)
        i, j = self.pairs[:, 0], self.pairs[:, 1]
        return np.concatenate([self.weights[0] * (a_s[i] - a_s[j]), self.weights[1] * (a_b[i] - a_b[j])])

    def apply(self, x):
        """D x / tau for interleaved unknowns x (2 n_groups,) or (2 n_groups, p)."""
        x = np.asarray(x, dtype=np.float64)
        return self.residuals(x[0::2], x[1::2])

    def penalty(self, a_s, a_b):
        """The prior's term of chi^2: the sum of the squared :meth:`residuals`."""
        r = self.residuals(a_s, a_b)
        return float(r @ r)

    def null_dims(self):
        """The null space's dimension: 2 per connected component of the neighbour graph."""
        if self._null is None:
            self._null = 2 * components(self.n_groups, self.pairs)
        return self._null

    def describe(self):
        return (f"Gaussian first-difference prior on 4-neighbour pairs: tau_s {self.tau[0]:g}, tau_b "
                f"{self.tau[1]:g} (k_s, k_b units)")
