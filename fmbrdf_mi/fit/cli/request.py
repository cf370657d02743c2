"""The one request of a ``fmbrdf-mi fit`` run: an entry point's keyword arguments from the parsed options."""
from __future__ import annotations

import inspect

#: Options of the command whose entry-point keyword has another name.
ALIASES = {"fixed": "fix"}


def request(entry, args, **converted):
    """``entry``'s keyword arguments, each from the parsed option of the same name (:data:`ALIASES`), then
    ``converted`` (the values the command turns into another form: one input or several, a parsed vector,
    ``--max-pixels 0`` for all).  ``entry`` is a function (its named parameters) or a tuple of names (a
    function that takes them as ``**kwargs``).  ``--from`` builds the same request from a fit.json
    (:mod:`fmbrdf_mi.fit.outputs.record`)."""
    names = entry if isinstance(entry, tuple) else tuple(inspect.signature(entry).parameters)
    kw = {n: getattr(args, ALIASES.get(n, n)) for n in names if hasattr(args, ALIASES.get(n, n))}
    kw.update(converted)
    return kw
