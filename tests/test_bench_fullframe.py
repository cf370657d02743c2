"""The pure helpers of tools/bench_fullframe.py: frame sizes, the frame's textures and camera, the estimates'
comparison and the marginal cost per super-pixel."""
import math

import numpy as np
import pytest

import bench_fullframe as B
from bench_textured import texture
from fmbrdf_mi import geometry as G


def test_parse_frame():
    assert B.parse_frame("256") == (256, 256)
    assert B.parse_frame(" 1224x1024 ") == (1224, 1024)
    assert B.parse_frame("full") == (1224, 1024)
    for bad in ("abc", "4", "256x", "257x256", "0x0"):
        with pytest.raises(SystemExit, match="--sizes"):
            B.parse_frame(bad)


def test_parse_list():
    assert B.parse_list("lights", "3, 1,3", B.LIGHTS, int) == [3, 1]
    for bad in ("", "2", "x"):
        with pytest.raises(SystemExit, match="--lights"):
            B.parse_list("lights", bad, B.LIGHTS, int)


@pytest.mark.parametrize("name,theirs", [("smooth", "smooth"), ("checker", "high")])
def test_square_textures_are_bench_textured_ones(name, theirs):
    """On a square frame the textures are tools/bench_textured.py's (the docstring says so)."""
    for a, b in zip(B.frame_texture(name, 30, 30), texture(theirs, 30)):
        np.testing.assert_array_equal(a, b)


def test_checker_squares():
    ks, kb = B.frame_texture("checker", 12, 9)
    assert ks.shape == (9, 12)
    assert set(np.unique(ks)) == {0.4, 1.0} and set(np.unique(kb)) == {0.25, 0.55}
    assert ks[0, 0] == ks[2, 2] == 0.4 and ks[0, 3] == ks[3, 0] == 1.0 and ks[3, 3] == 0.4
    assert np.all((ks == 1.0) == (kb == 0.55))       # the bright squares of both maps coincide


def test_placement_centres_the_square():
    assert B.placement(1224, 1024) == (1024, 100, 0)
    assert B.placement(20, 30) == (20, 0, 5)


def test_frame_fov_keeps_the_square_rays():
    """The frame's perspective rays through the square are those of the square alone."""
    w, h = 40, 24
    side, ox, oy = B.placement(w, h)
    fov = B.frame_fov(side, w)
    assert G.focal_length(w, fov) == pytest.approx(G.focal_length(side, B.MESH_FOV), rel=1e-12)
    frame = G.pixel_rays((h, w), "perspective", fov)[oy:oy + side, ox:ox + side]
    np.testing.assert_allclose(frame, G.pixel_rays((side, side), "perspective", B.MESH_FOV), atol=1e-12)


@pytest.mark.parametrize("scene", ["sphere", "mesh"])
def test_ideal_frame_geometry_matches_its_maps(scene):
    """The frame's geometry (exact at any point) gives the normal map at the pixel centres, and the object's
    Stokes image is dark off the square."""
    w, h = 16, 12
    ideal = B.ideal_frame(scene, "smooth", w, h, (-0.5, 0.5, 1.0), area=1)
    assert ideal["stokes"].shape == (3, 2 * h, 2 * w) and ideal["mask"].shape == (h, w)
    side, ox, oy = B.placement(w, h)
    assert not ideal["mask"][:, :ox].any() and not ideal["mask"][:, ox + side:].any()
    assert not ideal["stokes"][:, :, :2 * ox].any() and not ideal["stokes"][:, :, 2 * (ox + side):].any()
    X, Y = G.pixel_centres((h, w))
    n, v = ideal["geometry"].at(X, Y)
    m = ideal["mask"]
    assert m.sum() > 10
    np.testing.assert_allclose(n[m], ideal["normals"][m], atol=1e-5)
    np.testing.assert_allclose(v, ideal["view_dirs"], atol=1e-6)


def test_map_summary_skips_unfitted_pixels():
    m = np.full((4, 5), np.nan)
    m[1, 1:4] = [1.0, 2.0, 2.0]
    s = B.map_summary(m)
    assert s["count"] == 3 and s["mean"] == pytest.approx(5 / 3) and s["rms"] == pytest.approx(math.sqrt(3))
    assert len(s["values"]) == 16 and s["values"][0] == 1.0 and s["values"][-1] == 2.0
    assert B.map_summary(np.full((2, 2), np.nan)) == {"count": 0}


def test_rel_diff():
    assert B.rel_diff(2.0, 2.0) == 0 and B.rel_diff(0.0, 0.0) == 0 and B.rel_diff(math.nan, math.nan) == 0
    assert B.rel_diff(1.0, 1.0 + 1e-6) == pytest.approx(1e-6 / (1 + 1e-6))
    assert B.rel_diff(-1.0, 1.0) == 2.0
    assert B.rel_diff(1.0, math.nan) == math.inf


def run(mode="cli", eta=1.5, pixels=100, time=1.0, cpu=1.0, peak=1e6, width=64, **extra):
    r = {"mode": mode, "scene": "sphere", "texture": "smooth", "K": 1, "width": width, "height": width, "area": 4,
         "seed": 0, "pixels": pixels, "time": time, "cpu": cpu, "peak": peak,
         "estimates": {"params": {"eta": eta, "kappa": 0.0},
                       "maps": {"k_s": {"count": pixels, "values": [0.5, 0.6]}}},
         "uncertainty": {"std_errors": {"eta": 0.01}}}
    r.update(extra)
    return r


def test_compare_runs():
    a = [run(), run(mode="api"), run(width=128)]
    b = [run(eta=1.5 * (1 + 3e-6)), run(mode="api")]
    rows, unmatched = B.compare_runs(a, b, 1e-6)
    assert unmatched == [B.label(a[2])]
    by = {r[0]: r for r in rows}
    key, diff, ok = by[B.label(a[0])][1], by[B.label(a[0])][2], by[B.label(a[0])][5]
    assert key == "params.eta" and diff == pytest.approx(3e-6, rel=1e-3) and not ok
    assert by[B.label(a[1])][2] == 0 and by[B.label(a[1])][5]
    assert B.compare_runs(a, b, 1e-5)[0][0][5]
    c = run()
    del c["estimates"]["maps"]["k_s"]["values"]
    rows, _ = B.compare_runs([run()], [c], 1.0)
    assert rows[0][2] == math.inf and not rows[0][5]        # a number in one file only


def test_main_compare_exit_status(tmp_path):
    import json

    for name, runs in (("a", [run()]), ("b", [run(eta=1.6)]), ("c", [run(width=32)])):
        (tmp_path / f"{name}.json").write_text(json.dumps({"header": "", "runs": runs}))
    assert B.main(["--compare", str(tmp_path / "a.json"), str(tmp_path / "a.json")]) == 0
    assert B.main(["--compare", str(tmp_path / "a.json"), str(tmp_path / "b.json")]) == 1
    assert B.main(["--compare", str(tmp_path / "a.json"), str(tmp_path / "c.json")]) == 2
    with pytest.raises(SystemExit, match="--compare"):
        B.main(["--compare", str(tmp_path / "a.json"), str(tmp_path / "missing.json")])


def test_cells_are_the_maps_pixels():
    """With K images ``pixels`` counts a super-pixel once per image; the fitted super-pixels are the map's."""
    r = run(pixels=300)
    r["estimates"]["maps"]["k_s"]["count"] = 110
    assert B.cells(r) == 110
    del r["estimates"]["maps"]["k_s"]
    assert B.cells(r) == 300


def test_marginals_of_a_linear_cost():
    """time = 2 s + 3 ms per super-pixel, peak = 0.5 GB + 10 kB per super-pixel: the marginals are 3 ms and
    10 kB whatever the fixed part; another case is not mixed in."""
    runs = [run(width=w, pixels=n, time=2 + 3e-3 * n, cpu=1 + 2e-3 * n, peak=5e8 + 1e4 * n)
            for w, n in ((512, 4000), (256, 1000), (1024, 16000))]
    runs.append(run(mode="api", width=256, pixels=1000, time=50.0))
    out = B.marginals(runs)
    assert [(n0, n1) for _, n0, n1, *_ in out] == [(1000, 4000), (4000, 16000)]
    for _, _, _, t, c, m in out:
        assert t == pytest.approx(3.0) and c == pytest.approx(2.0) and m == pytest.approx(10.0)
