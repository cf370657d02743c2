"""Wall time, CPU time and peak memory of the joint normal refinement
(:func:`fmbrdf_mi.fit.api.normal_joint.refine_joint`) of two source trees, interleaved on the same core: this
tree against another (e.g. an older commit's worktree), at one or several object sizes.

    python tools/bench_normal_refine_speed.py --old /path/to/old/worktree [--new ROOT] [--res 40,80,100]
                                             [--reps 2] [--lights 4] [--seed 11] [--lam 0.3] [--threads 1]
                                             [--inputs DIR] [--json OUT.json]

The object is tools/bench_normal_refine.py's (``--starts ps``: Lambertian photometric stereo start, material by
a joint fit on it, then ``refine_joint`` at ``--lam``).  Per size, one child process of the new tree builds
these inputs once and pickles them (``--inputs DIR``: kept there as ``inputsRES.pkl`` and reused by a later
run with the same DIR, lights, seed and lam: the inputs' own build is the slow part at 100²); then, ``--reps`` times, a child of the old tree and one of the new refine
them (interleaved).  Each child is a fresh process with ``PYTHONPATH`` set to its tree (checked:
``fmbrdf_mi.__file__`` must lie in it) and ``--threads`` Dr.Jit threads (``dr.set_thread_count``; with 1,
pin the whole command to one core with ``taskset -c N``).  Only ``refine_joint`` is timed: wall and CPU
seconds (``time.process_time``, all threads; on a shared machine the CPU time is the steadier figure),
LM iterations and seconds per iteration, peak resident memory of the child (``ru_maxrss``, the inputs
included; also given before the refinement), the refined normals' mean / median angle to the ray-cast ones
and the material (k_s relative to the truth's scale).  The two trees should agree on all but the times.
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile

HERE = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

PREAMBLE = r"""
import json, os, pickle, resource, sys, time
root = sys.argv[1]
sys.path.insert(0, root)
import numpy as np
import drjit as dr
dr.set_thread_count(int(os.environ["DRJIT_NUM_THREADS"]))
import fmbrdf_mi
assert os.path.abspath(fmbrdf_mi.__file__).startswith(os.path.abspath(root) + os.sep), fmbrdf_mi.__file__
cfg = json.loads(sys.argv[2])
"""

BUILD = PREAMBLE + r"""
import tempfile
from fmbrdf_mi.fit.inputs.authors import read_object
from fmbrdf_mi.fit.api.joint import fit_joint
from fmbrdf_mi.fit.api.normal_refine import photometric_stereo
from fmbrdf_mi.fit.evaluate.synthetic_object import write_authors_object
K = cfg["lights"]
with tempfile.TemporaryDirectory() as tmp:
    truth = write_authors_object(tmp + "/blob", cfg["truth"], cfg["lights_dirs"][:K], res=cfg["res"], fov=12.0,
                                 powers=cfg["powers"][:K], seed=cfg["seed"])
    specs, _ = read_object(tmp + "/blob", conversion_gain=truth["camera"]["conversion_gain"], read_noise=2.5)
obs = [s.input for s in specs]
gt = obs[0].normals.copy()
n0 = photometric_stereo(obs)
for o in obs:
    o.normals, o.geometry = n0, None
params = fit_joint(obs, progress=False).params
with open(cfg["inputs"], "wb") as f:
    pickle.dump({"obs": obs, "gt": gt, "n0": n0, "params": params,
                 "ks_scale": truth["irradiance_dn"] * max(cfg["powers"][:K])}, f)
"""

CHILD = PREAMBLE + r"""
from fmbrdf_mi.fit.api.normal_joint import refine_joint
from fmbrdf_mi.fit.api.normal_refine import angular_error_deg
with open(cfg["inputs"], "rb") as f:
    c = pickle.load(f)
rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
t, cpu = time.time(), time.process_time()
j = refine_joint(c["obs"], c["n0"], c["params"], lam=cfg["lam"])
dt, dcpu = time.time() - t, time.process_time() - cpu
e1 = angular_error_deg(j.normals, c["gt"], j.mask)
p = dict(j.params)
p["k_s"] /= c["ks_scale"]
print("RESULT " + json.dumps({"file": fmbrdf_mi.__file__, "time": dt, "cpu": dcpu, "iterations": len(j.history),
                              "pixels": j.n_pixels, "converged": j.converged, "mean": float(e1.mean()),
                              "median": float(np.median(e1)), "params": p, "energy": j.loss,
                              "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                              "rss_before_mb": rss0, "stop_reason": j.stop_reason,
                              "material_stage": j.options.get("material_stage"),
                              "history": [[h["round"], h["iter"], h["energy"]] for h in j.history]}))
"""


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--old", required=True, help="the other source tree (repository root)")
    ap.add_argument("--new", default=HERE, help="default: this tree")
    ap.add_argument("--res", default="40", help="object sizes, comma-separated (default %(default)s)")
    ap.add_argument("--reps", type=int, default=2)
    ap.add_argument("--lights", type=int, default=4)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--lam", type=float, default=0.3)
    ap.add_argument("--threads", type=int, default=1, help="Dr.Jit threads of each child (default %(default)s)")
    ap.add_argument("--inputs", metavar="DIR", help="keep (and reuse) the pickled inputs here (default: a temporary "
                    "directory)")
    ap.add_argument("--json", metavar="OUT.json", help="every run's record, with the LM history (round, iter, energy)")
    args = ap.parse_args(argv)
    sys.path.insert(0, os.path.join(HERE, "tools"))
    from bench_normal_refine import LIGHTS, POWERS, TRUTH
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        if args.inputs:
            os.makedirs(args.inputs, exist_ok=True)
            tmp = args.inputs
        for res in [int(r) for r in args.res.split(",")]:
            cfg = {"res": res, "lights": args.lights, "seed": args.seed, "lam": args.lam, "truth": TRUTH,
                   "lights_dirs": LIGHTS, "powers": POWERS, "inputs": os.path.join(tmp, f"inputs{res}.pkl")}
            env = dict(os.environ, PYTHONPATH=args.new, DRJIT_NUM_THREADS=str(args.threads))
            out = subprocess.run([sys.executable, "-c", BUILD, args.new, json.dumps(cfg)], env=env,
                                 capture_output=True, text=True) if not os.path.exists(cfg["inputs"]) else None
            if out is not None and out.returncode:
                print(out.stdout, out.stderr, file=sys.stderr)
                return 1
            for rep in range(args.reps):
                for name, root in (("old", args.old), ("new", args.new)):
                    env = dict(os.environ, PYTHONPATH=root, DRJIT_NUM_THREADS=str(args.threads))
                    out = subprocess.run([sys.executable, "-c", CHILD, root, json.dumps(cfg)], env=env,
                                         capture_output=True, text=True)
                    line = [s for s in out.stdout.splitlines() if s.startswith("RESULT ")]
                    if out.returncode or not line:
                        print(out.stdout, out.stderr, file=sys.stderr)
                        return 1
                    r = json.loads(line[0][7:])
                    r.update(tree=name, rep=rep, res=res, load=os.getloadavg()[0])
                    rows.append(r)
                    mat = ", ".join(f"{k} {v:.6g}" for k, v in r["params"].items())
                    print(f"{res}² {name} ({os.path.dirname(os.path.dirname(r['file']))}) rep {rep}: "
                          f"{r['time']:.1f} s wall, {r['cpu']:.1f} s CPU, {r['iterations']} iterations "
                          f"({r['time'] / r['iterations']:.2f} s wall, {r['cpu'] / r['iterations']:.2f} s CPU "
                          f"each), {r['pixels']} pixels, peak RSS {r['peak_rss_mb']:.0f} MB (inputs "
                          f"{r['rss_before_mb']:.0f} MB), energy {r['energy']:.8e}, normals {r['mean']:.4f} / "
                          f"{r['median']:.4f} deg (mean / median); {mat}; load {r['load']:.1f}", flush=True)
            for name in ("old", "new"):
                rs = [r for r in rows if r["tree"] == name and r["res"] == res]
                ts, cs = [r["time"] for r in rs], [r["cpu"] for r in rs]
                print(f"{res}² {name}: {min(ts):.1f} s wall, {min(cs):.1f} s CPU best of {len(ts)} (all wall: "
                      f"{', '.join(f'{t:.1f}' for t in ts)}; CPU: {', '.join(f'{t:.1f}' for t in cs)})", flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"config": vars(args), "runs": rows}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
