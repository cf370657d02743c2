"""Several materials (``fit(..., materials=labels)``, issue 25): a two-material sphere is recovered with its
labels; with the camera noise known the fit of two materials is the two fits of each material's pixels
(the likelihood separates); one material is the ordinary fit; bad labels are refused in one line."""
import dataclasses

import numpy as np
import pytest

A = dict(eta=1.5, alpha=0.2, beta=1.0, kappa=10.0, k_s=0.8, r_k=0.5)
B = dict(eta=1.8, alpha=0.4, beta=2.0, kappa=20.0, k_s=0.5, r_k=1.2)
LIGHT = (-0.5, 0.5, 1.0)


def _ideal(res=16):
    from fmbrdf_mi.synthetic.spheres import half_labels, material_sphere

    return material_sphere([A, B], half_labels(res), res=res, light=LIGHT, area=2)


def _exact_observation(res=16):
    """The two-material sphere captured without noise or rounding: the raw samples are the model's exact
    values (2 x 2 points per raw pixel, as the fit models them), the camera's noise stated."""
    from fmbrdf_mi.synthetic.spheres import capture_observation
    from fmbrdf_mi.sensor import samples as SM
    from fmbrdf_mi.sensor.camera import CameraModel, intensity_at_each_pixel

    ideal = _ideal(res)
    cam = CameraModel(bits=16, full_well=1e6)
    obs, cap = capture_observation(ideal, cam, noiseless=True)
    exact = intensity_at_each_pixel(ideal["stokes"], cam.layout) * cap["exposure"] / cam.conversion_gain
    return dataclasses.replace(obs, samples=SM.from_raw(exact, cam.layout, 0.0, cam.white_level)), ideal["labels"]


def _noisy_observation(seed, res=16):
    from fmbrdf_mi.synthetic.spheres import capture_observation

    ideal = _ideal(res)
    return capture_observation(ideal, seed=seed)[0], ideal["labels"]


def test_material_sphere_is_each_material_on_its_pixels():
    """The synthetic two-material capture is, on each material's pixels, that material's one-material sphere
    (the test data are what they say)."""
    from fmbrdf_mi.synthetic.spheres import ideal_sphere

    ideal = _ideal()
    up = np.repeat(np.repeat(ideal["labels"], 2, 0), 2, 1)
    for m, p in enumerate((A, B)):
        one = ideal_sphere(p, res=16, light=LIGHT, area=2)["stokes"]
        assert np.array_equal(ideal["stokes"][:, up == m], one[:, up == m])
    assert ideal["labels"][0, 0] == 0 and ideal["labels"][0, -1] == 1


def test_noise_free_two_material_sphere_is_recovered():
    """Each material's shape parameters within 0.05 of their standard errors of the truth (the fit stops
    where the Gauss-Newton decrement is below 0.01, within ~0.1 SE) and within 0.1 %, its albedos within 1e-3
    (relative); the parameters' names and the materials block agree."""
    from fmbrdf_mi.fit import fit

    obs, lab = _exact_observation()
    res = fit(obs, materials=lab, max_pixels=None, intervals="fisher", progress=False, area_points=2, starts=1)
    assert res.converged
    blk = res.materials
    assert blk["count"] == 2 and sum(blk["pixels"]) == res.n_pixels and min(blk["pixels"]) >= 40
    for m, truth in enumerate((A, B)):
        got, se = blk["parameters"][m], blk["std_errors"][m]
        assert set(got) == set(truth)
        for k in ("eta", "alpha", "beta", "kappa"):
            assert abs(got[k] - truth[k]) < 0.05 * se[k] and abs(got[k] / truth[k] - 1) < 1e-3, (m, k, got, se)
        for k in ("k_s", "r_k"):
            assert abs(got[k] / truth[k] - 1) < 1e-3, (m, k, got)
        for k, v in got.items():
            assert res.params[f"{k}[{m}]"] == v
            assert blk["std_errors"][m][k] == res.std_errors[f"{k}[{m}]"] > 0
            lo, hi = blk["ci95"][m][k]
            assert lo < v < hi
    json = res.to_json()
    assert json["materials"]["parameters"][1]["eta"] == blk["parameters"][1]["eta"]


@pytest.mark.slow
def test_two_materials_are_the_fits_of_each_material_alone():
    """Known noise, per-material albedos: the likelihood is a sum of the two materials' terms with no
    unknown in common, so the two-material fit must equal the ordinary fits of each material's pixels (the
    other material's labelled -1): estimates within 0.15 standard errors (each fit stops within ~0.05 SE
    of its optimum), standard errors within 5 % (each is the Fisher information at its own fit's end, and
    kappa's, at a standard error of 25 %, changes that fast over those 0.15 SE: 2.5 % measured); and the truth within
    3.5 standard errors (6 parameters x 2 materials: a 3.5 SE miss has probability ~0.006 in all)."""
    from fmbrdf_mi.fit import fit

    for seed in (1,):
        obs, lab = _noisy_observation(seed)
        both = fit(obs, materials=lab, max_pixels=None, intervals="fisher", starts=1, progress=False)
        assert both.converged
        for m, truth in enumerate((A, B)):
            alone = fit(obs, materials=np.where(lab == m, 0, -1), max_pixels=None, intervals="fisher", starts=1,
                        progress=False)
            assert alone.converged and alone.n_pixels == both.materials["pixels"][m]
            got, se = both.materials["parameters"][m], both.materials["std_errors"][m]
            for k in truth:
                assert abs(got[k] - alone.params[k]) < 0.15 * alone.std_errors[k], (seed, m, k)
                assert abs(se[k] / alone.std_errors[k] - 1) < 0.05, (seed, m, k)
                assert abs(got[k] - truth[k]) < 3.5 * se[k], (seed, m, k, got[k], se[k])


def test_one_material_is_the_ordinary_fit():
    """Labels with one material (some pixels -1) give exactly the ordinary fit of the labelled pixels (the
    same path: equal numbers), with a materials block of one."""
    from fmbrdf_mi.fit import fit

    obs, lab = _noisy_observation(5)
    one = np.where(lab == 0, 0, -1)         # material A's half; B's not fitted
    got = fit(obs, materials=one, max_pixels=None, intervals="fisher", starts=1, progress=False)
    from fmbrdf_mi.fit.inputs.observations import erode

    # the labels select after the mask's erosion: the same pixels as the eroded mask cut by the labels
    ref = fit(dataclasses.replace(obs, mask=erode(obs.mask, 2) & (one >= 0)), erode=0, max_pixels=None,
              intervals="fisher", starts=1, progress=False)
    assert got.converged and got.n_pixels == ref.n_pixels
    assert got.params == ref.params and got.std_errors == ref.std_errors
    assert got.uncertainty["ci95"] == ref.uncertainty["ci95"]
    assert got.materials["count"] == 1 and got.materials["parameters"][0] == ref.params
    assert ref.materials is None


def test_raw_sensor_labels_are_taken_per_super_pixel():
    """Labels on the raw sensor's grid (2H, 2W): a super-pixel takes its 2 x 2 block's label when the four
    agree, else it is not fitted."""
    from fmbrdf_mi.fit.evaluate.materials import check_labels

    lab = np.zeros((4, 6), int)
    lab[:, 3:] = 1          # sensor column 3 splits super-pixel column 1
    lab[0, 0] = 2           # one sensor pixel of super-pixel (0, 0) differs
    got = check_labels(lab, (2, 3))
    assert got.tolist() == [[-1, -1, 1], [0, -1, 1]]
    assert check_labels(lab[::2, ::2], (2, 3)).tolist() == [[2, 0, 1], [0, 0, 1]]   # the fit's own grid


@pytest.mark.parametrize("labels, words", [
    (np.zeros((5, 5), int), ["materials", "shape (5, 5)", "(16, 16)", "(32, 32)"]),
    (np.full((16, 16), 0.5), ["materials", "integers"]),
    (np.full((16, 16), -1), ["materials", "no pixel has a label >= 0"]),
    ("two", ["materials", "shape ()"]),
])
def test_bad_labels_are_refused(labels, words):
    from fmbrdf_mi.fit import fit

    obs, _ = _exact_observation()
    with pytest.raises(ValueError) as e:
        fit(obs, materials=labels, progress=False)
    msg = str(e.value)
    assert "\n" not in msg and all(w in msg for w in words), msg


def test_a_material_without_enough_pixels_is_refused():
    """A label with no pixel (0 and 2 given, no 1) and a material with too few pixels for its own
    parameters (many small materials: M too large for the data) are refused, naming the label."""
    from fmbrdf_mi.fit import fit

    obs, lab = _exact_observation()
    with pytest.raises(ValueError, match=r"materials: label 1 has 0 fitted pixels, need at least 20"):
        fit(obs, materials=lab * 2, progress=False)
    many = (np.arange(16)[None, :] // 2) * np.ones((16, 1), int)    # 8 materials of ~10 pixels each
    with pytest.raises(ValueError, match=r"materials: label 0 has \d+ fitted pixels, need at least 20"):
        fit(obs, materials=many, progress=False)


def test_materials_need_the_likelihood():
    from fmbrdf_mi.fit import fit

    obs, lab = _exact_observation()
    with pytest.raises(ValueError, match="materials: needs the likelihood"):
        fit(obs, materials=lab, loss="paper", progress=False)


def test_noise_free_two_materials_with_pixel_albedos():
    """Per-pixel albedo maps with two materials: each material's shape within 0.1 % and every fitted pixel's
    k_b within 1e-3 (relative) of its material's k_s r_k; the model's options apply to every material: a
    fixed kappa holds kappa[0] and kappa[1] (no standard error), bounds and a start given by the model's
    names are accepted (each applies to every material)."""
    from fmbrdf_mi.fit import fit

    obs, lab = _exact_observation()
    res = fit(obs, materials=lab, albedo="per-pixel", max_pixels=None, intervals="fisher", progress=False,
              area_points=2, starts=1)
    assert res.converged and res.materials["count"] == 2
    for m, truth in enumerate((A, B)):
        got = res.materials["parameters"][m]
        assert set(got) == {"eta", "alpha", "beta", "kappa"}
        for k, v in got.items():
            assert abs(v / truth[k] - 1) < 1e-3, (m, k, got)
        f = np.isfinite(res.maps["k_b"]) & (lab == m)
        assert f.sum() > 30
        assert np.all(np.abs(res.maps["k_b"][f] / (truth["k_s"] * truth["r_k"]) - 1) < 1e-3)
    held = fit(obs, materials=lab, albedo="per-pixel", max_pixels=None, intervals="fisher", progress=False,
               init={k: A[k] for k in ("eta", "alpha", "beta", "kappa")}, fixed={"kappa": 15.0}, starts=1,
               bounds={"eta": (1.2, 2.5)})
    assert held.converged
    assert [p["kappa"] for p in held.materials["parameters"]] == [15.0, 15.0]
    assert all("kappa" not in se for se in held.materials["std_errors"])
