"""Wall time of the joint normal refinement (:func:`fmbrdf_mi.fit.api.normal_joint.refine_joint`) of two source trees,
interleaved on the same core: this tree against another (e.g. an older commit's worktree).

    python tools/bench_normal_refine_speed.py --old /path/to/old/worktree [--new ROOT] [--res 40] [--reps 2]
                                             [--lights 4] [--seed 11] [--lam 0.3] [--json OUT.json]

Each run is a fresh process with ``PYTHONPATH`` set to the tree (checked: ``fmbrdf_mi.__file__`` must lie in it)
and one Dr.Jit thread (``dr.set_thread_count(1)``; pin the whole command to one core with ``taskset -c N``).
The object is tools/bench_normal_refine.py's (``--starts ps``: Lambertian photometric stereo start, material by
a joint fit on it, then ``refine_joint`` at ``--lam``); only ``refine_joint`` is timed.  Printed per run: the
tree, seconds, LM iterations, the refined normals' mean / median angle to the ray-cast ones and the material
(k_s relative to the truth's scale): the two trees should agree on all but the time.
"""
import argparse
import json
import os
import subprocess
import sys

HERE = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

CHILD = r"""
import json, os, sys, tempfile, time
root = sys.argv[1]
sys.path.insert(0, root)
import numpy as np
import drjit as dr
dr.set_thread_count(1)
import fmbrdf_mi
assert os.path.abspath(fmbrdf_mi.__file__).startswith(os.path.abspath(root) + os.sep), fmbrdf_mi.__file__
from fmbrdf_mi.fit.inputs.authors import read_object
from fmbrdf_mi.fit.api.joint import fit_joint
from fmbrdf_mi.fit.api.normal_joint import refine_joint
from fmbrdf_mi.fit.api.normal_refine import angular_error_deg, photometric_stereo
from fmbrdf_mi.fit.evaluate.synthetic_object import write_authors_object
cfg = json.loads(sys.argv[2])
K = cfg["lights"]
with tempfile.TemporaryDirectory() as tmp:
    truth = write_authors_object(tmp + "/blob", cfg["truth"], cfg["lights_dirs"][:K], res=cfg["res"], fov=12.0,
                                 powers=cfg["powers"][:K], seed=cfg["seed"])
    specs, _ = read_object(tmp + "/blob", conversion_gain=truth["camera"]["conversion_gain"], read_noise=2.5)
ks_scale = truth["irradiance_dn"] * max(cfg["powers"][:K])
obs = [s.input for s in specs]
gt = obs[0].normals.copy()
n0 = photometric_stereo(obs)
for o in obs:
    o.normals, o.geometry = n0, None
params = fit_joint(obs, progress=False).params
t = time.time()
j = refine_joint(obs, n0, params, lam=cfg["lam"])
dt = time.time() - t
e1 = angular_error_deg(j.normals, gt, j.mask)
p = dict(j.params)
p["k_s"] /= ks_scale
print("RESULT " + json.dumps({"file": fmbrdf_mi.__file__, "time": dt, "iterations": len(j.history),
                              "pixels": j.n_pixels, "converged": j.converged, "mean": float(e1.mean()),
                              "median": float(np.median(e1)), "params": p, "energy": j.loss,
                              "stop_reason": j.stop_reason, "material_stage": j.options.get("material_stage"),
                              "history": [[h["round"], h["iter"], h["energy"]] for h in j.history]}))
"""


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--old", required=True, help="the other source tree (repository root)")
    ap.add_argument("--new", default=HERE, help="default: this tree")
    ap.add_argument("--res", type=int, default=40)
    ap.add_argument("--reps", type=int, default=2)
    ap.add_argument("--lights", type=int, default=4)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--lam", type=float, default=0.3)
    ap.add_argument("--json", metavar="OUT.json", help="every run's record, with the LM history (round, iter, energy)")
    args = ap.parse_args(argv)
    sys.path.insert(0, os.path.join(HERE, "tools"))
    from bench_normal_refine import LIGHTS, POWERS, TRUTH
    cfg = json.dumps({"res": args.res, "lights": args.lights, "seed": args.seed, "lam": args.lam, "truth": TRUTH,
                      "lights_dirs": LIGHTS, "powers": POWERS})
    rows = []
    for rep in range(args.reps):
        for name, root in (("old", args.old), ("new", args.new)):
            env = dict(os.environ, PYTHONPATH=root, DRJIT_NUM_THREADS="1")
            out = subprocess.run([sys.executable, "-c", CHILD, root, cfg], env=env, capture_output=True, text=True)
            line = [s for s in out.stdout.splitlines() if s.startswith("RESULT ")]
            if out.returncode or not line:
                print(out.stdout, out.stderr, file=sys.stderr)
                return 1
            r = json.loads(line[0][7:])
            r["tree"], r["rep"] = name, rep
            rows.append(r)
            mat = ", ".join(f"{k} {v:.6g}" for k, v in r["params"].items())
            print(f"{name} ({os.path.dirname(os.path.dirname(r['file']))}) rep {rep}: {r['time']:.1f} s, "
                  f"{r['iterations']} iterations, {r['pixels']} pixels, energy {r['energy']:.8e}, normals "
                  f"{r['mean']:.4f} / {r['median']:.4f} deg (mean / median); {mat}", flush=True)
    for name in ("old", "new"):
        ts = [r["time"] for r in rows if r["tree"] == name]
        print(f"{name}: {min(ts):.1f} s best of {len(ts)} (all: {', '.join(f'{t:.1f}' for t in ts)})")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"config": vars(args), "runs": rows}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
