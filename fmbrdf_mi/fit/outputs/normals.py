"""``--refine-normals``: :class:`NormalRefinement` fits the material on a start map, then material and normals
(:func:`fmbrdf_mi.fit.api.normal_joint.refine_joint`); ``normals.npy``: (H, W, 3), x image right, y up, z to camera."""
from __future__ import annotations

import os
import time

import numpy as np

from fmbrdf_mi.geometry import sphere_normals
from fmbrdf_mi.fit.api.options import fit_options
from fmbrdf_mi.fit.api.fitting import fit_joint
from fmbrdf_mi.fit.api.normal_joint import refine_joint
from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.inputs.normal_maps import angular_error_deg, check_views, photometric_stereo
from fmbrdf_mi.fit.inputs.observations import erode, find_sphere, read_vectors
from fmbrdf_mi.fit.outputs import plots
from fmbrdf_mi.fit.outputs.record import command_block
from fmbrdf_mi.fit.outputs.job import FitJob
from fmbrdf_mi.fit.solve.optimise import default_progress

OUTPUTS = ("fit.json", "normals.npy", "normals.png", "normals_change.png")


def start_normals(obs, start):
    """(H, W, 3) start map and the mask of pixels it covers; ``start``: ``ps`` (photometric stereo), ``sphere``
    (the mask's sphere) or a ``.npy`` in this package's camera frame."""
    m = obs[0].mask.copy()
    if start == "ps":
        return photometric_stereo(obs), m
    if start == "sphere":
        (cx, cy), r = find_sphere(m)
        ns, ms, _ = sphere_normals(obs[0].shape, (cx, cy), r)
        m &= ms
        return np.where(m[..., None], ns, np.array([0.0, 0.0, 1.0])), m
    n = read_vectors(start, "--normals-start", obs[0].shape)
    ln = np.linalg.norm(n, axis=-1)
    ok = np.isfinite(ln) & (ln > 0.5)
    if not np.all(ok[m]):
        raise InputError(f"--normals-start {start}: {int((~ok & m).sum())} pixels of the mask have no unit normal "
                         "(non-finite or length < 0.5)")
    n = np.where(ok[..., None], n / np.where(ok, ln, 1.0)[..., None], np.array([0.0, 0.0, 1.0]))
    if np.mean(np.sum(n[m] * obs[0].view_dirs[m], 1) < 0) > 0.5:
        raise InputError(f"--normals-start {start}: most normals face away from the camera (this package's frame "
                         "is x image right, y image up, z towards the camera; OpenCV maps need y and z negated)")
    return n, m


def _errors(n, gt, mask):
    """Mean, median and 90th percentile of the angles (degrees) between ``n`` and ``gt`` on ``mask``."""
    e = angular_error_deg(n, gt, mask)
    return {"mean": float(e.mean()), "median": float(np.median(e)), "p90": float(np.percentile(e, 90)),
            "pixels": int(mask.sum())}


class NormalRefinement(FitJob):
    """Refine the normals of the non-held-out images (the caller's observations ``obs``) and write the outputs."""

    def __init__(self, specs, names, obs, out, *, start, lam, model, fit_kw, ground_truth, **kw):
        super().__init__(out, **kw)
        self.specs, self.names, self.obs = specs, names, obs
        self.start, self.lam, self.model, self.fit_kw = start, lam, model, dict(fit_kw or {})
        self.gt = None if ground_truth is None else np.asarray(ground_truth, float).copy()
        self.keep = [k for k, s in enumerate(specs) if not s.holdout]
        self.say = default_progress if self.progress else (lambda m: None)

    def check(self):
        if len(self.keep) < 3:
            raise InputError(f"--refine-normals: needs K >= 3 images under different lights, got {len(self.keep)}"
                             + (" (held-out images do not count)" if len(self.keep) < len(self.specs) else ""))

    def files(self):
        return [os.path.join(self.out, f) for f in OUTPUTS]

    def read(self):
        self.fit_obs = fit_obs = [self.obs[k] for k in self.keep]
        self.n0, m0 = start_normals(fit_obs, self.start)
        check_views(fit_obs, self.n0)
        for o in fit_obs:
            o.mask = o.mask & m0

    def fit(self):
        fit_obs, n0, say, kw = self.fit_obs, self.n0, self.say, self.fit_kw
        self.t_fit = time.time()
        opts = fit_options(kw, model=self.model)
        say(f"[normals] start {self.start}; {len(fit_obs)} images; the material on the start map, then the joint "
            f"step; smoothness {self.lam:g}")
        for o in fit_obs:
            o.normals = n0
            o.geometry = None
        params = fit_joint(fit_obs, opts, progress=say).params
        self.joint = refine_joint(fit_obs, n0, params, mask=erode(fit_obs[0].mask, max(int(opts.erode), 1)),
                                  lam=self.lam, model=self.model, bounds=opts.bounds, fixed=opts.fixed,
                                  max_iter=opts.max_iter, progress=say)

    def report(self):
        joint, obs, specs, names, n0 = self.joint, self.obs, self.specs, self.names, self.n0
        m = joint.mask
        report = {"images": [{"name": names[k], "light_dir": obs[k].light_dir.tolist(),
                              "irradiance": obs[k].irradiance, "holdout": specs[k].holdout}
                             for k in range(len(specs))],
                  "truth": next((o.meta.get("truth") for o in obs if o.meta.get("truth")), None),
                  "refine_normals": {"start": self.start, "smooth": self.lam, "pixels": int(m.sum()),
                                     "frame": "x image right, y image up, z towards the camera",
                                     "converged": joint.converged, "stop_reason": joint.stop_reason,
                                     "material_stage": joint.options.get("material_stage"),
                                     "energy": {"total": joint.loss, "data_chi2": joint.loss_terms["data_chi2"],
                                                "prior": joint.loss_terms["prior"]},
                                     "joint_history": joint.history, "time": time.time() - self.t_fit,
                                     "angle_change": _errors(joint.normals, n0, m), "outputs": self.files(),
                                     "angular_error": None if self.gt is None else {
                                         "before": _errors(n0, self.gt, m), "after": _errors(joint.normals, self.gt, m),
                                         "reference": "normal/normal_GT.npy"}},
                  "models": {self.model: {"params": joint.params, "uncertainty": None,
                                          "converged": joint.converged, "stop_reason": joint.stop_reason}}}
        unc = joint.uncertainty or {}
        if unc.get("calibrated"):
            # the material at refine_joint's weakened prior (lam_material), whose errors are calibrated
            report["models"][self.model]["uncertainty"] = unc
        elif unc.get("std_errors"):
            report["models"][self.model]["uncertainty_uncalibrated"] = dict(unc, note=UNCALIBRATED)
        report["reproduce"] = command_block(self.command)
        return report

    def write(self, report):
        files, joint, m = self.files(), self.joint, self.joint.mask
        np.save(files[1], joint.normals.astype(np.float32))
        self.wrote(files[1])
        plots.plot_normal_map(joint.normals, m, files[2], title=f"refined normals ({self.start} start)")
        self.wrote(files[2])
        plots.plot_change(self.n0, joint.normals, m, files[3], gt=self.gt)
        self.wrote(files[3])


UNCALIBRATED = ("curvature-based standard errors of the material with the normals free, estimated with a "
                "smoothness prior that biases it (see warning), so they are not reported as standard errors")
