"""The result of a fit (:class:`FitResult`) and the JSON encoder of every fit output."""
from __future__ import annotations

import dataclasses
import json

import numpy as np


def json_default(x):
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, tuple):
        return list(x)
    raise TypeError(f"not JSON serialisable: {type(x)}")


@dataclasses.dataclass
class FitResult:
    """The result of every fit: one image or several, one albedo pair or per-channel albedos, free powers.

    ``params``: the model's reported parameters (per-channel albedos as ``{"R": .., "G": .., "B": ..}``).
    ``result["key"]`` reads a field or a ``details`` entry.
    """

    model: str
    params: dict
    loss: float
    loss_terms: dict
    std_errors: dict
    history: list
    stop_reason: str
    n_pixels: int
    n_outliers: int
    timings: dict
    options: dict
    weakly_identified: list = dataclasses.field(default_factory=list)
    converged: bool = True
    objective: str = "paper"
    uncertainty: dict = dataclasses.field(default_factory=dict)
    noise: dict = None
    pixels_excluded: dict = dataclasses.field(default_factory=dict)
    starts: list = dataclasses.field(default_factory=list)
    #: flat indices of the fitted (super-)pixels; several images: one array per image
    pixels: object = dataclasses.field(repr=False, default=None)
    #: several images: per-image diagnostics (pixels, light, chi^2 per dof, intensity error, power)
    images: list = None
    #: free light powers: the ``powers`` block of :func:`fmbrdf_mi.fit.problem.free_power.split_result`
    powers: dict = None
    #: colour mosaics: the channels of the per-channel albedos
    channels: list = None
    #: the mode's own numbers, not written by :meth:`to_json` (read them as ``result["key"]``)
    details: dict = dataclasses.field(repr=False, default=None)
    #: normal refinement: the refined normal map (H, W, 3) and the pixels refined (H, W); not in :meth:`to_json`
    normals: np.ndarray = dataclasses.field(repr=False, default=None)
    mask: np.ndarray = dataclasses.field(repr=False, default=None)
    #: per-pixel albedos (``FitOptions.albedo="per-pixel"``): the maps' summary numbers; in :meth:`to_json`
    albedo: dict = None
    #: the maps (:func:`fmbrdf_mi.fit.api.assemble.albedo_maps`): ``k_s``, ``k_b``, ``k_s_se``, ``k_b_se``,
    #: ``identified``, (H, W) or (C, H, W); NaN where no pixel was fitted; not in :meth:`to_json`
    maps: dict = dataclasses.field(repr=False, default=None)

    #: several materials: the block of :func:`fmbrdf_mi.fit.api.assemble.material_block`; in :meth:`to_json`
    materials: dict = None
    #: the problem behind the result (:class:`fmbrdf_mi.fit.api.assemble.Fitted`); not in :meth:`to_json`
    fitted: object = dataclasses.field(repr=False, default=None, compare=False)

    #: written by :meth:`to_json` only when set
    OPTIONAL = ("images", "powers", "channels", "albedo", "materials")

    #: never written by :meth:`to_json`
    INTERNAL = ("pixels", "details", "normals", "mask", "maps", "fitted")

    def to_json(self):
        d = dataclasses.asdict(dataclasses.replace(self, **dict.fromkeys(self.INTERNAL)))
        for k in self.INTERNAL:
            d.pop(k)
        for k in self.OPTIONAL:
            if d[k] is None:
                d.pop(k)
        return d

    def __getitem__(self, key):
        if key in self.__dataclass_fields__:
            return getattr(self, key)
        if self.details and key in self.details:
            return self.details[key]
        raise KeyError(key)

    def save_json(self, path, extra=None):
        d = self.to_json()
        d.update(extra or {})
        with open(path, "w") as f:
            json.dump(d, f, indent=2, default=json_default)
