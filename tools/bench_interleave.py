"""Fit times of two versions of the package, measured in interleaved rounds (a refactor must not slow fits).

    python tools/bench_interleave.py --old ../old --rounds 3 -- tools/bench_fit.py --sets 6 --no-baselines
    python tools/bench_interleave.py --old ../old --rounds 3 -- tools/bench_fit_lights.py --materials glossy \\
        --lights 3 --seeds 2 --size 24
    python tools/bench_interleave.py --old ../old --rounds 3 -- tools/bench_fit_colour.py --periods 12 --seeds 3

``--old DIR``: a checkout of the other version (``git worktree add --detach ../old COMMIT``).  Each round
runs the bench once with ``DIR`` first on ``PYTHONPATH`` (its ``tools/`` script, its package) and once with
this checkout, alternating which goes first, each writing ``--json``.  From every JSON it sums the fits' own
times (every number under a key ``time`` or ``fit_time`` of its runs: the fit, not the data's rendering), and reports
per version the best round (the least disturbed by other load) and the ratio new / old of the best rounds,
with the date and CPU.  Timings on this 2-core machine move 2-3x with load: only the ratio in one run means
something, and only on a quiet machine.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, HERE)

from _common import cpu_name  # noqa: E402


def fit_times(d):
    """Every number under a key 'time' or 'fit_time' in a bench's JSON."""
    out = []
    if isinstance(d, dict):
        for k, v in d.items():
            if k in ("time", "fit_time") and isinstance(v, (int, float)):
                out.append(float(v))
            else:
                out += fit_times(v)
    elif isinstance(d, list):
        for v in d:
            out += fit_times(v)
    return out


def run(tree, script, args, work, tag):
    path = os.path.join(work, f"{tag}.json")
    env = dict(os.environ, PYTHONPATH=tree + (os.pathsep + os.environ["PYTHONPATH"] if os.environ.get("PYTHONPATH")
                                               else ""))
    t = time.time()
    subprocess.run([sys.executable, os.path.join(tree, script), *args, "--json", path], cwd=tree, env=env,
                   check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wall = time.time() - t
    with open(path) as f:
        d = json.load(f)
    times = fit_times(d["runs"] if isinstance(d, dict) and "runs" in d else d)   # not the tables' means
    return {"fits": len(times), "fit_total": sum(times), "fit_max": max(times) if times else None, "wall": wall}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--old", required=True, help="checkout of the version to compare with")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("bench", nargs=argparse.REMAINDER, help="-- tools/SCRIPT.py [its options, without --json]")
    a = p.parse_args(argv)
    bench = a.bench[1:] if a.bench[:1] == ["--"] else a.bench
    if not bench:
        p.error("give the bench after --, e.g. -- tools/bench_fit.py --sets 6 --no-baselines")
    old = os.path.abspath(a.old)
    script, args = bench[0], bench[1:]
    res = {"old": [], "new": []}
    with tempfile.TemporaryDirectory() as work:
        for r in range(a.rounds):
            order = [("old", old), ("new", ROOT)] if r % 2 == 0 else [("new", ROOT), ("old", old)]
            for tag, tree in order:
                x = run(tree, script, args, work, f"{tag}{r}")
                res[tag].append(x)
                print(f"round {r + 1} {tag}: {x['fits']} fits, fit time {x['fit_total']:.1f} s (max {x['fit_max']:.1f}), "
                      f"wall {x['wall']:.1f} s", flush=True)
    best = {k: min(v, key=lambda x: x["fit_total"]) for k, v in res.items()}
    print(f"\n{time.strftime('%Y-%m-%d')}, {cpu_name()}, {os.cpu_count()} cores: {' '.join(bench)}")
    print(f"best of {a.rounds}: old {best['old']['fit_total']:.2f} s, new {best['new']['fit_total']:.2f} s, "
          f"new / old = {best['new']['fit_total'] / best['old']['fit_total']:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
