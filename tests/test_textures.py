"""Albedo textures on the built-in sphere (issue: textured objects): the true maps a textured render writes
are the albedos the renderer used (checked through the renderer itself), and the command's texture option."""
import numpy as np

from conftest import one_line_error


def _checker(path):
    from fmbrdf_mi.stokes_io import write_map_exr

    tex = np.where((np.arange(4)[:, None] + np.arange(8)[None]) % 2, 0.9, 0.3)
    write_map_exr(path, tex, force=True)


def test_true_maps_are_what_the_renderer_used(tmp_path):
    """A surface-only sphere (r_k = 0) with a k_s texture, head-on light, against the same sphere with
    k_s = 1 (same sample positions): their S0 ratio is the albedo each pixel saw, averaged over its area.
    true_albedo_maps (ray cast at the pixel centres) must match it to the texture's change within a pixel
    (measured: median 0.003, 90th percentile 0.009 for a bilinear 8 x 4 checker on a 48 px sphere)."""
    import mitsuba as mi

    mi.set_variant("llvm_ad_mono_polarized")
    import fmbrdf_mi
    from fmbrdf_mi import scene as S
    from fmbrdf_mi.fit.inputs.observations import erode

    fmbrdf_mi.register()
    _checker(tmp_path / "checker.exr")
    res = 48
    s0 = {}
    for name, ks in (("tex", S.texture_file_dict(tmp_path / "checker.exr")), ("one", 1.0)):
        mat = {"k_s": ks, "r_k": 0.0}
        sc = fmbrdf_mi.load_dict(S.sphere_scene(mat, resolution=res, spp=16, light_dir=(0, 0, 1)))
        s0[name] = S.render_stokes(sc, progress=False)[0, :, :, 0]
        if name == "tex":
            maps = S.true_albedo_maps(sc, mat)
    _, _, m = S.sphere_geometry(res)
    m = erode(m, 2) & (s0["one"] > 1e-3 * s0["one"].max())
    err = np.abs(s0["tex"][m] / s0["one"][m] - maps["k_s"][m])
    assert m.sum() > 600
    assert np.median(err) < 0.006 and np.percentile(err, 90) < 0.02, (np.median(err), np.percentile(err, 90))
    assert np.allclose(maps["k_b"], 0.0)
    assert 0.3 - 1e-6 <= maps["k_s"][m].min() and maps["k_s"][m].max() <= 0.9 + 1e-6


def test_render_writes_the_true_maps_beside_a_textured_capture(tmp_path, capsys):
    """`render -D k_s=FILE -D r_k=0.5 --raw`: OUT_k_s.exr, OUT_k_b.exr (k_b = r_k k_s) at the render's pixels
    and OUT_raw_k_*.exr on the super-pixel grid (2 x 2 means); a missing texture file and existing maps
    without --force are one-line errors."""
    import OpenEXR

    from fmbrdf_mi.cli import main

    _checker(tmp_path / "checker.exr")
    out = tmp_path / "out" / "t.exr"
    args = ["render", str(out), "--variant", "llvm_ad_mono_polarized", "-D", f"k_s={tmp_path / 'checker.exr'}",
            "-D", "r_k=0.5", "--res", "32", "--spp", "4", "--raw", "--no-previews", "-q"]
    assert main(args) == 0

    def read(name):
        with OpenEXR.File(str(tmp_path / "out" / name), separate_channels=True) as f:
            return np.asarray(f.channels()["Y"].pixels, dtype=np.float64)

    ks, kb, raw_ks = read("t_k_s.exr"), read("t_k_b.exr"), read("t_raw_k_s.exr")
    assert ks.shape == (32, 32) and raw_ks.shape == (16, 16)
    np.testing.assert_allclose(kb, 0.5 * ks, rtol=1e-6)
    np.testing.assert_allclose(raw_ks, ks.reshape(16, 2, 16, 2).mean(axis=(1, 3)), rtol=1e-6)
    capsys.readouterr()
    for name in ("t.exr", "t_raw.png", "t_raw.json"):     # only the maps are left: they alone are refused
        (tmp_path / "out" / name).unlink()
    one_line_error(main(args), capsys.readouterr().err, "render", "t_k_s.exr exists", "--force")
    assert not (tmp_path / "out" / "t.exr").exists()
    bad = ["render", str(tmp_path / "b.exr"), "-D", f"k_s={tmp_path / 'none.png'}", "-q"]
    one_line_error(main(bad), capsys.readouterr().err, "render", "k_s=", "no such texture file")
    assert not (tmp_path / "b.exr").exists()
