"""The ``fit-brdf`` subcommand: ``fmbrdf-mi fit-brdf FILE.binary [-o DIR]``.

Follows the subcommand protocol of :mod:`fmbrdf_mi.cli` (user errors, a
ValueError or OSError, become one line and exit status 1).
"""
from __future__ import annotations

import argparse
import json
import os
import sys

HELP = "fit FMBRDF (shared eta, alpha, beta, kappa; per-channel k_s, k_b) to a MERL BRDF binary file"
EPILOG = """\
examples:
  fmbrdf-mi fit-brdf brdfs/blue-acrylic.binary
  fmbrdf-mi fit-brdf brdfs/blue-acrylic.binary -o fits/blue-acrylic --samples 100000 --starts 3

Writes DIR/params.json (parameters, log10 RMSE on the fitted samples and on
every usable bin, per channel, the samples used and the timings) and
DIR/slices.png (measured against fitted BRDF slices).  The error is the RMS of
log10(f_fit) - log10(f_measured), as in the FMBRDF authors' MERL fits."""

OUTPUTS = ("params.json", "slices.png")


def add_fit_brdf_arguments(p):
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.epilog = EPILOG
    p.add_argument("file", metavar="FILE", help="MERL BRDF binary (.binary)")
    p.add_argument("-o", "--out", metavar="DIR", help="output directory (default: FILE without extension + _fit)")
    p.add_argument("--samples", type=int, default=50_000, metavar="N",
                   help="bins fitted (a seeded random subset of the usable ones; default 50000)")
    p.add_argument("--starts", type=int, default=2, metavar="K", help="refine the K best start-grid points")
    p.add_argument("--max-evals", type=int, default=60, metavar="N", help="error evaluations per refinement")
    p.add_argument("--seed", type=int, default=0, help="seed of the sample subset")
    p.add_argument("--force", action="store_true", help="overwrite existing outputs")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress output, only the summary")


def run_fit_brdf(args):
    from .fitting import BRDFFitOptions, fit_brdf, model_brdf
    from .merl import read_merl
    from .plots import slice_plot

    for name, v, lo in (("--samples", args.samples, 100), ("--starts", args.starts, 1),
                        ("--max-evals", args.max_evals, 1)):
        if v < lo:
            raise ValueError(f"{name}: must be an integer >= {lo}, got {v}")
    from fmbrdf_mi._paths import check_output_dir
    from fmbrdf_mi.fit.outputs.summary import EXIT_NOT_CONVERGED

    out = args.out or os.path.splitext(args.file)[0] + "_fit"
    check_output_dir(out)   # before the fit (minutes), as the overwrite refusal below
    existing = [os.path.join(out, f) for f in OUTPUTS if os.path.exists(os.path.join(out, f))]
    if existing and not args.force:
        raise FileExistsError(f"{existing[0]} exists; pass --force to overwrite it")
    brdf = read_merl(args.file)
    progress = None if args.quiet else (lambda msg: print(msg, file=sys.stderr, flush=True))
    opts = BRDFFitOptions(max_samples=args.samples, starts=args.starts, max_evals=args.max_evals, seed=args.seed)
    res = fit_brdf(brdf, opts, progress=progress)
    os.makedirs(out, exist_ok=True)
    name = os.path.splitext(os.path.basename(args.file))[0]
    fitted = model_brdf(res.params)
    slice_plot(brdf, fitted, os.path.join(out, "slices.png"),
               title=f"{name}: FMBRDF fit, log10 RMSE {res.log_rmse_all:.3f} (all usable bins)")
    report = {"file": os.path.abspath(args.file), "params": res.params,
              "log10_rmse": {"fitted_samples": res.log_rmse, "all_usable_bins": res.log_rmse_all,
                             "per_channel_fitted_samples": dict(zip("rgb", res.log_rmse_channels))},
              "converged": res.converged, "stop_reason": res.stop_reason,
              "n_samples": res.n_samples, "n_usable_bins": res.n_usable, "at_bound": res.at_bound,
              "options": opts.__dict__, "history": res.history, "timings": res.timings}
    tmp = os.path.join(out, "params.json.part")
    with open(tmp, "w") as f:
        json.dump(report, f, indent=2, default=float)
    os.replace(tmp, os.path.join(out, "params.json"))
    p = res.params
    print(f"{name}: eta {p['eta']:.4g}, alpha {p['alpha']:.4g}, beta {p['beta']:.4g}, kappa {p['kappa']:.4g}, "
          f"k_s {', '.join(f'{v:.4g}' for v in p['k_s'])}, k_b {', '.join(f'{v:.4g}' for v in p['k_b'])}; "
          f"log10 RMSE {res.log_rmse_all:.4f} over {res.n_usable} bins"
          + (f"; at the bound: {', '.join(res.at_bound)}" if res.at_bound else "") + f" -> {out}")
    if not res.converged:
        print(f"fmbrdf-mi fit-brdf: NOT converged ({res.stop_reason}): the parameters are the last accepted ones; "
              f"raise --max-evals (exit status {EXIT_NOT_CONVERGED})", file=sys.stderr)
        return EXIT_NOT_CONVERGED
    return 0
