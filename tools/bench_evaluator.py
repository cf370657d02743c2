"""CPU time of one derivative evaluation of the pixel evaluator in chunks (the per-pixel fits' unit of work on
frames larger than one chunk), of this checkout against another, in interleaved rounds.

    python tools/bench_evaluator.py --old ../old [--directions 4000000] [--chunk 2000000] [--rounds 2]

Each round runs, in a fresh process per version (``--old DIR``'s package, then this checkout's, alternating which
goes first), :meth:`~fmbrdf_mi.fit.evaluate.pixel_model.PixelEvaluator.parts` with the derivatives in every shape
parameter of the FMBRDF at ``--directions`` random normals (4 footprint directions per pixel) in chunks of
``--chunk`` directions, three times at nearby shapes; a round's time is the least CPU time (user + system, all
threads) of its second and third evaluations (the first compiles the kernels).  Reported: each version's best
round and the ratio new / old; only the ratio of one run means something on a loaded machine.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def worker(directions, chunk):
    import numpy as np

    from fmbrdf_mi.fit.evaluate import pixel_model as PM
    from fmbrdf_mi.fit.evaluate.models import get_model

    rng = np.random.default_rng(0)
    n = rng.normal(size=(directions, 3))
    n[:, 2] = np.abs(n[:, 2]) + 1.0
    v = np.array([0.0, 0.0, 1.0]) + 0.1 * rng.normal(size=(directions, 3))
    model = get_model("fmbrdf")
    PM.PixelEvaluator.CHUNK_DIRECTIONS = chunk
    ev = PM.PixelEvaluator(model, n, v, (-0.5, 0.5, 1.0), weights=np.full(4, 0.25))
    shape = dict(eta=1.45, alpha=0.25, beta=1.0, kappa=10.0)
    cpu = []
    for i in range(3):
        c = time.process_time()
        ev.parts({k: x * (1 + 0.01 * i) for k, x in shape.items()}, wrt=[p.name for p in model.shape])
        cpu.append(time.process_time() - c)
    print(json.dumps({"cpu": min(cpu[1:]), "chunks": len(ev._chunks())}))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--old", required=True, help="a checkout of the other version")
    ap.add_argument("--directions", type=int, default=4_000_000)
    ap.add_argument("--chunk", type=int, default=2_000_000)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.worker:
        return worker(a.directions, a.chunk)
    best = {}
    for r in range(a.rounds):
        for name, code in (("old", a.old), ("new", ROOT))[::1 if r % 2 == 0 else -1]:
            out = subprocess.run([sys.executable, os.path.abspath(__file__), "--worker", "--old", a.old,
                                  "--directions", str(a.directions), "--chunk", str(a.chunk)],
                                 env=dict(os.environ, PYTHONPATH=code), capture_output=True, text=True, check=True)
            res = json.loads(out.stdout.strip().splitlines()[-1])
            print(f"round {r + 1} {name}: {res['cpu']:.2f} s CPU per evaluation ({res['chunks']} chunks)", flush=True)
            best[name] = min(best.get(name, float("inf")), res["cpu"])
    print(f"best: old {best['old']:.2f} s, new {best['new']:.2f} s, new / old {best['new'] / best['old']:.2f}; "
          f"{time.strftime('%Y-%m-%d')}, DRJIT_NUM_THREADS={os.environ.get('DRJIT_NUM_THREADS', 'default')}, "
          f"load average {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
