"""The result of a fit (:class:`FitResult`) and the JSON encoder of every fit output."""
from __future__ import annotations

import dataclasses

import numpy as np


def json_default(x):
    """``json.dump``'s ``default``: NumPy scalars and arrays as JSON numbers and lists."""
    if isinstance(x, (np.generic, np.ndarray)):
        return x.tolist()
    raise TypeError(f"not JSON serialisable: {type(x)}")


@dataclasses.dataclass
class FitResult:
    """The result of every fit.  ``params``: the model's reported parameters (per-channel albedos as
    ``{"R": .., "G": .., "B": ..}``); ``result["key"]`` reads a field or a ``details`` entry; :meth:`to_json`
    writes the fields but :data:`INTERNAL`, and those of :data:`OPTIONAL` only when set."""

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
    #: free light powers (:func:`fmbrdf_mi.fit.problem.free_power.split_result`)
    powers: dict = None
    #: colour mosaics: the channels of the per-channel albedos
    channels: list = None
    #: the mode's own numbers (read them as ``result["key"]``)
    details: dict = dataclasses.field(repr=False, default=None)
    #: normal refinement: the refined normal map (H, W, 3) and the pixels refined (H, W)
    normals: np.ndarray = dataclasses.field(repr=False, default=None)
    mask: np.ndarray = dataclasses.field(repr=False, default=None)
    #: per-pixel albedos (``FitOptions.albedo="per-pixel"``): the maps' summary numbers
    albedo: dict = None
    #: the albedo maps of :func:`fmbrdf_mi.fit.api.assemble.albedo_maps`
    maps: dict = dataclasses.field(repr=False, default=None)
    #: several materials: fit.json's ``materials`` block (:func:`fmbrdf_mi.fit.api.assemble.settle`)
    materials: dict = None
    #: the problem behind the result (:class:`fmbrdf_mi.fit.api.assemble.Fitted`)
    fitted: object = dataclasses.field(repr=False, default=None, compare=False)

    OPTIONAL = ("images", "powers", "channels", "albedo", "materials")
    INTERNAL = ("pixels", "details", "normals", "mask", "maps", "fitted")

    def to_json(self):
        d = dataclasses.asdict(dataclasses.replace(self, **dict.fromkeys(self.INTERNAL)))
        return {k: v for k, v in d.items() if k not in self.INTERNAL and not (k in self.OPTIONAL and v is None)}

    def __getitem__(self, key):
        if key in self.__dataclass_fields__:
            return getattr(self, key)
        if key in (self.details or {}):
            return self.details[key]
        raise KeyError(key)
