"""The package's shape: layers that import only from below, no import cycles, no private names across modules.

Every ``import`` / ``from ... import`` of the package's own modules is read
with :mod:`ast` (function-level imports included: a deferred import is still
a dependency), relative imports resolved.  Three rules:

* **layers**: ``fmbrdf_mi.fit``'s sub-packages are ordered (the list in
  ``fmbrdf_mi/fit/__init__.py``); a module imports only from its own layer or
  the ones before it.  The package's top level is ordered too: the model's
  maths, then the Mitsuba plugins, then scenes and the sensor (the camera model), then the
  fits, then the tools built on them, then the command line.
* **no cycles** among modules (a cycle is a layer in disguise);
* **no private names** (``_x``, not dunder) imported from another module.

The checker itself is tested on made-up graphs, so a rule that stopped
finding anything would fail here too.
"""
from __future__ import annotations

import ast
import os
import re

import pytest

ROOT = os.path.join(os.path.dirname(__file__), "..", "fmbrdf_mi")

#: fmbrdf_mi.fit's layers, bottom first (fmbrdf_mi/fit/__init__.py).
FIT_LAYERS = ["errors", "inputs", "evaluate", "objectives", "problem", "solve", "uncertainty", "result",
              "api", "outputs", "cli"]

#: The package's top level, bottom first; a module or sub-package not listed fails the test.
TOP_LAYERS = [
    {"model", "params", "geometry", "stokes_io", "_llvm", "_paths", "interrupt"},
    {"bsdf", "oren_nayar_bsdf"},
    {"scene", "sensor", "previews"},
    {"fit"},
    {"brdf_fit", "mesogeometry", "dataset", "render", "synthetic"},
    {"cli", "__main__"},
]


def module_name(path):
    rel = os.path.relpath(path, os.path.join(ROOT, ".."))
    parts = rel[:-3].split(os.sep)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def package_sources():
    out = {}
    for dp, _, files in os.walk(ROOT):
        for f in files:
            if f.endswith(".py"):
                p = os.path.join(dp, f)
                with open(p) as fh:
                    out[module_name(p)] = (fh.read(), f == "__init__.py")
    return out


def imports(sources):
    """[(importer, imported module, imported name or None, line)] of the package's own modules."""
    mods = set(sources)
    out = []
    for mod, (text, is_pkg) in sources.items():
        pkg = mod if is_pkg else mod.rpartition(".")[0]
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.Import):
                for a in node.names:
                    if a.name.split(".")[0] == "fmbrdf_mi":
                        out.append((mod, a.name, None, node.lineno))
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = pkg.split(".")[:len(pkg.split(".")) - node.level + 1]
                    target = ".".join(base + ([node.module] if node.module else []))
                else:
                    target = node.module or ""
                if target.split(".")[0] != "fmbrdf_mi":
                    continue
                for a in node.names:
                    sub = f"{target}.{a.name}"
                    if sub in mods:           # `from pkg import module`
                        out.append((mod, sub, None, node.lineno))
                    else:
                        out.append((mod, target, a.name, node.lineno))
    return out


def cycles(edges):
    """Strongly connected components with more than one module (Tarjan)."""
    graph = {}
    for a, b in edges:
        graph.setdefault(a, set()).add(b)
        graph.setdefault(b, set())
    index, low, stack, on, out = {}, {}, [], set(), []
    counter = [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def top_rank(mod):
    parts = mod.split(".")
    if len(parts) == 1:           # fmbrdf_mi itself: registration and versions, importable from anywhere
        return None
    for r, names in enumerate(TOP_LAYERS):
        if parts[1] in names:
            return r
    raise AssertionError(f"{mod}: not in tests/test_layers.py's TOP_LAYERS: place it in a layer")


def fit_rank(mod):
    parts = mod.split(".")
    if parts[:2] != ["fmbrdf_mi", "fit"] or len(parts) == 2:
        return None
    if parts[2] not in FIT_LAYERS:
        raise AssertionError(f"{mod}: fmbrdf_mi.fit.{parts[2]} is not one of the layers {FIT_LAYERS}")
    return FIT_LAYERS.index(parts[2])


def violations(sources):
    """Human-readable lines, one per broken rule."""
    imps = imports(sources)
    mods = set(sources)
    bad = []
    edges = set()
    for a, target, name, line in imps:
        b = target if target in mods else target.rpartition(".")[0] if target.rpartition(".")[0] in mods else target
        if b == a:
            continue
        edges.add((a, b))
        ra, rb = top_rank(a), top_rank(b)
        if ra is not None and rb is not None and rb > ra:
            bad.append(f"{a}:{line} imports {b}: a higher layer of the package")
        fa, fb = fit_rank(a), fit_rank(b)
        if fa is not None and fb is not None and fb > fa:
            bad.append(f"{a}:{line} imports {b}: layer {FIT_LAYERS[fb]} is above {FIT_LAYERS[fa]}")
        if a.startswith("fmbrdf_mi.fit.") and b == "fmbrdf_mi.fit":
            bad.append(f"{a}:{line} imports the fmbrdf_mi.fit package (its API facade) from inside it")
        if name is not None and name.startswith("_") and not name.startswith("__"):
            bad.append(f"{a}:{line} imports the private name {name} from {target}")
    for comp in cycles(edges):
        bad.append("import cycle: " + " -> ".join(comp))
    return bad


def test_package_layers_cycles_private_names():
    bad = violations(package_sources())
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("extra, expect", [
    ({"fmbrdf_mi.sensor.x": "from fmbrdf_mi.fit.errors import InputError\n"}, "a higher layer of the package"),
    ({"fmbrdf_mi.fit.inputs.x": "from ..solve import optimise\n"}, "layer solve is above inputs"),
    ({"fmbrdf_mi.model.x": "from ..fit.errors import InputError\n"}, "a higher layer of the package"),
    ({"fmbrdf_mi.fit.api.x": "from .y import _helper\n", "fmbrdf_mi.fit.api.y": "def _helper(): pass\n"},
     "private name _helper"),
    ({"fmbrdf_mi.fit.api.x": "def f():\n    from . import y\n", "fmbrdf_mi.fit.api.y": "from . import x\n"},
     "import cycle: fmbrdf_mi.fit.api.x -> fmbrdf_mi.fit.api.y"),
    ({"fmbrdf_mi.fit.api.x": "from fmbrdf_mi.fit import fit\n"}, "API facade"),
])
def test_checker_finds_each_kind_of_violation(extra, expect):
    """Each rule, broken on purpose in a made-up module added to the real package, is reported."""
    sources = package_sources()
    sources.update({k: (v, False) for k, v in extra.items()})
    bad = violations(sources)
    assert any(expect in line for line in bad), bad


def test_fit_layers_match_the_package():
    """Every sub-package of fmbrdf_mi.fit is a listed layer, and the package docstring's list of layers names them
    in order."""
    fit_dir = os.path.join(ROOT, "fit")
    found = {f[:-3] if f.endswith(".py") else f for f in os.listdir(fit_dir)
             if (f.endswith(".py") and f != "__init__.py") or os.path.isfile(os.path.join(fit_dir, f, "__init__.py"))}
    assert found == set(FIT_LAYERS)
    import fmbrdf_mi.fit as F

    listed = re.findall(r"``(\w+)``", F.__doc__.split("Layers", 1)[1])
    assert listed == FIT_LAYERS
