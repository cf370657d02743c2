"""Coverage of the reported 95 % intervals on a tiny sphere (shape fixed, k_s and r_k free), many camera-noise seeds.

    python tools/check_paper_coverage.py N RES SEED0 [paper|likelihood]

IMX250MZR-like camera (full well 3000 e-, read noise 6 e-, 12 bits), the material of
tests/fit/test_objectives_likelihood.py; prints the mean error +- its SE, the spread, the mean reported SE and the coverage.
"""
import os, sys, time
import numpy as np
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from fmbrdf_mi.camera import CameraModel
from fmbrdf_mi.fit import fit
from fmbrdf_mi.fit.api.fitting import FitOptions
from fmbrdf_mi.fit.problem.data import prepare, select_pixels
from fmbrdf_mi.fit.evaluate.synthetic import capture_observation, ideal_sphere
TRUE = {"eta": 1.55, "alpha": 0.35, "beta": 1.4, "kappa": 30.0, "k_s": 0.9, "r_k": 1.7}
SHAPE = {k: TRUE[k] for k in ("eta", "alpha", "beta", "kappa")}
LIGHT = (0.45, 0.35, 1.0)
N, res, seed0 = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
loss = sys.argv[4] if len(sys.argv) > 4 else "paper"
cam = CameraModel(full_well=3000.0, read_noise=6.0, bits=12)
ideal = ideal_sphere(TRUE, res=res, light=LIGHT)
opts = FitOptions(loss=loss, fixed=SHAPE, starts=1)
evs = {}
est, se, cov = [], [], []
t0 = time.time(); nc = 0
for s in range(seed0, seed0 + N):
    obs, _ = capture_observation(ideal, cam, seed=s)
    idx, _ = select_pixels(obs, opts)
    key = tuple(idx)
    if key not in evs:
        evs[key] = prepare([obs], opts, loss, single=True).evaluator
    r = fit(obs, opts, evaluator=evs[key], progress=False)
    if not r.converged:
        nc += 1; continue
    est.append([r.params[k] for k in ("k_s", "r_k")]); se.append([r.std_errors[k] for k in ("k_s", "r_k")])
    cov.append([r.uncertainty["ci95"][k][0] <= TRUE[k] <= r.uncertainty["ci95"][k][1] for k in ("k_s", "r_k")])
TR = np.array([0.9, 1.7]); est, se, cov = map(np.array, (est, se, cov)); e = est - TR
print(f"res {res} N {N} (NC {nc}) pixels {len(idx)} time {time.time()-t0:.1f} s")
print("mean err %", np.round(100 * e.mean(0) / TR, 2), "+-", np.round(100 * e.std(0, ddof=1) / TR / np.sqrt(len(e)), 2))
print("spread %", np.round(100 * e.std(0, ddof=1) / TR, 2), "mean SE %", np.round(100 * se.mean(0) / TR, 2), "coverage", cov.mean(0))
