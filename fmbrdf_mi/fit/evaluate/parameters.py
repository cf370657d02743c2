"""The parameters of a fit as one table, :class:`Parameters`, of :class:`Param` rows (shape parameters per
material, free light powers, albedos per group), built in one place so that no name is parsed back."""
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
    """One named parameter: ``name`` as reported, ``base`` the model's name, ``kind`` ``shape`` (BSDF traverse
    ``key``), ``power`` (image ``image``'s light power) or ``albedo``; ``scale`` as
    :class:`~fmbrdf_mi.fit.evaluate.models.Bounds`; ``fixed`` None when free."""

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
    """The parameter table of a fit of ``model``.  ``materials``: M (None: one); ``channels``: labels of
    per-channel albedos; ``maps``: no albedo rows; ``powers``: the given relative powers G_0 .. G_{K-1} of a
    joint fit whose P_1 .. P_{K-1} are free; ``bounds`` {name: (lo, hi)} and ``fixed`` {name: value} (a model
    name stands for every material's).  ``rows`` are in :meth:`report`'s order; ``shape``: the rows of z."""

    def __init__(self, model, *, materials=None, channels=None, maps=False, powers=None, bounds=None, fixed=None):
        self.model = model
        self.count = None if materials is None else int(materials)
        self.channels = None if channels is None else tuple(channels)
        self.given = None if powers is None else [float(g) for g in powers]
        #: the albedo names of one group: (surface, body); r_k = k_b / k_s for the fmbrdf (paper: s_s + s_b)
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
        rows = [self._narrowed(r, *bounds[r.name]) if r.name in bounds else r for r in rows]
        for what, given in (("bounds", bounds), ("fixed", fixed)):
            unknown = [k for k in given if k not in self.shape_names]
            if unknown:
                raise ValueError(f"{what}: {model.name} has no shape parameter {unknown[0]!r} (it has "
                                 f"{', '.join(self.shape_names)})")
        self._index([dataclasses.replace(r, fixed=fixed[r.name]) if r.name in fixed else r for r in rows])

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
        """The reported name: ``eta``, ``eta[1]`` (material 1), ``k_s[R]`` (channel R), ``power_2`` (image 2)."""
        if image is not None:
            return f"{base}_{image}"
        label = material if channel is None else self.channels[channel]
        return base if label is None else f"{base}[{label}]"

    @property
    def shape_names(self):
        return tuple(r.name for r in self.shape)

    @property
    def reported_names(self):
        return tuple(r.name for r in self.rows)

    def param(self, name):
        return self.row[name]

    def report(self, shape_values, a_s, a_b):
        """{name: value} in the order of ``rows``; albedos times the model's ``albedo_factor``."""
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
        """Inverse of :meth:`report` for a start, from the model's names (every material starts there): (shape
        values, a_s, a_b); the powers from their names, else the given ones."""
        model = self.model
        names = model.shape_names + self.albedo_pair
        if not isinstance(reported, Mapping):
            raise InputError(f"{model.name} parameters: expected a dict of {', '.join(names)}, got {reported!r:.80}")
        missing = [n for n in names if n not in reported]
        if missing:
            raise InputError(f"{model.name} parameters: missing {', '.join(missing)} (give all of "
                             f"{', '.join(names)}), got {reported!r:.80}")

        def number(v):
            try:
                return not isinstance(v, (bool, str, bytes)) and float(v) is not None
            except (TypeError, ValueError):
                return False

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

    def expand(self, values):
        """{name: v} of the model's shape names -> the same for every material (``eta[1]`` kept as is)."""
        if not values or self.count is None:
            return values
        out = {}
        for k, v in values.items():
            rows = [r.name for r in self.shape if r.kind == "shape" and r.base == k]
            out.update(dict.fromkeys(rows, v) if rows else {k: v})
        return out

    def nest(self, flat):
        """``{"k_s[R]": x, ...}`` -> ``{"k_s": {"R": x, ...}}``; other names stay as they are."""
        out = {}
        for k, v in flat.items():
            r = self.row.get(k)
            if r is not None and r.channel is not None:
                out.setdefault(r.base, {})[self.channels[r.channel]] = v
            else:
                out[k] = v
        return out

    def per_material(self, flat):
        """[{name: x} per material] of ``flat``'s rows under the model's names; other names are left out."""
        out = [{} for _ in range(self.count or 1)]
        for k, v in (flat or {}).items():
            r = self.row.get(k)
            if r is not None:
                out[r.material or 0][r.name if r.material is None else r.base] = v
        return out
