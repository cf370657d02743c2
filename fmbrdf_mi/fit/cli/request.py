"""The one request of a ``fmbrdf-mi fit`` run: an entry point's keyword arguments from the parsed options."""
from __future__ import annotations

from fmbrdf_mi.fit.api.options import record_keys
from fmbrdf_mi.fit.inputs.parse import parse_vector


def request(record, args, **converted):
    """The options of ``record`` (``single``, ``colour`` or ``joint``:
    :func:`~fmbrdf_mi.fit.api.options.record_keys`) as parsed, ``--max-pixels 0`` as None, ``--light`` and
    ``--relight-light`` parsed, then ``converted`` (values the command converts itself)."""
    values = vars(args)
    kw = {k: values[k] for k in record_keys(record)}
    kw["max_pixels"] = kw["max_pixels"] or None
    if "light" in kw:
        kw["light"] = parse_vector((kw["light"] or [None])[0], "--light")
    if "relight_light" in kw:
        kw["relight_light"] = parse_vector(kw["relight_light"], "--relight-light")
    return {**kw, **converted}
