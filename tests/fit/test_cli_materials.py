"""`fmbrdf-mi fit --materials LABELS` (issue 25): a two-material sphere through the command, one image and a
manifest of several lights with per-pixel albedos; fit.json's materials block, materials.png, `--from`; bad
label files in one line with nothing written."""
import json

import numpy as np
import pytest

from conftest import figures_not_drawn, one_line_error

A = dict(eta=1.5, alpha=0.2, beta=1.0, kappa=10.0, k_s=0.8, r_k=0.5)
B = dict(eta=1.8, alpha=0.4, beta=2.0, kappa=20.0, k_s=0.5, r_k=1.2)
RES = 16


def _labels_png(path, labels):
    from fmbrdf_mi.fit.inputs.labels import write_labels

    write_labels(path, labels)
    return str(path)


def _raw(path, light, seed, exposure=None):
    from fmbrdf_mi.synthetic.spheres import half_labels, material_sphere
    from fmbrdf_mi.sensor.camera import CameraModel, capture

    cam = CameraModel()
    ideal = material_sphere([A, B], half_labels(RES), res=RES, light=light)
    cap = capture(ideal["stokes"], cam, exposure=exposure, peak_fraction=0.8, seed=seed)
    np.save(path, cap["raw"])
    return cam, cap["exposure"], ideal["labels"]


def test_command_fits_two_materials_and_reruns(tmp_path, capsys):
    """One raw capture of the two-material sphere with its labels as a PNG (a column marked 255, not fitted):
    each material's parameters within 4 standard errors of its truth (k_s is in image units), the materials block and materials.png
    written, the summary says so; `--from` gives the same numbers; a changed label file is refused by --from.
    (One start: the search for two materials is tested in tests/fit/test_api_fitting_materials.py.)"""
    from fmbrdf_mi.cli import main

    cam, _, lab = _raw(tmp_path / "raw.npy", (-0.5, 0.5, 1.0), seed=4)
    lab = lab.copy()
    lab[:, 3] = -1
    labels = _labels_png(tmp_path / "labels.png", lab)
    args = ["fit", str(tmp_path / "raw.npy"), "--sphere", "8,8,7", "--light=-0.5,0.5,1", "--conversion-gain",
            str(cam.conversion_gain), "--read-noise", "2.5", "--materials", labels, "--max-pixels", "0",
            "--intervals", "fisher", "--starts", "1", "-q"]
    with figures_not_drawn(keep=("materials.png",)):
        assert main(args + ["-o", str(tmp_path / "a")]) == 0
    out = capsys.readouterr().out
    assert "2 material(s)" in out and "eta[1]" in out and "materials.png" in out
    rep = json.loads((tmp_path / "a" / "fit.json").read_text())
    m = rep["models"]["fmbrdf"]
    blk = m["materials"]
    assert m["converged"] and blk["count"] == 2
    for k, truth in enumerate((A, B)):
        for name, v in truth.items():
            if name == "k_s":       # in image units (the irradiance is not given: k_s absorbs the exposure)
                continue
            got, se = blk["parameters"][k][name], blk["std_errors"][k][name]
            assert abs(got - v) < 4 * se, (k, name, got, v, se)
    assert (tmp_path / "a" / "materials.png").stat().st_size > 5000
    args_rec = rep["reproduce"]["arguments"]
    assert args_rec["materials"] == labels and labels in rep["reproduce"]["files_sha256"]
    with figures_not_drawn():
        assert main(["fit", "--from", str(tmp_path / "a" / "fit.json"), "-o", str(tmp_path / "b"), "-q"]) == 0
    rep_b = json.loads((tmp_path / "b" / "fit.json").read_text())
    assert rep_b["models"]["fmbrdf"]["params"] == m["params"]
    capsys.readouterr()
    _labels_png(tmp_path / "labels.png", np.zeros((RES, RES), int))
    rc = main(["fit", "--from", str(tmp_path / "a" / "fit.json"), "-o", str(tmp_path / "c")])
    one_line_error(rc, capsys.readouterr().err, "fit", "labels.png", "changed")
    assert not (tmp_path / "c").exists()


@pytest.mark.parametrize("albedo, relit", [("shared", 0.05), ("per-pixel", 0.2)])
def test_manifest_with_materials(tmp_path, capsys, albedo, relit, no_figures):
    """Two lights of the two-material sphere and a third held out, through a manifest with `--materials`
    (shared albedos per material, or per-pixel maps): each material's shape within 4 standard errors,
    materials.png (and the maps) written, the held-out light relit with each material's estimates to RMSE /
    mean below ``relit``.  Measured (this data): 0.022 shared; 0.11 per pixel, where each pixel's k_s from
    two lights is poorly determined away from the highlight (relative SE > 0.5 in 39 % of the pixels; 0.056
    with three lights fitted), so the per-pixel bound is loose: it catches a broken prediction, not a
    small bias.  (One start, as in :func:`test_command_fits_two_materials_and_reruns`.)"""
    from fmbrdf_mi.cli import main

    lights = [(-0.5, 0.5, 1.0), (0.29, 0.5, 0.82), (0.29, -0.5, 0.82)]
    lines = ["[defaults]", 'sphere = "8,8,7"']
    exposure = cam = lab = None
    for k, light in enumerate(lights):
        cam, exposure, lab = _raw(tmp_path / f"l{k}.npy", light, seed=20 + k, exposure=exposure)
        lines += ["[[image]]", f'input = "l{k}.npy"', f"light = {list(light)}"] + (["holdout = true"] if k == 2 else [])
    lines[2:2] = [f"conversion_gain = {cam.conversion_gain}", "read_noise = 2.5"]
    (tmp_path / "m.toml").write_text("\n".join(lines) + "\n")
    np.save(tmp_path / "labels.npy", lab)
    out = tmp_path / "fit"
    assert main(["fit", "--manifest", str(tmp_path / "m.toml"), "--materials", str(tmp_path / "labels.npy"),
                 "--albedo", albedo, "--max-pixels", "0", "--intervals", "fisher", "--starts", "1", "-o", str(out),
                 "-q"]) == 0
    text = capsys.readouterr().out
    assert "relighting l2" in text and "2 material(s)" in text and ("albedo maps:" in text) == (albedo != "shared")
    rep = json.loads((out / "fit.json").read_text())
    m = rep["models"]["fmbrdf"]
    assert m["converged"] and m["materials"]["count"] == 2
    for k, truth in enumerate((A, B)):
        got, se = m["materials"]["parameters"][k], m["materials"]["std_errors"][k]
        assert set(got) == ({"eta", "alpha", "beta", "kappa"} | ({"k_s", "r_k"} if albedo == "shared" else set()))
        for name in ("eta", "alpha", "beta", "kappa"):
            assert abs(got[name] - truth[name]) < 4 * se[name], (k, name, got, se)
    assert rep["relight"]["l2"]["fmbrdf"]["rel_rmse"] < relit, rep["relight"]
    maps = ("k_s.exr", "k_b.exr", "albedo_maps.png") if albedo != "shared" else ()
    for f in maps + ("materials.png", "relight_l2.png"):
        assert (out / f).is_file(), f
    assert str(tmp_path / "labels.npy") in rep["reproduce"]["files_sha256"]
    if albedo == "shared":      # the joint record reruns to the same numbers
        assert main(["fit", "--from", str(out / "fit.json"), "-o", str(tmp_path / "again"), "-q"]) == 0
        again = json.loads((tmp_path / "again" / "fit.json").read_text())["models"]["fmbrdf"]
        assert again["params"] == m["params"] and again["materials"] == m["materials"]
        assert (tmp_path / "again" / "materials.png").is_file()


@pytest.mark.parametrize("make, words", [
    (lambda p: _rgb_png(p), ["--materials", "one-channel PNG", "mode RGB"]),
    (lambda p: np.save(p.with_suffix(".npy"), np.zeros((5, 5), int)) or p.with_suffix(".npy"),
     ["materials", "shape (5, 5)", "(16, 16)"]),
    (lambda p: p.with_suffix(".txt"), ["--materials", "no such file"]),
])
def test_bad_label_files_are_one_line(tmp_path, capsys, make, words):
    from fmbrdf_mi.cli import main

    cam, _, _ = _raw(tmp_path / "raw.npy", (-0.5, 0.5, 1.0), seed=4)
    path = make(tmp_path / "labels.png") or (tmp_path / "labels.png")
    capsys.readouterr()
    rc = main(["fit", str(tmp_path / "raw.npy"), "--sphere", "8,8,7", "--light=-0.5,0.5,1", "--conversion-gain",
               str(cam.conversion_gain), "--read-noise", "2.5", "--materials", str(path), "-o", str(tmp_path / "o")])
    one_line_error(rc, capsys.readouterr().err, "fit", *words)
    assert not (tmp_path / "o").exists()


def _rgb_png(path):
    from PIL import Image

    Image.fromarray(np.zeros((RES, RES, 3), np.uint8)).save(path)
    return path
