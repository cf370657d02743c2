"""The one request of a ``fmbrdf-mi fit`` run: an entry point's keyword arguments from the parsed options."""
from __future__ import annotations

from fmbrdf_mi.fit.api.options import record_keys


def request(record, args, **converted):
    """The options of ``record`` (``single``, ``colour`` or ``joint``:
    :func:`~fmbrdf_mi.fit.api.options.record_keys`) as parsed, then ``converted`` (the values the command turns
    into another form: one input or several, a parsed vector, ``--max-pixels 0`` for all).  ``--from`` builds
    the same request from a fit.json (:mod:`fmbrdf_mi.fit.outputs.record`)."""
    values = vars(args)
    return {**{k: values[k] for k in record_keys(record)}, **converted}
