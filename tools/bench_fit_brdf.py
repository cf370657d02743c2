"""fit-brdf: times and results of two versions of the package, interleaved, on the two synthetic MERL files.

    taskset -c 1 env DRJIT_NUM_THREADS=1 python tools/bench_fit_brdf.py --old ../brdf-old --rounds 3

``--old DIR``: a checkout of the other version (``git worktree add --detach ../brdf-old COMMIT``).  The two
files are those of tools/check_fit_brdf.py (FMBRDF eta 1.55, alpha 0.23, beta 1.7, kappa 15; Lambert + GGX),
written once.  Each round runs ``python -m fmbrdf_mi fit-brdf FILE -q --force`` (the defaults) on both files
with ``DIR`` on ``PYTHONPATH`` and with this checkout, the two back to back on each file and alternating
which goes first, and reads each params.json.  Reported per file and version, the best round (the least
disturbed by other load), and the median and range of the ratios new / old of the back-to-back pairs: the
command's wall time (Python start and imports, reading the file, the fit, the plot), the fit's own time
(params.json timings.total) and the start grid's (timings.grid); then the fitted
parameters and log10 RMSE of both versions side by side with their largest relative difference.
``--batch N``: also one batch run of the new version over both files (``--jobs N``), its wall time (with fewer
cores than N in the affinity mask the workers share them).
Timings on the 2-core machine move 2-3x with load: compare the ratios of one run only.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, HERE)
sys.path.insert(0, ROOT)

from bench_rebuild import cpu_name  # noqa: E402

NAMES = ("fmbrdf", "lambert_ggx")


def make_files(work):
    import numpy as np

    from check_fit_brdf import TRUE, lambert_ggx
    from fmbrdf_mi.brdf_fit import merl
    from fmbrdf_mi.brdf_fit.fitting import model_brdf

    th, td, pd = merl.bin_angles()
    w_in, w_out = merl.half_diff_to_dirs(*np.meshgrid(th, td, pd, indexing="ij"))
    ok = (w_in[..., 2] > 0) & (w_out[..., 2] > 0)
    ggx = np.full(merl.DIMS + (3,), np.nan)
    ggx[ok] = lambert_ggx(w_in[ok], w_out[ok], np.array([0.4, 0.2, 0.1]), np.ones(3))
    paths = {}
    for name, table in (("fmbrdf", model_brdf(TRUE)), ("lambert_ggx", ggx)):
        paths[name] = merl.write_merl(os.path.join(work, name + ".binary"), table)
    return paths


def run(tree, args, env_extra=None):
    env = dict(os.environ, PYTHONPATH=tree)
    env.update(env_extra or {})
    t = time.time()
    p = subprocess.run([sys.executable, "-m", "fmbrdf_mi", "fit-brdf", *args], cwd=tree, env=env,
                       stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    if p.returncode not in (0, 3):
        raise SystemExit(f"fit-brdf failed ({tree}): {p.stderr.strip()}")
    return time.time() - t


def fit(tree, path, out, samples):
    wall = run(tree, [path, "-o", out, "-q", "--force", "--samples", str(samples)])
    with open(os.path.join(out, "params.json")) as f:
        rep = json.load(f)
    return {"wall": wall, "fit": rep["timings"]["total"], "grid": rep["timings"]["grid"], "params": rep["params"],
            "rmse": rep["log10_rmse"]["all_usable_bins"],
            "grid_points": rep["history"][0].get("points", 320)}


def flat(params):
    out = {}
    for k, v in params.items():
        if isinstance(v, list):
            out.update({f"{k}[{i}]": x for i, x in enumerate(v)})
        else:
            out[k] = v
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--old", required=True, help="checkout of the version to compare with")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--samples", type=int, default=50_000)
    p.add_argument("--batch", type=int, metavar="JOBS", help="also time a --jobs JOBS batch of both files (new)")
    p.add_argument("--json", help="write every round's numbers here")
    a = p.parse_args(argv)
    old = os.path.abspath(a.old)
    res = {t: {n: [] for n in NAMES} for t in ("old", "new")}
    with tempfile.TemporaryDirectory() as work:
        paths = make_files(work)
        k = 0
        for r in range(a.rounds):
            for name in NAMES:   # old and new back to back on each file, alternating which goes first
                order = [("old", old), ("new", ROOT)] if k % 2 == 0 else [("new", ROOT), ("old", old)]
                k += 1
                for tag, tree in order:
                    x = fit(tree, paths[name], os.path.join(work, f"{tag}_{name}"), a.samples)
                    res[tag][name].append(x)
                    print(f"round {r + 1} {tag} {name}: wall {x['wall']:.1f} s, fit {x['fit']:.1f} s, "
                          f"grid {x['grid']:.1f} s ({x['grid_points']} points)", flush=True)
        batch = None
        if a.batch:
            batch = run(ROOT, [paths[n] for n in NAMES] + ["-o", os.path.join(work, "batch"), "-q", "--force",
                                                            "--jobs", str(a.batch), "--samples", str(a.samples)])
            print(f"batch of both files, --jobs {a.batch} (new): wall {batch:.1f} s", flush=True)
    print(f"\n{time.strftime('%Y-%m-%d %H:%M %Z')}, {cpu_name()}, {os.cpu_count()} cores, "
          f"affinity {len(os.sched_getaffinity(0))} core(s), DRJIT_NUM_THREADS={os.environ.get('DRJIT_NUM_THREADS')}"
          f"; best of {a.rounds} interleaved rounds, --samples {a.samples}")
    print("| file | quantity | old, best (s) | new, best (s) | new / old, best | new / old per pair: median "
          "(range) |\n|---|---|---|---|---|---|")
    for name in NAMES:
        for q in ("wall", "fit", "grid"):
            bo = min(x[q] for x in res["old"][name])
            bn = min(x[q] for x in res["new"][name])
            pairs = sorted(n[q] / o[q] for o, n in zip(res["old"][name], res["new"][name]))
            label = {"wall": "command (wall)", "fit": "fit (timings.total)", "grid": "start grid"}[q]
            print(f"| {name} | {label} | {bo:.2f} | {bn:.2f} | {bn / bo:.3f} | {statistics.median(pairs):.3f} "
                  f"({pairs[0]:.3f}-{pairs[-1]:.3f}) |")
    print("\nfitted parameters (last round), old vs new:")
    worst = 0.0
    for name in NAMES:
        o, n = res["old"][name][-1], res["new"][name][-1]
        fo, fn = flat(o["params"]), flat(n["params"])
        for k in fo:
            d = abs(fo[k] - fn[k]) / max(abs(fo[k]), abs(fn[k]), 1e-300)
            worst = max(worst, d)
            print(f"  {name} {k}: {fo[k]:.10g} {fn[k]:.10g} (rel. diff {d:.1e})")
        d = abs(o["rmse"] - n["rmse"]) / max(o["rmse"], n["rmse"])
        worst = max(worst, d)
        print(f"  {name} log10 RMSE (all usable bins): {o['rmse']:.10g} {n['rmse']:.10g} (rel. diff {d:.1e})")
    print(f"largest relative difference old / new: {worst:.1e}")
    if a.json:
        with open(a.json, "w") as f:
            json.dump({"rounds": res, "batch_wall": batch, "cpu": cpu_name(), "date": time.strftime("%Y-%m-%d")},
                      f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
