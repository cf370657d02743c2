"""The parameters of a fit as one table (as lmfit's ``Parameters``): one row per named parameter.

A fit estimates a model's shape parameters (per material with a label
image), the light powers of a joint fit's images after the first
(:mod:`fmbrdf_mi.fit.problem.free_power`) and two albedos per group (shared,
per colour channel, per material; albedo maps are reported as maps, not
rows).  Each is a :class:`Param` row: its name as fit.json and the summaries
write it, the model's name of it, what it is (``shape``, ``power``,
``albedo``), its bounds and scale for the bounded reparameterisation
(:class:`~fmbrdf_mi.fit.evaluate.models.Bounds`), its coarse-search grid,
and its group: the material, colour channel or image it belongs to.
:class:`Parameters` builds the rows of one fit in one place; the solver, the
uncertainty and the report read the rows, and no name is parsed back.
"""
from __future__ import annotations

import copy
import dataclasses
import math
from collections.abc import Mapping

import numpy as np

from fmbrdf_mi.fit.errors import InputError

#: A free light power P_k is searched in [G_k / POWER_RANGE, G_k * POWER_RANGE] (G_k: the given power).
POWER_RANGE = 1000.0


@dataclasses.dataclass(frozen=True)
class Param:
    """One named parameter: ``name`` (as reported), ``base`` (the model's name of it), ``kind`` (``shape``: a
    BSDF parameter, traverse ``key``; ``power``: image ``image``'s light power; ``albedo``: reported from the
    albedos of its group), bounds ``lo``, ``hi``, ``scale`` of the bounded reparameterisation, coarse-search
    ``grid``; its group: ``material`` index, ``channel`` index (None: not per material / channel); ``fixed``:
    the value it is held at (None: free)."""

    name: str
    base: str
    kind: str
    key: str = None
    lo: float = 0.0
    hi: float = math.inf
    scale: str = "linear"
    grid: tuple = ()
    material: int = None
    channel: int = None
    image: int = None
    fixed: float = None


class Parameters:
    """The parameter table of a fit of ``model``.

    ``materials``: M (per-material shape parameters and, without maps, albedos; None: one material);
    ``channels``: the colour channels' labels of per-channel albedos (None: none); ``maps``: the albedos are
    maps (no albedo rows); ``powers``: the given relative powers G_0 .. G_{K-1} of a joint fit whose powers
    P_1 .. P_{K-1} are free (image 0 is the reference; None: none); ``bounds``: {name: (lo, hi)} narrowing
    the model's bounds, ``fixed``: {name: value} held fixed (the model's names stand for every material's;
    ValueError naming a bound outside the model's or a name that is not a shape parameter).

    ``rows`` are in the order of :meth:`report` (per material its shape parameters then its albedos; per
    channel each albedo name over the channels; the powers last); ``shape`` the rows the optimiser sees
    through the bounds (shape parameters and powers), in the order of z.
    """

    def __init__(self, model, *, materials=None, channels=None, maps=False, powers=None, bounds=None, fixed=None):
        self.model = model
        self.count = None if materials is None else int(materials)
        self.channels = None if channels is None else tuple(channels)
        self.given = None if powers is None else [float(g) for g in powers]
        #: the albedo names of one group: (surface, body); r_k = k_b / k_s for the fmbrdf (paper eq:fmbrdf)
        self.albedo_pair = (model.surface_name, model.body_name)
        rows = []
        for m in ([None] if self.count is None else range(self.count)):
            rows += [dataclasses.replace(p, name=self.name_of(p.name, material=m), material=m) for p in model.shape]
            if not maps and self.channels is None:
                rows += [Param(self.name_of(b, material=m), b, "albedo", material=m) for b in self.albedo_pair]
        if not maps and self.channels is not None:
            rows += [Param(self.name_of(b, channel=c), b, "albedo", channel=c)
                     for b in self.albedo_pair for c in range(len(self.channels))]
        rows += [Param(self.name_of("power", image=k), "power", "power", None, g / POWER_RANGE, g * POWER_RANGE,
                       "log", (g,), image=k) for k, g in enumerate(self.given or ()) if k]
        self._index(rows)
        bounds, fixed = self.expand(bounds) or {}, self.expand(fixed) or {}
        self._index([self._narrowed(r, *bounds[r.name]) if r.name in bounds else r for r in rows])
        names = self.shape_names
        unknown = [k for k in bounds if k not in names]
        if unknown:
            raise ValueError(f"bounds: {model.name} has no shape parameter {unknown[0]!r} (it has {', '.join(names)})")
        unknown = [k for k in fixed if k not in names]
        if unknown:
            raise ValueError(f"fixed: {model.name} has no shape parameter {', '.join(unknown)} "
                             f"(it has {', '.join(names)})")
        self._index([dataclasses.replace(r, fixed=fixed[r.name]) if r.name in fixed else r for r in self.rows])

    def _index(self, rows):
        self.rows = tuple(rows)
        self.row = {r.name: r for r in rows}
        self.shape = tuple(r for r in rows if r.kind != "albedo")
        self.powers = tuple(r for r in rows if r.kind == "power")
        self.albedo_names = tuple(r.name for r in rows if r.kind == "albedo")

    @staticmethod
    def _narrowed(row, lo, hi):
        lo, hi = float(lo), float(hi)
        if not (row.lo <= lo < hi <= row.hi):
            raise ValueError(f"bounds of {row.name}: need {row.lo:g} <= lo < hi <= {row.hi:g}, got ({lo:g}, {hi:g})")
        return dataclasses.replace(row, lo=lo, hi=hi)

    def with_fixed(self, values):
        """This table with the rows ``values`` ({name: value}) held fixed too."""
        out = copy.copy(self)
        out._index([dataclasses.replace(r, fixed=values[r.name]) if r.name in values else r for r in self.rows])
        return out

    def name_of(self, base, material=None, channel=None, image=None):
        """The reported name of parameter ``base`` of a group: ``eta``, ``eta[1]`` (material 1), ``k_s[R]``
        (channel R), ``power_2`` (image 2's light power).  The one place these names are made."""
        if image is not None:
            return f"{base}_{image}"
        label = material if channel is None else self.channels[channel]
        return base if label is None else f"{base}[{label}]"

    @property
    def shape_names(self):
        return tuple(r.name for r in self.shape)

    @property
    def reported_names(self):
        """The names of :meth:`report`'s parameters."""
        return tuple(r.name for r in self.rows)

    def param(self, name):
        return self.row[name]

    def report(self, shape_values, a_s, a_b):
        """The parameters as reported to the user, {name: value} in the order of ``rows``: the shape
        values and powers as they are, each group's albedos through the model's ``albedo_factor`` (the fmbrdf's
        k_s and r_k = k_b / k_s)."""
        groups = self.count if self.channels is None else len(self.channels)
        if groups is not None and self.albedo_names:
            a_s, a_b = (np.broadcast_to(np.asarray(a, dtype=np.float64), (groups,)) for a in (a_s, a_b))
        out = {}
        for r in self.rows:
            if r.kind != "albedo":
                out[r.name] = float(shape_values[r.name])
                continue
            g = r.material if r.channel is None else r.channel
            ks, kb = (self.model.albedo_factor * a for a in ((a_s, a_b) if g is None else (a_s[g], a_b[g])))
            if r.base == self.albedo_pair[0]:
                out[r.name] = float(ks)
            elif self.model.body_ratio:
                out[r.name] = float(kb / ks) if ks > 0 else float("inf")
            else:
                out[r.name] = float(kb)
        return out

    def split(self, reported):
        """Inverse of :meth:`report` for a start (``init``): (shape values, a_s, a_b) from the model's own
        names (every material starts there: a_s, a_b arrays (M,)); the powers from their names, else the
        given ones.  InputError naming what is missing or not a number (``dict(eta=9)`` for fmbrdf)."""
        model = self.model
        names = model.shape_names + self.albedo_pair
        if not isinstance(reported, Mapping):
            raise InputError(f"{model.name} parameters: expected a dict of {', '.join(names)}, got {reported!r:.80}")
        missing = [n for n in names if n not in reported]
        if missing:
            raise InputError(f"{model.name} parameters: missing {', '.join(missing)} (give all of "
                             f"{', '.join(names)}), got {reported!r:.80}")

        def number(v):
            if isinstance(v, (bool, str, bytes)):
                return False
            try:
                float(v)
            except (TypeError, ValueError):
                return False
            return True

        bad = [n for n in names if not number(reported[n])]
        if bad:
            raise InputError(f"{model.name} parameters: {bad[0]} must be a number, got {reported[bad[0]]!r}")
        shape = {r.name: float(reported[r.base]) for r in self.shape if r.kind == "shape"}
        shape.update({r.name: float(reported.get(r.name, self.given[r.image])) for r in self.powers})
        ks = float(reported[self.albedo_pair[0]])
        kb = ks * float(reported[self.albedo_pair[1]]) if model.body_ratio else float(reported[self.albedo_pair[1]])
        a_s, a_b = ks / model.albedo_factor, kb / model.albedo_factor
        if self.count is not None:
            a_s, a_b = np.full(self.count, a_s), np.full(self.count, a_b)
        return shape, a_s, a_b

    def of(self, values, m):
        """Material ``m``'s shape values under the model's names."""
        return {r.base: values[r.name] for r in self.shape if r.kind == "shape" and r.material == m}

    def expand(self, values):
        """{name: v} of the model's shape names (``bounds``, ``fixed``) -> the same for every material; names of
        the table's rows (``eta[1]``) are kept."""
        if not values or self.count is None:
            return values
        out = {}
        for k, v in values.items():
            rows = [r.name for r in self.shape if r.kind == "shape" and r.base == k]
            out.update(dict.fromkeys(rows, v) if rows else {k: v})
        return out

    def nest(self, flat):
        """``{"k_s[R]": x, ...}`` -> ``{"k_s": {"R": x, ...}}``: each channel's row under its model's name and
        channel label, in the order of ``flat``; other names stay as they are."""
        out = {}
        for k, v in flat.items():
            r = self.row.get(k)
            if r is not None and r.channel is not None:
                out.setdefault(r.base, {})[self.channels[r.channel]] = v
            else:
                out[k] = v
        return out

    def per_material(self, flat):
        """[{name: x} per material] of the rows of ``flat`` (a report, standard errors, intervals): under the
        model's names (one material: under the rows' own names); names not in the table are left out."""
        out = [{} for _ in range(self.count or 1)]
        for k, v in (flat or {}).items():
            r = self.row.get(k)
            if r is not None:
                out[r.material or 0][r.name if r.material is None else r.base] = v
        return out
