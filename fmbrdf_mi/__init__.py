"""fmbrdf-mi: the Fresnel Microfacet BRDF as a polarised Mitsuba 3 BSDF.

    import mitsuba as mi
    mi.set_variant("llvm_ad_spectral_polarized")
    import fmbrdf_mi
    fmbrdf_mi.register()          # also done on import when a variant is set
    bsdf = mi.load_dict({"type": "fmbrdf", "eta": 1.5, "alpha": 0.3})
"""
from ._llvm import LLVMTooOldError, check_llvm, pin_newest_llvm
from .params import ParameterError

__version__ = "0.1.0"
__all__ = ["register", "ParameterError", "LLVMTooOldError", "SUPPORTED_VARIANTS"]

pin_newest_llvm()

#: Variants in which the plugin works.  Scalar variants (unpolarised only:
#: a Python BSDF called once per ray is for checks, not production) build
#: their tables with the LLVM backend.
SUPPORTED_VARIANTS = (
    "llvm_ad_rgb", "llvm_ad_mono", "llvm_ad_mono_polarized", "llvm_ad_spectral",
    "llvm_ad_spectral_polarized", "cuda_ad_rgb", "cuda_ad_mono", "cuda_ad_mono_polarized",
    "cuda_ad_spectral", "cuda_ad_spectral_polarized", "scalar_rgb", "scalar_mono", "scalar_spectral",
)

_registered = set()


def register(variant=None):
    """Register the ``fmbrdf`` BSDF plugin for the current (or given) Mitsuba variant.

    Raises ValueError for a variant the plugin cannot run in, and
    LLVMTooOldError when Dr.Jit's LLVM backend would crash on this machine.
    """
    import mitsuba as mi

    if variant is not None:
        mi.set_variant(variant)
    variant = mi.variant()
    if variant is None:
        raise RuntimeError("fmbrdf_mi.register(): call mi.set_variant(...) first, e.g. "
                           "mi.set_variant('llvm_ad_spectral_polarized')")
    if variant not in SUPPORTED_VARIANTS:
        raise ValueError(f"fmbrdf: variant '{variant}' is not supported; use one of "
                         f"{', '.join(SUPPORTED_VARIANTS)}")
    if not variant.startswith("cuda"):
        check_llvm()
    if variant in _registered:
        return
    from .bsdf import make_plugin_class

    cls = make_plugin_class()
    mi.register_bsdf("fmbrdf", lambda props: cls(props))
    _registered.add(variant)


def _register_if_variant_set():
    import sys

    mi = sys.modules.get("mitsuba")
    if mi is not None and mi.variant() in SUPPORTED_VARIANTS:
        register()


_register_if_variant_set()
