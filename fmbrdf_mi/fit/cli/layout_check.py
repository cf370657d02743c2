"""After a raw-mosaic likelihood fit that does not explain its data: would the mirrored polariser layout (45 and
135 degrees swapped: S2 negated)?  From :data:`POOR_CHI2` per sample, the fit reruns swapped in a temporary
directory; :data:`MUCH_BETTER` times lower, one line names ``--layout``."""
from __future__ import annotations

import os
import sys
import tempfile

from fmbrdf_mi.fit.inputs.parse import layout_text, parse_layout
from fmbrdf_mi.interrupt import interrupted

#: chi^2 per raw sample from which a misfit is checked (the right layout gives about 1, a mirrored one more).
POOR_CHI2 = 1.5

#: How many times lower the mirrored layout's chi^2 must be to be named.
MUCH_BETTER = 2.0


def mirrored(layout):
    """The 2x2 layout with 45 and 135 degrees swapped (the polarisers as a mirror image sees them)."""
    return tuple(tuple({45: 135, 135: 45}.get(int(a), int(a)) for a in row) for row in layout)


def chi2_per_sample(m):
    """chi^2 per raw sample of a likelihood fit's fit.json ``models`` entry ``m``, else None."""
    t = m.get("loss_terms") or {}
    if m.get("objective") != "likelihood" or not t.get("samples") or "chi2" not in t:
        return None
    return float(t["chi2"]) / float(t["samples"])


def needs_check(report, model):
    """Whether ``report`` (a single-image fit) is a raw-mosaic likelihood fit with a poor chi^2."""
    m = (report.get("models") or {}).get(model)
    settings = ((report.get("reproduce") or {}).get("images") or [{}])[0].get("settings") or {}
    if m is None or settings.get("demosaic") is None or not settings.get("layout"):
        return False             # not a raw mosaic
    c = chi2_per_sample(m)
    return c is not None and bool(not m.get("converged") or (m.get("uncertainty") or {}).get("misfit")) \
        and c >= POOR_CHI2


def mirrored_layout_hint(report, kw, fit_files, progress=True):
    """A line naming ``--layout`` if the mirrored layout explains the data far better, else None (``kw``: the fit's)."""
    model = kw.get("model", "fmbrdf")
    if not needs_check(report, model):
        return None
    used = report["reproduce"]["images"][0]["settings"]["layout"]
    other = mirrored(used)
    if other == parse_layout(used):
        return None              # no 45 / 135 in the layout
    c0 = chi2_per_sample(report["models"][model])
    took = report["models"][model].get("timings", {}).get("total", 0.0)
    if progress:
        print(f"fmbrdf-mi fit: chi^2 per sample {c0:.3g}: checking the mirrored polariser layout "
              f"{layout_text(other)} (45 and 135 deg swapped), a second fit (~{took:.0f} s, as the first) ...",
              file=sys.stderr, flush=True)
    with tempfile.TemporaryDirectory(prefix="fmbrdf-mi-layout-") as tmp:
        try:
            other_report = fit_files(**dict(kw, layout=layout_text(other), out=os.path.join(tmp, "fit"), force=False,
                                            progress=False, baselines=False, relight=None, relight_light=None,
                                            relight_irradiance=None))
        except Exception as e:   # an optional check: its failure leaves the fit as it is (Ctrl-C stops)
            if interrupted(e):
                raise
            return None
    c1 = chi2_per_sample((other_report.get("models") or {}).get(model) or {})
    if c1 is None or not c1 * MUCH_BETTER <= c0:
        return None
    return (f"the mirrored polariser layout {layout_text(other)} (45 and 135 deg swapped) explains the data much "
            f"better (chi^2 per sample {c1:.3g} against {c0:.3g} with {layout_text(used)}): the mosaic's 45 and "
            f"135 deg pixels look swapped (a mirrored optical path, a camera upside down, another sensor's "
            f"convention); rerun with --layout {layout_text(other)}")
