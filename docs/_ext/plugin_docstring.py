"""``.. plugin-docstring:: fmbrdf``: the BSDF plugin's class docstring, Mitsuba style.

The parameter table of a plugin lives in its class docstring (as Mitsuba's
plugins do); this directive renders that docstring (reStructuredText) into the
page, so the reference cannot drift from the code.  The docstring is parsed
with the state of the document it sits in, so in a MyST page put the directive
in an ``eval-rst`` block (a MyST directive would parse it as Markdown)::

    ```{eval-rst}
    .. plugin-docstring:: fmbrdf
    ```
"""
import inspect

from docutils import nodes
from docutils.statemachine import StringList
from sphinx.util.docutils import SphinxDirective

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


class PluginDocstring(SphinxDirective):
    required_arguments = 1
    has_content = False

    def run(self):
        name = self.arguments[0]
        if name not in PLUGINS:
            raise self.error(f"unknown plugin {name!r}; known: {', '.join(PLUGINS)}")
        module, _ = PLUGINS[name]
        self.env.note_dependency(__import__(module, fromlist=["x"]).__file__)
        container = nodes.container(classes=["plugin-docstring"])
        lines = StringList(plugin_doc(name).splitlines(), source=f"{module} docstring")
        self.state.nested_parse(lines, self.content_offset, container)
        return [container]


def setup(app):
    app.add_directive("plugin-docstring", PluginDocstring)
    return {"version": "1", "parallel_read_safe": True, "parallel_write_safe": True}
