"""``fmbrdf-mi fit-brdf TABLE.csv|TABLE.npz``: a Mueller-matrix BRDF table, fitted per wavelength (``--share``:
some parameters common to every wavelength) by FMBRDF and the polarised baselines (:mod:`.mueller_fit`), with the conventions of the MERL fits (DIR/params.json written
last and atomically, the summary to stdout, exit status 3 when a fit did not converge).

Outputs in DIR: params.json (per wavelength and model: parameters, standard errors and intervals, the noise
model and its sigmas, errors, convergence; the held-out errors with ``--holdout``), comparison.tsv (one row
per wavelength and model, also printed), and per wavelength mueller_panel_<wl>.png and residuals_<wl>.png
(:mod:`.mueller_plots`).  Every input is read, and every option checked, before anything is written.
"""
from __future__ import annotations

import json
import math
import os
import sys
import time

#: The comparison table's columns.
COLUMNS = ("wavelength_um", "model", "set", "rows", "log10_rmse_f_r11", "rmse_dolp", "rmse_elements", "rmse_m21_sp",
           "m21_sign_agrees", "sigma_f", "sigma_m", "converged", "params")


def add_mueller_arguments(p):
    """The options of Mueller tables (.csv, .npz FILEs), in their own group of ``fit-brdf``."""
    g = p.add_argument_group("Mueller-matrix BRDF tables (FILE .csv/.tsv/.txt/.dat: SCATMECH/NIST layout or the "
                             "plain table; .npz: the plain table; see docs/howto/fit-mueller.md)")
    g.add_argument("--models", default="fmbrdf,pplastic,lambert", metavar="LIST",
                   help="comma-separated models to fit and compare: fmbrdf, pplastic, lambert, lambert_ts, "
                        "oren_nayar_ts (the image fits' Lambertian or Oren-Nayar + Torrance-Sparrow); default "
                        "fmbrdf,pplastic,lambert")
    g.add_argument("--share", metavar="LIST",
                   help="comma-separated parameters common to every wavelength (e.g. alpha,beta,kappa), fitted "
                        "jointly over the wavelengths by each model that has them; the others per wavelength "
                        "(default: every parameter per wavelength)")
    g.add_argument("--holdout", metavar="TABLE", help="a second table evaluated with the fitted parameters")
    g.add_argument("--residual", choices=("log", "relative"), default="log",
                   help="residual of f_r11: ln(f_fit / f) (default) or f_fit / f - 1")
    g.add_argument("--noise", choices=("residuals", "vanishing"), default="residuals",
                   help="how sigma_m is estimated when not given: from the fit residuals (default) or from the "
                        "elements that vanish in the plane of incidence")
    g.add_argument("--noise-f", type=float, metavar="S", help="given relative noise sigma_f of f_r11")
    g.add_argument("--noise-m", type=float, metavar="S", help="given noise sigma_m of the normalised elements")
    g.add_argument("--physical-tolerance", type=float, default=None, metavar="T",
                   help="slack of the physical bounds on normalised Mueller elements (default 0.05)")


#: The Mueller options and their defaults (refused on MERL files when changed).
_MUELLER_DEFAULTS = {"models": "fmbrdf,pplastic,lambert", "share": None, "holdout": None, "residual": "log",
                     "noise": "residuals",
                     "noise_f": None, "noise_m": None, "physical_tolerance": None}


def _flag(name):
    return "--" + name.replace("_", "-")


def refuse_mueller_options(args):
    """MERL files: the options of Mueller tables would be ignored, so they are refused (one line)."""
    given = [_flag(k) for k, v in _MUELLER_DEFAULTS.items() if getattr(args, k, v) != v]
    if given:
        raise ValueError(f"{', '.join(given)}: options of Mueller-matrix tables (.csv, .npz); the MERL files "
                         f"given ({args.file[0]}{', ...' if len(args.file) > 1 else ''}) do not use them")


def _refuse_merl_options(args):
    given = [f for f, on in (("--jobs", args.jobs != 1), ("--skip-existing", args.skip_existing),
                             ("--full-grid", getattr(args, "full_grid", False))) if on]
    if given:
        raise ValueError(f"{', '.join(given)}: options of MERL batches and start grids; a Mueller table "
                         f"({args.file[0]}) does not use them")


def _options(args):
    from .mueller_fit import MuellerFitOptions
    from .mueller_values import MODELS

    models = tuple(m.strip() for m in args.models.split(",") if m.strip())
    o = MuellerFitOptions(models=models, residual=args.residual, noise=args.noise, noise_f=args.noise_f,
                          noise_m=args.noise_m, starts=args.starts, max_evals=args.max_evals,
                          max_rows=args.samples, seed=args.seed,
                          share=tuple(n.strip() for n in (args.share or "").split(",") if n.strip()))
    try:
        o.check()
    except ValueError as e:
        raise ValueError(f"--{str(e).split(':')[0].replace('_', '-')}:{str(e).split(':', 1)[1]}") from None
    if not models:
        raise ValueError(f"--models: give at least one of {', '.join(MODELS)}")
    return o


def _tolerance(args):
    from .mueller import PHYSICAL_TOLERANCE

    t = args.physical_tolerance
    if t is None:
        return PHYSICAL_TOLERANCE
    if not (t >= 0 and math.isfinite(t)):
        raise ValueError(f"--physical-tolerance: must be a number >= 0, got {t}")
    return t


def _result_dict(r):
    return {"params": r.params, "se": r.se, "interval": r.interval, "interval_kind": r.interval_kind,
            "noise": r.noise, "rmse": r.rmse,
            "chi2": r.chi2, "dof": r.dof, "n_rows": r.n_rows, "at_bound": r.at_bound, "converged": r.converged,
            "stop_reason": r.stop_reason, "history": r.history, "seconds": r.seconds, "builds": r.builds,
            "shared": r.shared}


def _fmt(v, spec=".4g"):
    return "" if v is None else format(v, spec) if isinstance(v, float) else str(v)


def run_fit_mueller(args):
    from . import mueller as T
    from . import mueller_fit as F
    from .mueller_plots import mueller_panel, residual_maps

    if len(args.file) != 1 or os.path.isdir(args.file[0]):
        raise ValueError("fit-brdf: a Mueller table is fitted alone: give one .csv or .npz FILE")
    path = args.file[0]
    _refuse_merl_options(args)
    opts = _options(args)
    tol = _tolerance(args)
    out = args.out or os.path.splitext(path)[0] + "_fit"
    from fmbrdf_mi._paths import check_output_dir

    check_output_dir(out)
    if os.path.exists(os.path.join(out, "params.json")) and not args.force:
        raise FileExistsError(f"{os.path.join(out, 'params.json')} exists; pass --force to overwrite it")
    table = T.read_table(path, tol)
    holdout = T.read_table(args.holdout, tol) if args.holdout else None
    if holdout is not None:
        missing = [w for w in table.wavelengths() if not any(
            (math.isnan(w) and math.isnan(h)) or w == h for h in holdout.wavelengths())]
        if missing:
            raise ValueError(f"{args.holdout}: no rows at wavelength {missing[0]:g} µm of {path}")
    say = (lambda msg: None) if args.quiet else (lambda msg: print(msg, file=sys.stderr, flush=True))
    t0 = time.time()
    say(f"[fit-brdf] {path}: Mueller table ({table.kind}), {len(table)} rows, "
        f"{len(table.wavelengths())} wavelength(s); models {', '.join(opts.models)}")
    results = F.fit_table(table, opts, progress=say)
    rows, report_wl = [], []
    os.makedirs(out, exist_ok=True)
    for wl, per_model in results.items():
        sub = table.at_wavelength(wl)
        tag = "none" if math.isnan(wl) else f"{wl:g}"
        fitted = {m: F.predict(m, r.params, sub.w_in, sub.w_out) for m, r in per_model.items()}
        entry = {"wavelength_um": None if math.isnan(wl) else wl, "rows": len(sub),
                 "models": {m: _result_dict(r) for m, r in per_model.items()}, "fitted_errors": {}}
        sets = [("fitted", sub, fitted)]
        if holdout is not None:
            hsub = holdout.at_wavelength(wl)
            sets.append(("holdout", hsub, {m: F.predict(m, r.params, hsub.w_in, hsub.w_out)
                                           for m, r in per_model.items()}))
            entry["holdout_errors"] = {}
        for name, data, pred in sets:
            for m, r in per_model.items():
                e = F.prediction_errors(pred[m], data)
                entry["fitted_errors" if name == "fitted" else "holdout_errors"][m] = e
                rows.append({"wavelength_um": tag, "model": m, "set": name, "rows": e["n_rows"],
                             "log10_rmse_f_r11": _fmt(e["log10_f_r11"]), "rmse_dolp": _fmt(e["dolp"]),
                             "rmse_elements": _fmt(e["elements"]), "rmse_m21_sp": _fmt(e["m21_sp"]),
                             "m21_sign_agrees": _fmt(e["m21_sign_agrees"], ".3f"),
                             "sigma_f": _fmt(r.noise["sigma_f"]), "sigma_m": _fmt(r.noise["sigma_m"]),
                             "converged": "yes" if r.converged else "no",
                             "params": " ".join(f"{k}={v:.4g}±{r.se[k]:.2g}" for k, v in r.params.items())})
        mueller_panel(sub, fitted, os.path.join(out, f"mueller_panel_{tag}.png"),
                      title=f"{os.path.basename(path)}, {tag} µm")
        residual_maps(sub, fitted, os.path.join(out, f"residuals_{tag}.png"),
                      title=f"{os.path.basename(path)}, {tag} µm: fitted rows")
        van, n_van = F.vanishing_noise(sub)
        entry["noise_from_vanishing_elements"] = {"sigma_m": van, "in_plane_rows": n_van}
        report_wl.append(entry)
    text = "\t".join(COLUMNS) + "\n" + "".join("\t".join(str(r[c]) for c in COLUMNS) + "\n" for r in rows)
    tmp = os.path.join(out, "comparison.tsv.part")
    with open(tmp, "w") as f:
        f.write(text)
    os.replace(tmp, os.path.join(out, "comparison.tsv"))
    any_result = next(iter(next(iter(results.values())).values()))
    report = {"file": os.path.abspath(path), "kind": f"mueller ({table.kind})", "holdout": args.holdout and
              os.path.abspath(args.holdout), "noise_model": any_result.noise["model"].split(" (")[0],
              "interval_level": opts.level, "frames": "package (Mitsuba stokes_basis(-w_in) -> stokes_basis(w_out)); "
              "m21_sp in SCATMECH's s/p bases", "wavelengths": report_wl,
              "options": {k: v for k, v in opts.__dict__.items()}, "timings": {"command": time.time() - t0}}
    tmp = os.path.join(out, "params.json.part")
    with open(tmp, "w") as f:
        json.dump(report, f, indent=2, default=float)
    os.replace(tmp, os.path.join(out, "params.json"))
    sys.stdout.write(text)
    not_conv = [f"{m} at {w:g} µm" for w, d in results.items() for m, r in d.items() if not r.converged]
    if not_conv:
        from fmbrdf_mi.fit.outputs.summary import EXIT_NOT_CONVERGED

        print(f"fmbrdf-mi fit-brdf: NOT converged: {', '.join(not_conv)}; raise --max-evals (exit status "
              f"{EXIT_NOT_CONVERGED})", file=sys.stderr)
        return EXIT_NOT_CONVERGED
    return 0
