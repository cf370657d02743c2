"""The text summaries a fit prints to stdout, and the exit status they imply."""
from __future__ import annotations

import sys

import numpy as np

from fmbrdf_mi.fit.problem.free_power import power_text
from fmbrdf_mi.fit.uncertainty import WEAK_REL, misfit_text, noise_flagged

#: Exit status of a fit that stopped before it converged (time limit, iteration limit).
EXIT_NOT_CONVERGED = 3


def kind_text(model_entry, name):
    """`` (profile likelihood ...)`` after an interval that is not the Fisher one."""
    unc = model_entry.get("uncertainty") or {}
    kind = (unc.get("interval_kind") or {}).get(name, "fisher")
    if kind == "optima":
        return " (widened over another optimum)"
    return "" if kind == "fisher" else f" ({kind.replace('profile', 'profile likelihood')})"


def param_line(name, value, std, ci, width=6, tail=""):
    """``  name  value  +- se  95% [lo, hi]``: the interval where there is a standard error."""
    line = f"  {name:<{width}} {value:10.5g}"
    if std is not None:
        line += f"  +- {std:.3g}  95% [{ci[0]:.5g}, {ci[1]:.5g}]{tail}"
    return line


def print_params(m, std, ci, width=6):
    """:func:`param_line` s of a ``models`` entry ``m`` (per channel), fixed ones marked, with the error vs metadata."""
    rel, fixed = m.get("relative_error") or {}, m.get("fixed") or {}
    for k, v in m["params"].items():
        if isinstance(v, dict):
            lines = [(param_line(f"{k}[{c}]", x, std[k][c] if k in std else None, ci.get(k, {}).get(c), width),
                      rel[k].get(c) if isinstance(rel.get(k), dict) else None) for c, x in v.items()]
        else:
            lines = [(param_line(k, v, None if k in fixed else std.get(k), ci.get(k), width, kind_text(m, k))
                      + ("  (fixed)" if k in fixed else ""), rel.get(k))]
        for line, r in lines:
            print(line + ("" if r is None else f"  (vs metadata {r:+.2%})"))


def uncertainty_lines(unc):
    """Print the ``uncertainty:`` line of a model (its method, chi^2/dof), if it has one, and its warnings."""
    if unc.get("method"):
        print(f"  uncertainty: {unc['method']}" + (f"; chi2/dof {unc['chi2_per_dof']:.3f}" if "chi2_per_dof" in unc
                                                     else ""))
    if noise_flagged(unc):
        print("  warning: " + misfit_text(unc))
    if (unc.get("other_optima") or {}).get("warning"):
        print("  warning: " + unc["other_optima"]["warning"])


def albedo_text(a):
    """One line on a per-pixel albedo fit's maps (fit.json's ``albedo`` block), plus one per colour channel."""
    per = "".join(f"\n    {c}: median k_s {p['k_s_median']:.4g}, k_b {p['k_b_median']:.4g}; relative standard error "
                  f"<= 0.5 for k_s in {p['k_s_determined_fraction']:.0%}, for k_b in "
                  f"{p['k_b_determined_fraction']:.0%}; split identified in {p['identified_fraction']:.0%}"
                  for c, p in (a.get("per_channel") or {}).items())
    return (f"albedo maps: {a['pixels']} pixels, median k_s {a['k_s_median']:.4g}, k_b {a['k_b_median']:.4g}; "
            f"relative standard error <= 0.5 for k_s in {a['k_s_determined_fraction']:.0%}, for k_b in "
            f"{a['k_b_determined_fraction']:.0%} of them; surface / body split identified in "
            f"{a['identified_fraction']:.0%}" + per + (f"\n  warning: {a['warning']}" if a.get("warning") else ""))


def convergence_status(name, m):
    """0, or :data:`EXIT_NOT_CONVERGED` and a line on stderr when the fit ``name`` (entry ``m``) did not converge."""
    if m["converged"]:
        return 0
    print(f"fmbrdf-mi fit: {name}: stopped before convergence ({m['stop_reason']}); the estimates are the last "
          f"accepted ones and have no standard errors (exit status {EXIT_NOT_CONVERGED})", file=sys.stderr)
    return EXIT_NOT_CONVERGED


def wrote(report):
    print(f"wrote {', '.join(report['outputs'])} ({report['wall_s']:.1f} s)")


def print_normals(report):
    """The stdout summary of a normal refinement; returns the exit status."""
    rn = report["refine_normals"]
    for name, mdl in report["models"].items():
        unc = mdl.get("uncertainty") or {}
        print(f"{name}: normal refinement ({'converged' if rn['converged'] else 'NOT converged'}: {rn['stop_reason']})"
              f", {rn['pixels']} pixels, start {rn['start']}, smoothness {rn['smooth']:g}"
              + (f" (material at {rn['material_stage']['lam']:g})" if rn.get("material_stage") else ""))
        for k, v in mdl["params"].items():
            print(param_line(k, v, unc.get("std_errors", {}).get(k), unc.get("ci95", {}).get(k)))
        if mdl.get("uncertainty_uncalibrated"):
            print("  no standard errors: " + mdl["uncertainty_uncalibrated"].get("warning", "not calibrated")
                  + " (fit.json: uncertainty_uncalibrated; docs: how-to 'Fit several images of one object', "
                  "Normal refinement)")
        uncertainty_lines(unc)
    ch, ae = rn["angle_change"], rn.get("angular_error")
    print(f"  normals moved from the start by {ch['mean']:.2f} deg mean, {ch['median']:.2f} deg median")
    if ae:
        b, a = ae["before"], ae["after"]
        print(f"  angle to the ground truth: before {b['mean']:.2f} / {b['median']:.2f} deg, after "
              f"{a['mean']:.2f} / {a['median']:.2f} deg (mean / median, {a['pixels']} pixels)")
    wrote(report)
    return 0 if rn["converged"] else EXIT_NOT_CONVERGED


def print_summary(report):
    """The stdout summary of any fit's report; returns the exit status (0 or :data:`EXIT_NOT_CONVERGED`)."""
    if report.get("refine_normals"):
        return print_normals(report)
    colour, status = report.get("sensor") == "colour", 0
    for name, m in report["models"].items():
        unc = m.get("uncertainty") or {}
        state = f"({'converged' if m['converged'] else 'NOT converged'}: {m['stop_reason']})"
        if colour:   # the standard errors beside the uncertainty block
            unc = dict(unc, std_errors=m["std_errors"] or {}, ci95=m["ci95"] or {})
            print(f"{name} (colour, {'albedo maps per pixel and channel' if m.get('albedo') else 'per-channel albedos'}"
                  f"): chi2/dof {m['chi2_per_dof']:.4f} over {m['n_samples']} raw samples of {m['n_pixels']} periods  "
                  + state)
        else:
            print(f"{name}: {m['objective']} {m['loss']:.6e}  {state}")
        if m.get("noise"):
            print(f"  camera noise {m['noise'].get('description', m['noise'])}")
        ex = m.get("pixels_excluded") or {}
        if ex.get("saturated") or ex.get("dark"):
            print(f"  excluded {ex['saturated']} saturated and {ex['dark']} dark super-pixels of "
                  f"{ex['candidates']}; fitted {ex['used']}")
        print_params(m, unc.get("std_errors", {}), unc.get("ci95", {}), 8 if colour else 6)
        uncertainty_lines(unc)
        if unc.get("correlation") and not colour:   # (a colour fit's albedos are correlated)
            c = unc["correlation"]
            big = [(c["names"][i], c["names"][j], c["matrix"][i][j]) for i in range(len(c["names"]))
                   for j in range(i + 1, len(c["names"])) if abs(c["matrix"][i][j]) > 0.9]
            if big:
                print("  strongly correlated: " + ", ".join(f"{a}/{b} {x:+.2f}" for a, b, x in big))
        if m.get("weakly_identified"):
            print(f"  weakly identified (standard error > {WEAK_REL:.0%} of the value, or at a bound): "
                  f"{', '.join(m['weakly_identified'])}")
        if m.get("albedo"):
            print("  " + albedo_text(m["albedo"]))
        for img, c2 in (m.get("chi2_per_sample") or {}).items():
            print(f"  {img}: chi2 per raw sample {c2:.3f}")
        if m.get("materials"):
            b = m["materials"]
            print(f"  {b['count']} material(s), fitted pixels "
                  + ", ".join(f"{k}: {n}" for k, n in enumerate(b["pixels"]))
                  + ("; parameter[m] is material m's" if b["count"] > 1 else ""))
        status = max(status, convergence_status(name, m))
    for name, m in report["models"].items():
        for im in m.get("images") or []:
            line = (f"  {im['name']}: {im['n_pixels']} px, light {np.round(im['light_dir'], 3).tolist()}"
                    + ("" if im.get("chi2_per_dof") is None else f", chi2/dof {im['chi2_per_dof']:.3f}")
                    + f", intensity RMSE/mean {im['intensity_rel_rmse']:.4f}"
                    + ("" if im.get("power") is None else ", " + power_text(im)))
            print(f"{name}{line}" if len(report["models"]) > 1 else line)
    for img, errs in (report.get("relight") or {}).items():   # per image and model
        for name, e in errs.items():
            print(f"relighting {img} ({name}): " + (
                f"raw-sample RMSE / mean = {e['rel_rmse']:.4f} (R {e['rel_rmse_R']:.4f}, G {e['rel_rmse_G']:.4f}, B "
                f"{e['rel_rmse_B']:.4f})" if colour else f"RMSE / mean intensity = {e['rel_rmse']:.4f}"))
    wrote(report)
    return status
