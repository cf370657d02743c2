"""`fmbrdf-mi render --materials UV_LABELS` (issue 25): a built-in sphere of several materials is, inside each
material's pixels, the render of that material alone; the true label maps are written beside it (render grid and,
with --raw, the fit's super-pixel grid); bad options are one line."""
import numpy as np

from conftest import one_line_error

A = dict(eta=1.5, alpha=0.2)
B = dict(eta=1.8, alpha=0.4, beta=2.0)


def _uv(path):
    from fmbrdf_mi.fit.inputs.labels import write_labels

    lab = np.zeros((16, 32), int)
    lab[:, 16:] = 1           # u in [0.5, 1): material 1 (the sphere's pole faces the camera: u is the azimuth,
                              # so this is one half of the image; v >= 0.5 is the far hemisphere)
    write_labels(path, lab)


def test_render_is_each_material_inside_its_labels(tmp_path, capsys):
    """Same seed and sample count: on the pixels whose label and all 8 neighbours' labels are m (no pixel
    footprint reaches another material), the two-material render equals the render of material m alone
    (relative 1e-5: the blend weight there is exactly 0 or 1); both materials cover over 100 pixels; the raw
    label map is the 2 x 2 agreement of the render grid's."""
    from PIL import Image

    from fmbrdf_mi.cli import main
    from fmbrdf_mi.fit.evaluate.materials import check_labels
    from fmbrdf_mi.stokes_io import read_stokes_exr

    _uv(tmp_path / "uv.png")
    common = ["--variant", "llvm_ad_mono_polarized", "--res", "32", "--spp", "4", "--no-previews", "-q",
              "-D", "light_dir=-0.5,0.5,1"]
    assert main(["render", str(tmp_path / "two.exr"), "--materials", str(tmp_path / "uv.png"), "--raw",
                 *[x for k, v in A.items() for x in ("-D", f"{k}={v}")],
                 *[x for k, v in B.items() for x in ("-D", f"{k}_1={v}")], *common]) == 0
    for name, mat in (("a", A), ("b", dict(A, **B))):
        assert main(["render", str(tmp_path / f"{name}.exr"),
                     *[x for k, v in mat.items() for x in ("-D", f"{k}={v}")], *common]) == 0
    lab = np.asarray(Image.open(tmp_path / "two_labels.png")).astype(int)
    lab = np.where(lab == 255, -1, lab)
    raw = np.asarray(Image.open(tmp_path / "two_raw_labels.png")).astype(int)
    assert np.array_equal(np.where(raw == 255, -1, raw), check_labels(lab, (16, 16)))
    two = read_stokes_exr(str(tmp_path / "two.exr"))[0]
    pad = np.pad(lab, 1, constant_values=-1)
    for m, name in ((0, "a"), (1, "b")):
        inside = np.ones_like(lab, bool)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                inside &= pad[1 + dy:33 + dy, 1 + dx:33 + dx] == m
        one = read_stokes_exr(str(tmp_path / f"{name}.exr"))[0]
        assert inside.sum() > 100, (m, inside.sum())
        np.testing.assert_allclose(two[:3, inside], one[:3, inside], rtol=1e-5, atol=1e-7 * one[0].max())
    assert (lab == 0).sum() > 0 and (lab == 1).sum() > 0 and (lab == -1).sum() > 0


def test_bad_render_materials_are_one_line(tmp_path, capsys):
    from fmbrdf_mi.cli import main

    _uv(tmp_path / "uv.png")
    base = ["render", str(tmp_path / "o.exr"), "--variant", "llvm_ad_mono_polarized", "--res", "16", "--spp", "1"]
    rc = main(base + ["--materials", str(tmp_path / "uv.png"), "-D", "eta_2=1.7"])
    one_line_error(rc, capsys.readouterr().err, "render", "eta_2", "materials 0 .. 1")
    rc = main(base + ["--materials", str(tmp_path / "nope.png")])
    one_line_error(rc, capsys.readouterr().err, "render", "--materials", "no such file")
    rc = main(base + ["-D", "eta_1=1.7"])
    one_line_error(rc, capsys.readouterr().err, "render", "eta_1")
    assert not (tmp_path / "o.exr").exists()
