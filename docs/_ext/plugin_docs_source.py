"""The plugins' class docstrings (no Sphinx or docutils here, so that the test suite can read them with
the test extras alone; :mod:`plugin_docstring` renders them)."""
import inspect

#: plugin name -> (module, class holding the methods and docstring)
PLUGINS = {
    "fmbrdf": ("fmbrdf_mi.bsdf", "_FMBRDFMethods"),
    "orennayar": ("fmbrdf_mi.oren_nayar_bsdf", "_OrenNayarMethods"),
}


def plugin_doc(name):
    """The cleaned docstring of plugin ``name``, without its implementation notes
    (the paragraph that starts "Its methods become")."""
    import importlib

    import mitsuba as mi

    if mi.variant() is None:
        mi.set_variant("llvm_ad_rgb")
    module, cls = PLUGINS[name]
    doc = inspect.cleandoc(getattr(importlib.import_module(module), cls).__doc__ or "")
    return doc.split("\n\nIts methods become")[0]
