"""The label image of several materials when the user has none (``--materials auto:M``): :func:`find_materials`
clusters the per-pixel albedo fit's (k_s, k_b), free of the geometry, in units of their standard errors
(:func:`weighted_kmeans`, :func:`majority_filter`), then refines by hard EM on the model: each pixel to the
material of least :func:`material_chi2`, refit while labels change."""
from __future__ import annotations

import dataclasses
import time

import numpy as np

from fmbrdf_mi.fit.api.fitting import fit, progress_callable, usable_pixels
from fmbrdf_mi.fit.api.options import fit_options
from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.evaluate.models import get_model
from fmbrdf_mi.fit.evaluate.parameters import Parameters
from fmbrdf_mi.fit.evaluate.predict import predict_image
from fmbrdf_mi.fit.inputs.options import Option

#: A pixel is decided at this squared distance (noise units) to the nearest other material: 4 sd, error Phi(-2).
DECIDED_D = 16.0
#: Median chi^2 of 3 degrees of freedom (the per-pixel Stokes S0, S1, S2): the residuals' noise unit.
CHI2_3_MEDIAN = 2.3659738843753377
METHOD = ("per-pixel albedo fit (k_s, k_b in units of their standard errors) -> k-means (k-means++, 10 starts, "
          "fixed seed) -> 3x3 majority filter -> fit of M materials (refused unless separated), each pixel to "
          "the material of least chi^2, fitted again while labels change")


class MaterialsNotSeparated(InputError):
    """The clusters found do not separate into materials (the record says by how much)."""

    def __init__(self, message, record):
        super().__init__(message)
        self.record = record


@dataclasses.dataclass
class FoundMaterials:
    """``labels`` (H, W) 0 .. M-1, -1 not labelled; ``record``: fit.json's ``materials_found``; ``fit``: the
    last fit of M materials with these labels."""

    labels: np.ndarray
    record: dict
    fit: object = None


def parse_auto(value):
    """M of ``auto:M`` (``--materials auto:M``), None for anything else (a label file)."""
    if not isinstance(value, str) or not value.startswith("auto"):
        return None
    head, _, count = value.partition(":")
    if head != "auto" or not count.strip().isdigit() or not 2 <= int(count) <= 254:
        raise InputError(f"--materials {value}: expected auto:M with M an integer 2 .. 254 (the number of "
                         "materials to find), or a label image .png / .npy")
    return int(count)


def weighted_kmeans(x, w, count, seed=0, starts=10, max_iter=100):
    """k-means of ``x`` (n, F) with weights ``w`` (n, F) (1 / variance): distance sum_f w_f (x_f - c_f)^2;
    the best of ``starts`` k-means++ starts.  Returns (labels (n,), centres (count, F), total)."""
    x, w = np.asarray(x, dtype=np.float64), np.asarray(w, dtype=np.float64)
    n, rng, best = len(x), np.random.default_rng(seed), None

    def dist(c):
        return np.sum(w[:, None, :] * (x[:, None, :] - c[None, :, :]) ** 2, axis=-1)  # (n, count)

    for _ in range(starts):
        c = [x[rng.integers(n)]]
        for _ in range(1, count):
            d = dist(np.array(c)).min(axis=1)
            p = d / d.sum() if d.sum() > 0 else np.full(n, 1.0 / n)
            c.append(x[rng.choice(n, p=p)])
        c, lab = np.array(c), None
        for _ in range(max_iter):
            new = np.argmin(dist(c), axis=1)
            if lab is not None and np.array_equal(new, lab):
                break
            lab = new
            for k in range(count):
                sel = lab == k
                if sel.any():
                    c[k] = np.sum(w[sel] * x[sel], axis=0) / np.sum(w[sel], axis=0)
        total = float(np.sum(dist(c)[np.arange(n), lab]))
        if best is None or total < best[2]:
            best = (lab.copy(), c.copy(), total)
    return best


def majority_filter(labels, count, passes=1):
    """Each labelled pixel takes its 3 x 3 neighbourhood's most frequent label (a tie keeps its own)."""
    lab = np.asarray(labels).copy()
    for _ in range(passes):
        win = np.lib.stride_tricks.sliding_window_view(np.pad(lab, 1, constant_values=-1), (3, 3))
        votes = np.stack([np.sum(win == m, axis=(2, 3)) for m in range(count)])    # (count, h, w)
        own = np.take_along_axis(votes, np.clip(lab, 0, None)[None], 0)[0]
        new = np.where(own == votes.max(axis=0), lab, np.argmax(votes, axis=0))
        lab = np.where(lab >= 0, new, -1)
    return lab


def material_chi2(obs, model, params, count, idx):
    """(chi2 (count, n) of the S0, S1, S2 residuals, pred (count, 3, n) over the noise sd, the 3 noise scales)
    of each material at pixels ``idx``; each component's variance is scaled so the best material's median
    chi^2 is that of 3 dof (the noise model is trusted for its shape only)."""
    obs_s = np.asarray(obs.stokes, dtype=np.float64).reshape(3, -1)[:, idx]
    if obs.lin_variance is not None:
        lin = np.asarray(obs.lin_variance, dtype=np.float64).ravel()[idx]
        var = np.stack([0.5 * lin, lin, lin])
    else:
        s0 = np.abs(obs_s[0])
        var = np.repeat((s0 + 0.01 * np.median(s0))[None], 3, axis=0)
    var = np.maximum(var, 1e-12 * np.max(var))
    pred = np.stack([predict_image(model, pm, obs, idx).reshape(3, -1)[:, idx]
                     for pm in Parameters(get_model(model), materials=count).per_material(params)])
    r2 = (obs_s[None] - pred) ** 2 / var[None]
    best = np.argmin(r2.sum(axis=1), axis=0)
    own = r2[best, :, np.arange(len(idx))].T                 # (3, n)
    scale = np.maximum(np.median(own, axis=1), 1e-300) / (CHI2_3_MEDIAN / 3.0)  # per Stokes component
    sd = np.sqrt(var * scale[:, None])
    return (r2 / scale[None, :, None]).sum(axis=1), pred / sd[None], scale


def separation(pred, labels_flat, count):
    """Per material: the fraction of its pixels decided (D >= DECIDED_D) and the median D, the squared
    noise-unit distance between the own material's predicted Stokes and the nearest other's.  D compares
    models, not residuals, so noise cannot inflate it for identical materials."""
    n = pred.shape[2]
    own = pred[labels_flat, :, np.arange(n)]                 # (n, 3)
    d = np.sum((pred - own.T[None]) ** 2, axis=1)            # (count, n)
    d[labels_flat, np.arange(n)] = np.inf
    dist = [d.min(axis=0)[labels_flat == m] for m in range(count)]
    return ([float(np.mean(x >= DECIDED_D)) if len(x) else 0.0 for x in dist],
            [float(np.median(x)) if len(x) else 0.0 for x in dist])


def find_materials(obs, count, options=None, *, seed=0, rounds=2, clean=1, min_decided=0.5, progress=False,
                   **kw):
    """A :class:`FoundMaterials` of ``count`` materials for one mono :class:`Observation` (``options`` / ``kw``:
    its fits' options; ``rounds``: most fits of M materials; ``clean``: majority-filter passes); raises
    :class:`MaterialsNotSeparated` unless a ``min_decided`` fraction of each material's pixels is decided."""
    if isinstance(obs, (list, tuple)):
        raise InputError("find_materials: one image (an Observation); several images are not supported yet")
    count = Option("count", kind="int", lo=2, hi=254).check(count, "find_materials: count")
    Option("min_decided", kind="number", lo=0.0, lo_open=True, hi=1.0).check(min_decided,
                                                                            "find_materials: min_decided")
    opts = dataclasses.replace(fit_options(options, **kw), albedo="shared", intervals="fisher")
    report, t0, (h, w) = progress_callable(progress), time.perf_counter(), obs.shape

    def say(msg):
        report(f"find materials: {msg} ({time.perf_counter() - t0:.0f} s)")

    idx = np.asarray(usable_pixels(obs, dataclasses.replace(opts, max_pixels=None)))
    if len(idx) < 9 * count:
        raise InputError(f"--materials auto:{count}: {len(idx)} usable pixels, too few to find {count} materials "
                         f"(at least {9 * count})")
    say(f"per-pixel albedo fit of {len(idx)} pixels")
    pp = fit(obs, dataclasses.replace(opts, albedo="per-pixel", max_pixels=None), progress=False)
    feats, ses = (np.stack([pp.maps[k].ravel() for k in keys], axis=1) for keys in (("k_s", "k_b"),
                                                                                    ("k_s_se", "k_b_se")))
    ok = np.all(np.isfinite(feats) & np.isfinite(ses) & (ses > 0), axis=1)
    have = np.intersect1d(idx, np.flatnonzero(ok))
    if len(have) < 9 * count:
        raise InputError(f"--materials auto:{count}: only {len(have)} pixels have per-pixel albedos with standard "
                         f"errors, too few to find {count} materials")
    floor = np.median(ses[have], axis=0) * 1e-3          # a pixel with an SE near 0 must not dominate
    wts = 1.0 / np.maximum(ses[have], floor) ** 2
    lab = np.full(h * w, -1)
    lab[have], centres, _ = weighted_kmeans(feats[have], wts, count, seed=seed)
    lab = majority_filter(lab.reshape(h, w), count, clean).ravel()
    kmeans = {"centres": {"k_s": centres[:, 0].tolist(), "k_b": centres[:, 1].tolist()},
              "pixels": [int(np.sum(lab == m)) for m in range(count)]}
    say(f"k-means: {kmeans['pixels']} pixels, k_b centres {np.round(centres[:, 1], 4).tolist()}")
    record = {"method": METHOD, "count": count, "seed": int(seed), "features": ["k_s", "k_b"],
              "clean_passes": int(clean), "kmeans": kmeans, "rounds": [],
              "decided_distance": DECIDED_D, "min_decided": float(min_decided),
              "per_pixel_fit_shape": dict(pp.params)}
    for r in range(rounds):
        missing = [m for m in range(count) if not np.any(lab == m)]
        if missing:
            record.update(separated=False, pixels=[int(np.sum(lab == m)) for m in range(count)],
                          seconds=time.perf_counter() - t0)
            raise MaterialsNotSeparated(f"--materials auto:{count}: material(s) {missing} ended with no pixels: "
                                        f"the image does not show {count} separable materials", record)
        res = fit(obs, opts, materials=lab.reshape(h, w), progress=False)
        chi2, pred, scale = material_chi2(obs, opts.model, res.params, count, idx)
        frac, med = separation(pred, lab[idx], count)
        separated = min(frac) >= min_decided
        new = np.full(h * w, -1)
        new[idx] = np.argmin(chi2, axis=0)
        new = majority_filter(new.reshape(h, w), count, clean).ravel()
        changed = int(np.sum(new[idx] != lab[idx]))
        record["rounds"].append({"round": r + 1, "decided_fraction": frac, "median_distance": med,
                                 "changed_pixels": changed if separated else None})
        record.update(separated=separated, decided_fraction=frac, median_distance=med,
                      pixels=[int(np.sum(lab == m)) for m in range(count)],
                      noise_scale=[float(np.sqrt(x)) for x in scale],  # the residuals' sd / the assumed noise sd
                      seconds=time.perf_counter() - t0)
        say(f"fit {r + 1}: decided pixels per material {[round(f, 3) for f in frac]} (need {min_decided:g} "
            f"each), median distance to the nearest other material {[round(x, 1) for x in med]} (noise units "
            f"squared)" + (f"; {changed} pixel(s) would change material" if separated else ""))
        if not separated:
            raise MaterialsNotSeparated(
                f"--materials auto:{count}: the {count} clusters found are not separated materials: the fraction "
                f"of each one's pixels where its fitted material and the nearest other predict Stokes values at "
                f"least {np.sqrt(DECIDED_D):g} noise sd apart is {', '.join(f'{f:.0%}' for f in frac)} (needs "
                f"{min_decided:.0%} each): the materials look alike at each pixel (give a label image, or fewer "
                f"materials)", record)
        if changed == 0 or r == rounds - 1:
            break      # keep the last fit's labels (its separation is the one recorded)
        lab = new
    return FoundMaterials(lab.reshape(h, w), record, res)
