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
from docutils import nodes
from docutils.statemachine import StringList
from sphinx.util.docutils import SphinxDirective

from plugin_docs_source import PLUGINS, plugin_doc  # noqa: F401  (PLUGINS: the names the directive takes)


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
