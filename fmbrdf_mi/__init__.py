"""fmbrdf-mi: the Fresnel Microfacet BRDF as a polarised Mitsuba 3 BSDF.

::

    import mitsuba as mi
    mi.set_variant("llvm_ad_spectral_polarized")
    import fmbrdf_mi              # registers "fmbrdf" (and "orennayar") now and for every variant set later
    bsdf = fmbrdf_mi.load_dict({"type": "fmbrdf", "eta": 1.5, "alpha": 0.3})
    rough = fmbrdf_mi.load_dict({"type": "orennayar", "sigma": 0.4, "reflectance": 0.6})
    # (mi.load_dict works too; it reports a bad value as a RuntimeError, see load_dict)
"""
import re
import sys
import warnings

from ._llvm import LLVMTooOldError, check_llvm, pin_newest_llvm
from .params import ParameterError

__version__ = "0.1.0"
__all__ = ["register", "load_dict", "load_file", "check_variant", "ParameterError", "LLVMTooOldError",
           "UntestedVersionWarning", "check_versions", "SUPPORTED_VARIANTS", "TESTED_VERSIONS"]

#: The versions the package was tested with (pyproject.toml pins them).
TESTED_VERSIONS = {"mitsuba": "3.9.1", "drjit": "1.5.0"}


class UntestedVersionWarning(UserWarning):
    """Mitsuba or Dr.Jit is not the version the package was tested with."""


def check_versions():
    """Warn (:class:`UntestedVersionWarning`) if Mitsuba or Dr.Jit is not the tested version.

    Returns the list of ``(package, installed version)`` that differ.
    """
    from importlib import metadata

    bad = []
    for pkg, tested in TESTED_VERSIONS.items():
        mod = sys.modules.get(pkg)
        try:
            version = getattr(mod, "__version__", None) or metadata.version(pkg)
        except metadata.PackageNotFoundError:
            continue
        if version != tested:
            bad.append((pkg, version))
    if bad:
        found = ", ".join(f"{p} {v}" for p, v in bad)
        want = ", ".join(f"{p} {v}" for p, v in TESTED_VERSIONS.items())
        warnings.warn(f"fmbrdf_mi {__version__} was tested with {want} only; found {found}. "
                      "It may fail or give wrong results: install the tested versions "
                      f"(pip install {' '.join(f'{p}=={v}' for p, v in TESTED_VERSIONS.items())}) "
                      "or run the tests (python -m pytest tests) first.",
                      UntestedVersionWarning, stacklevel=3)
    return bad


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


def check_variant(variant):
    """Raise ValueError (one line) for a Mitsuba variant the plugin cannot run in: one not in
    :data:`SUPPORTED_VARIANTS` (the scalar polarised variants among them), or a ``cuda_`` variant on a
    machine without a CUDA device (Dr.Jit's own message then speaks of its thread state)."""
    if variant not in SUPPORTED_VARIANTS:
        polarised = [v for v in SUPPORTED_VARIANTS if v.endswith("_polarized")]
        raise ValueError(f"fmbrdf: variant '{variant}' is not supported; use one of {', '.join(SUPPORTED_VARIANTS)} "
                         f"(the polarised ones: {', '.join(polarised)})")
    if variant.startswith("cuda"):
        import drjit as dr

        if not dr.has_backend(dr.JitBackend.CUDA):
            raise ValueError(f"variant '{variant}': no CUDA device here (Dr.Jit's CUDA backend is unavailable); "
                             f"use the llvm_ variant, {variant.replace('cuda_', 'llvm_', 1)}")


def register(variant=None):
    """Register the ``fmbrdf`` and ``orennayar`` BSDF plugins for the current (or given) Mitsuba variant.

    Raises ValueError for a variant the plugin cannot run in, and
    LLVMTooOldError when Dr.Jit's LLVM backend would crash on this machine.
    """
    import mitsuba as mi

    if variant is not None:
        check_variant(variant)
        mi.set_variant(variant)
    variant = mi.variant()
    if variant is None:
        raise RuntimeError("fmbrdf_mi.register(): call mi.set_variant(...) first, e.g. "
                           "mi.set_variant('llvm_ad_spectral_polarized')")
    check_variant(variant)
    if not variant.startswith("cuda"):
        check_llvm()
    if variant in _registered:
        return
    from .bsdf import make_plugin_class
    from .oren_nayar_bsdf import make_plugin_class as make_oren_nayar_class

    cls = make_plugin_class()
    mi.register_bsdf("fmbrdf", lambda props: cls(props))
    on_cls = make_oren_nayar_class()
    mi.register_bsdf("orennayar", lambda props: on_cls(props))
    _registered.add(variant)


def _register_unsupported(variant):
    """In a variant the plugin cannot run in, register stand-ins named ``fmbrdf`` and ``orennayar`` whose
    construction raises :func:`check_variant`'s error, so that ``mi.load_dict`` says why instead of
    "plugin not found"."""
    import mitsuba as mi

    def refuse(props):
        check_variant(variant)

    for name in ("fmbrdf", "orennayar"):
        mi.register_bsdf(name, refuse)
    _registered.add(variant)


def _variant_error(exc):
    """The ValueError of :func:`check_variant` inside a Mitsuba RuntimeError raised by a stand-in of
    :func:`_register_unsupported`, or None."""
    m = re.search(r"(?:^|\n)\s*ValueError: (fmbrdf: variant .* is not supported.*)\Z", str(exc).strip(), re.S)
    return ValueError(" ".join(m.group(1).split())) if m else None


def _parameter_error(exc, where=None):
    """The ParameterError inside a Mitsuba RuntimeError (which wraps a plugin's Python
    exception, traceback and all, in its message), or None."""
    text = str(exc)
    m = re.search(r"(?:^|\n)\s*(?:[\w.]+\.)?ParameterError: (.*)\Z", text.strip(), re.S)
    if not m:
        return None
    msg = " ".join(m.group(1).split())
    return ParameterError(f"{where}: {msg}" if where else msg)


_ALBEDOS = {"fmbrdf": ("k_s", "k_b", "r_k"), "orennayar": ("reflectance",)}
_NUMBERS = {"fmbrdf": ("eta", "alpha", "beta", "kappa"), "orennayar": ("sigma",)}
_WORDS = {"fmbrdf": ("tables",), "orennayar": ("form",)}


def check_dict(d, where=""):
    """Raise :class:`ParameterError` for a value Mitsuba would crash on or report with a traceback.

    Anywhere in ``d`` (a scene or plugin dict): a ``None`` value (``mi.load_dict`` segfaults on it).
    In an ``fmbrdf`` or ``orennayar`` dict: a scalar parameter that is not a number (a list, a word,
    True) or NaN, an albedo that is not a number >= 0, a nested dict (texture, spectrum, rgb) or a
    Mitsuba object, an option (``tables``, ``form``) that is not text.
    """
    import math
    import numbers

    from .params import check_albedo, check_scalar

    if not isinstance(d, dict):
        return
    kind = d.get("type")
    name = kind if isinstance(kind, str) else "load_dict"
    at = f"{where}: " if where else ""
    for k, v in d.items():
        if v is None:
            raise ParameterError(f"{at}{name}: '{k}' is None; give a value or leave the key out")
        if isinstance(v, dict):
            check_dict(v, f"{where}.{k}" if where else str(k))
            continue
        if kind in _NUMBERS and k in _NUMBERS[kind]:
            if isinstance(v, (bool, list, tuple, dict)):
                raise ParameterError(f"{at}{kind}: '{k}' must be a number, got {v!r}")
            if kind == "fmbrdf" and isinstance(v, (numbers.Real, str)):
                try:
                    check_scalar(k, v)
                except ParameterError as e:
                    raise ParameterError(f"{at}{e}") from None
            elif isinstance(v, (numbers.Real, str)):
                try:
                    x = float(v)
                except ValueError:
                    raise ParameterError(f"{at}{kind}: '{k}' must be a number, got {v!r}") from None
                if not math.isfinite(x):
                    raise ParameterError(f"{at}{kind}: '{k}' must be finite, got {v!r}")
        elif kind in _ALBEDOS and k in _ALBEDOS[kind]:
            if isinstance(v, (bool, str, list, tuple)):
                raise ParameterError(f"{at}{kind}: '{k}' must be a number >= 0, {{'type': 'rgb', 'value': "
                                     f"[r, g, b]}} or a texture, got {v!r}")
            if isinstance(v, numbers.Real):
                try:
                    check_albedo(k, [float(v)])
                except ParameterError as e:
                    raise ParameterError(f"{at}{str(e).replace('fmbrdf:', f'{kind}:', 1)}") from None
        elif kind in _WORDS and k in _WORDS[kind] and not isinstance(v, str):
            raise ParameterError(f"{at}{kind}: '{k}' must be text, got {v!r}")


def load_dict(d, *args, **kwargs):
    """``mi.load_dict`` that raises :class:`ParameterError` (one line) for a bad fmbrdf value.

    Mitsuba wraps every exception a plugin's constructor raises in a
    ``RuntimeError`` whose message holds the Python traceback, so a plain
    ``mi.load_dict`` cannot raise the documented type; this one unwraps it.
    Values Mitsuba would crash on (None anywhere, which segfaults) or report
    with a traceback are refused first (:func:`check_dict`).  Other errors are passed on as Mitsuba raised them.
    """
    import mitsuba as mi

    check_dict(d)
    _register_current()
    try:
        return mi.load_dict(d, *args, **kwargs)
    except RuntimeError as e:
        err = _parameter_error(e) or _variant_error(e)
        if err is None:
            raise
        raise err from None


def load_file(path, *args, **kwargs):
    """``mi.load_file`` that raises :class:`ParameterError` naming the file for a bad fmbrdf value
    (see :func:`load_dict`)."""
    import mitsuba as mi

    _register_current()
    try:
        return mi.load_file(str(path), *args, **kwargs)
    except RuntimeError as e:
        err = _parameter_error(e, where=str(path)) or _variant_error(e)
        if err is None:
            raise
        raise err from None


def _register_current():
    import mitsuba as mi

    if mi.variant() is not None and mi.variant() not in _registered:
        if mi.variant() in SUPPORTED_VARIANTS:
            register()
        else:
            _register_unsupported(mi.variant())


def _on_variant(old, new):
    """Mitsuba variant callback: register the plugin for every supported variant that gets set, and the
    stand-ins that say so (:func:`_register_unsupported`) in the others."""
    if new is None or new in _registered:
        return
    if new not in SUPPORTED_VARIANTS:
        _register_unsupported(new)
        return
    try:
        register()
    except LLVMTooOldError as e:  # register() raises it; load_dict would only say "unknown plugin"
        warnings.warn(str(e), RuntimeWarning, stacklevel=2)


def _install():
    import mitsuba as mi

    check_versions()
    mi.detail.add_variant_callback(_on_variant)
    _register_current()


_install()
