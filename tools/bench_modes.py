"""Interval coverage in every fitting mode: one command over the per-mode benches, one table.

    python tools/bench_modes.py --json modes.json [--modes single,joint3,joint6,free_power,colour,normals]
                                [--seeds 64] [--mode-seeds colour=32,normals=16] [--size 40] [--material medium]
                                [--periods 16] [--normal-res 24]
    python tools/bench_modes.py --table modes.json         # the Markdown table of a saved run

Each mode is one of the per-mode benches, whose per-fit functions do the work
(same data, camera and fits as their own tables):

* ``single``: :func:`bench_fit_noise.noise_fit`: one image of the sphere
  (SIZE² super-pixels, light (-0.5, 0.5, 1)), likelihood fit; noise seed s;
* ``joint1``, ``joint3``, ``joint6``: :func:`bench_fit_lights.lights_fits`: K
  images under the ring of six lights 35 degrees from the view (K = 1: light 0,
  within 0.3 degrees of ``single``'s), joint likelihood fit; image j of seed s
  has noise seed 1000 s + j, so the K = 1 data are part of the K = 3 and 6 data;
* ``free_power``: the same K = 3 with true powers 1, 0.6, 1.7 told as 1, 1, 1 and
  estimated (``power_start="ratio"``); the powers are rows of their own;
* ``colour``: :func:`bench_fit_colour.colour_fit` (its own material; PERIODS² colour periods);
* ``normals``: :func:`bench_normal_refine.normal_fit` (the ``medium``
  material on the mesh object, NORMAL_RES² super-pixels, 4 lights): the
  material's standard errors are known to be too small and are withheld by
  the command (``calibrated: false``): the row shows by how much.

The JSON is written after every fit and read back at the start: seeds already
in it are skipped (a run can be stopped and resumed; a mode's settings must
match the saved ones).  Per mode and parameter the table gives: n fits (not
converged, left out of the statistics), the mean relative error +- its
standard error (bias), the spread (SD of the relative error), the mean
reported relative SE, spread / reported SE, the coverage of the reported 95 %
intervals with its Wilson 95 % interval, the coverage of the Fisher intervals
alone (where the fit replaced some ends by profile-likelihood ones: how many
fits), the mean fit time, and a flag (**no**) where the Wilson interval does
not overlap 90-99 %.  Errors of kappa = 0 are absolute.  Timings are wall clock
on one Dr.Jit thread.
"""
import argparse
import json
import math
import os
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.join(ROOT, "tools"))

from bench_fit_noise import MATERIALS, LIGHT, wilson  # noqa: E402

MODES = ("single", "joint1", "joint3", "joint6", "free_power", "colour", "normals")
TARGET = (0.90, 0.99)


class Runner:
    """Lazily built per-mode data (ideal images, colour case) shared by the seeds of a mode."""

    def __init__(self, args):
        from fmbrdf_mi.sensor.camera import CameraModel

        self.args = args
        self.cam = CameraModel(full_well=10000.0, read_noise=2.5, bits=12)
        self.truth = MATERIALS[args.material]
        self._cache = {}

    def settings(self, mode):
        """What the saved runs of ``mode`` must share with this run to be resumed."""
        a = self.args
        if mode == "colour":
            return {"periods": a.periods}
        if mode == "normals":
            return {"res": a.normal_res, "lights": 4, "lam": 0.3}
        extra = {"area_points": a.area_points} if a.area_points and mode == "single" else {}
        if a.intervals != "auto" and mode == "single":
            extra["intervals"] = a.intervals
        return {"material": a.material, "size": a.size, **extra}

    def _get(self, key, make):
        if key not in self._cache:
            self._cache[key] = make()
        return self._cache[key]

    def fit(self, mode, seed):
        """Run one seed of ``mode``; returns the record: truth, params, std_errors, ci95 (, ci95_fisher,
        interval_kind), converged, time."""
        a = self.args
        if mode == "single":
            from bench_fit_noise import noise_fit
            from fmbrdf_mi.synthetic.spheres import capture_observation, ideal_sphere

            ideal = self._get("single", lambda: ideal_sphere(self.truth, res=a.size, light=LIGHT))
            obs, cap = capture_observation(ideal, self.cam, seed=seed)
            rec, _ = noise_fit(obs, cap, material=a.material, size=a.size, seed=seed, loss="likelihood",
                               truth=self.truth, cache=self._cache.setdefault("single_ev", {}),
                               area_points=a.area_points, intervals=a.intervals)
            return rec
        if mode in ("joint1", "joint3", "joint6", "free_power"):
            from bench_fit_lights import capture_seed, ideal_images, lights_fits, subsets

            free = mode == "free_power"
            k = 3 if free else int(mode[-1])
            powers = (1.0, 0.8, 0.6, 1.2, 1.7, 0.9) if free else (1.0,) * 6
            ideals = self._get(("ring", powers), lambda: ideal_images(self.truth, a.size, powers))
            obs = capture_seed(ideals, self.cam, seed)
            (rec, _), = lights_fits(obs, k, subsets([k]), material=a.material, seed=seed, truth=self.truth,
                                    powers=powers, free_power=free, power_start=("ratio",))
            return rec
        if mode == "colour":
            from bench_fit_colour import _truth, colour_case, colour_fit

            case = self._get("colour", lambda: colour_case(a.periods))
            rec = colour_fit(case, seed)
            rec["truth"] = _truth({})
            return rec
        if mode == "normals":
            from bench_normal_refine import TRUTH, normal_fit

            rec = normal_fit(100 + seed, res=a.normal_res, lights=4, lam=0.3)
            rec["truth"] = dict(TRUTH)
            return rec
        raise ValueError(mode)


def load(path):
    if path and os.path.exists(path):
        with open(path) as f:
            return json.load(f)
    return {"modes": {}}


def save(path, data):
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        json.dump(data, f, indent=1, default=float)
    os.replace(tmp, path)


def run(args):
    import drjit as dr

    dr.set_thread_count(args.threads)
    data = load(args.json)
    runner = Runner(args)
    data.setdefault("machine", {})
    for mode in args.modes:
        n = args.mode_seeds.get(mode, args.seeds)
        m = data["modes"].setdefault(mode, {"settings": runner.settings(mode), "runs": []})
        if m["settings"] != runner.settings(mode):
            sys.exit(f"bench_modes: {args.json} has {mode} with {m['settings']}, this run {runner.settings(mode)}; "
                     "use another --json or the same settings")
        done = {r["seed"] for r in m["runs"]}
        todo = [s for s in range(args.seed0, args.seed0 + n) if s not in done]
        print(f"# {mode}: {len(done)} seeds saved, {len(todo)} to run", file=sys.stderr, flush=True)
        for seed in todo:
            t = time.time()
            rec = runner.fit(mode, seed)
            rec["seed"] = seed                  # the mode's seed index (normals: noise seed 100 + seed)
            rec["wall"] = time.time() - t
            m["runs"].append(rec)
            if args.json:
                save(args.json, data)
            print(f"{mode:10s} seed {seed:3d} {rec['time']:6.1f} s {'ok' if rec['converged'] else 'NC'} "
                  + " ".join(f"{k}={v:.4g}" for k, v in rec["params"].items() if v is not None),
                  file=sys.stderr, flush=True)
    return data


def _covers(iv, tv):
    return iv is not None and iv[0] is not None and iv[0] <= tv <= iv[1]


def summarise(data):
    """Rows per (mode, parameter): the statistics of the table."""
    rows = []
    for mode in [m for m in MODES if m in data["modes"]]:
        rs = data["modes"][mode]["runs"]
        if not rs:
            continue
        ok = [r for r in rs if r["converged"] and r.get("std_errors")]
        t = float(np.mean([r["time"] for r in rs]))
        truth = rs[0]["truth"]
        names = [k for k in truth if any(k in r["params"] for r in rs)]
        for k in names:
            tv = truth[k]
            denom = tv if tv != 0 else 1.0
            use = [r for r in ok if r["std_errors"].get(k) is not None]
            e = np.array([(r["params"][k] - tv) / denom for r in use])
            se = np.array([r["std_errors"][k] / abs(denom) for r in use])
            ci = [r.get("ci95") or {} for r in use]
            cov = [_covers(c.get(k), tv) if c.get(k) is not None else abs(r["params"][k] - tv) <= 1.96 * r["std_errors"][k]
                   for c, r in zip(ci, use)]
            fis = [r["ci95_fisher"][k] for r in use if k in (r.get("ci95_fisher") or {})]
            cov_f = [_covers(c, tv) for c in fis]
            profiled = sum(1 for r in use if "profile" in (r.get("interval_kind") or {}).get(k, ""))
            n = len(e)
            spread = float(e.std(ddof=1)) if n > 1 else np.nan
            rep = float(se.mean()) if n else np.nan
            lo, hi = wilson(int(np.sum(cov)), len(cov))
            rows.append({"mode": mode, "param": k, "truth": tv, "relative": tv != 0, "n": n,
                         "not_converged": len(rs) - len(ok), "mean_error": float(e.mean()) if n else np.nan,
                         "se_mean": spread / math.sqrt(n) if n > 1 else np.nan, "spread": spread,
                         "mean_reported_se": rep, "ratio": spread / rep if n > 1 and rep > 0 else np.nan,
                         "covered": int(np.sum(cov)), "coverage_n": len(cov),
                         "coverage": float(np.mean(cov)) if cov else np.nan, "wilson": [lo, hi],
                         "coverage_fisher": float(np.mean(cov_f)) if len(cov_f) == n and n else None,
                         "profiled": profiled, "time": t,
                         "flag": bool(cov) and not (lo <= TARGET[1] and hi >= TARGET[0]),
                         "uncalibrated": any(r.get("calibrated") is False for r in rs)})
    return rows


def table(rows):
    out = ["| mode | param | n (NC) | bias ± SE | spread | mean reported SE | spread / SE | "
           "95 % coverage (Wilson 95 %) | Fisher only (fits profiled) | fit time (s) | outside 90–99 % |",
           "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if r["relative"]:
            pm = lambda x: f"{100 * x:+.2f} %"  # noqa: E731
            pc = lambda x: f"{100 * x:.2f} %"  # noqa: E731
        else:
            pm = lambda x: f"{x:+.3g}"  # noqa: E731
            pc = lambda x: f"{x:.3g}"  # noqa: E731
        lo, hi = r["wilson"]
        fis = (f"{100 * r['coverage_fisher']:.1f} % ({r['profiled']})" if r["coverage_fisher"] is not None else "–")
        name = r["param"] + (" (withheld)" if r["uncalibrated"] else "")
        out.append(f"| {r['mode']} | {name} | {r['n']} ({r['not_converged']}) | {pm(r['mean_error'])} ± "
                   f"{pc(r['se_mean'])} | {pc(r['spread'])} | {pc(r['mean_reported_se'])} | {r['ratio']:.2f} | "
                   f"{100 * r['coverage']:.1f} % ({100 * lo:.1f}–{100 * hi:.1f}) | {fis} | {r['time']:.1f} | "
                   f"{'**no**' if r['flag'] else ''} |")
    return "\n".join(out)


def parse_mode_seeds(text):
    out = {}
    for item in filter(None, (text or "").split(",")):
        mode, _, n = item.partition("=")
        if mode not in MODES or not n.isdigit():
            raise ValueError(item)
        out[mode] = int(n)
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--modes", default="single,joint3,joint6,free_power,colour,normals",
                   help=f"comma-separated of {', '.join(MODES)}, run in this order (default %(default)s)")
    p.add_argument("--seeds", type=int, default=64, help="seeds per mode (default %(default)s)")
    p.add_argument("--mode-seeds", default="", metavar="MODE=N,...", help="per-mode seed counts, e.g. colour=32")
    p.add_argument("--seed0", type=int, default=0)
    p.add_argument("--material", default="medium", help=f"one of {', '.join(MATERIALS)} (not colour's)")
    p.add_argument("--size", type=int, default=40, help="super-pixels across the sphere's image (default 40)")
    p.add_argument("--periods", type=int, default=16, help="colour: 4x4 periods across (default 16)")
    p.add_argument("--normal-res", type=int, default=24, help="normals: super-pixels across (default 24)")
    p.add_argument("--area-points", type=int, default=None, metavar="M",
                   help="single: the likelihood's M x M points per raw sample (default: the fit's, 2; the data "
                        "average 4 x 4)")
    p.add_argument("--intervals", default="auto", choices=("auto", "profile", "fisher"),
                   help="single: the fit's intervals option (default %(default)s)")
    p.add_argument("--threads", type=int, default=1, help="Dr.Jit threads (default 1)")
    p.add_argument("--json", metavar="OUT.json", help="runs, saved after every fit; seeds in it are skipped")
    p.add_argument("--table", metavar="IN.json", help="print the table of a saved run and exit")
    args = p.parse_args(argv)
    if args.table:
        print(table(summarise(load(args.table))))
        return 0
    args.modes = [m for m in args.modes.split(",") if m]
    bad = [m for m in args.modes if m not in MODES]
    if bad:
        p.error(f"--modes: unknown {', '.join(bad)} (have {', '.join(MODES)})")
    if args.material not in MATERIALS:
        p.error(f"--material: one of {', '.join(MATERIALS)}")
    try:
        args.mode_seeds = parse_mode_seeds(args.mode_seeds)
    except ValueError as e:
        p.error(f"--mode-seeds: MODE=N, got {e}")
    t0 = time.time()
    data = run(args)
    print(table(summarise(data)))
    print(f"# {time.time() - t0:.0f} s", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
