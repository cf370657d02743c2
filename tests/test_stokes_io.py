"""Stokes EXR round trip, derived quantities and polarisation-camera algebra."""
import numpy as np
import pytest

from fmbrdf_mi import stokes_io
from fmbrdf_mi.sensor import mosaic


def _random_stokes(rng, h=5, w=7, c=3):
    s0 = rng.uniform(0.1, 2.0, (h, w, c))
    d = rng.uniform(0, 1, (h, w, c))
    psi = rng.uniform(-np.pi / 2, np.pi / 2, (h, w, c))
    return np.stack([s0, s0 * d * np.cos(2 * psi), s0 * d * np.sin(2 * psi),
                     np.zeros_like(s0)]).astype(np.float32), d, psi


@pytest.mark.parametrize("c", [1, 3])
def test_exr_round_trip_is_exact(tmp_path, c):
    s, _, _ = _random_stokes(np.random.default_rng(c), c=c)
    s[3] = 1e-3 * s[0]
    meta = {"eta": 1.5, "light": [0.1, 0.2, 0.97]}
    p = tmp_path / "x.exr"
    stokes_io.write_stokes_exr(p, s, meta)
    back, m = stokes_io.read_stokes_exr(p)
    assert back.dtype == np.float32 and back.shape == s.shape
    assert np.array_equal(back, s)
    assert m == meta


def test_exr_channels_readable_by_plain_openexr(tmp_path):
    import OpenEXR
    s, _, _ = _random_stokes(np.random.default_rng(0))
    p = tmp_path / "x.exr"
    stokes_io.write_stokes_exr(p, s)
    with OpenEXR.File(str(p), separate_channels=True) as f:
        ch = f.channels()
        assert set(ch) == {f"S{k}.{x}" for k in range(4) for x in "RGB"}
        assert np.array_equal(ch["S2.G"].pixels, s[2, :, :, 1])


def test_exr_refuses_overwrite_and_bad_files(tmp_path):
    s, _, _ = _random_stokes(np.random.default_rng(0))
    p = tmp_path / "x.exr"
    stokes_io.write_stokes_exr(p, s)
    with pytest.raises(FileExistsError, match="force"):
        stokes_io.write_stokes_exr(p, s)
    stokes_io.write_stokes_exr(p, 2 * s, force=True)
    assert np.array_equal(stokes_io.read_stokes_exr(p)[0], 2 * s)
    with pytest.raises(stokes_io.StokesFileError, match="no such file"):
        stokes_io.read_stokes_exr(tmp_path / "missing.exr")
    (tmp_path / "bad.exr").write_bytes(b"not an exr")
    with pytest.raises(stokes_io.StokesFileError, match="not a readable EXR"):
        stokes_io.read_stokes_exr(tmp_path / "bad.exr")
    with pytest.raises(ValueError, match=r"\(4, H, W, C\)"):
        stokes_io.write_stokes_exr(tmp_path / "y.exr", s[:3])


def test_dolp_aolp_recover_construction():
    s, d, psi = _random_stokes(np.random.default_rng(1))
    assert np.allclose(stokes_io.dolp(s), d, atol=1e-5)
    # AoLP is defined modulo pi
    diff = np.angle(np.exp(2j * (stokes_io.aolp(s) - psi))) / 2
    assert np.abs(diff[d > 1e-3]).max() < 1e-4


def test_angle_images_follow_malus_law():
    s, d, psi = _random_stokes(np.random.default_rng(2))
    imgs = mosaic.angle_images_from_stokes(s)
    for k, a in enumerate(mosaic.ANGLES):
        t = np.deg2rad(a)
        malus = s[0] * ((1 - d) / 2 + d * np.cos(t - psi) ** 2)
        assert np.allclose(imgs[k], malus, rtol=1e-5, atol=1e-6)


def test_mosaic_to_angles_to_stokes_is_exact():
    rng = np.random.default_rng(3)
    s, _, _ = _random_stokes(rng, h=6, w=4, c=1)
    imgs = mosaic.angle_images_from_stokes(s.astype(np.float64))[..., 0]
    for layout in (mosaic.IMX250MZR_LAYOUT, ((0, 45), (135, 90))):
        raw = mosaic.mosaic_from_angle_images(imgs, layout)
        assert raw.shape == (12, 8)
        assert raw[0, 0] == imgs[mosaic.ANGLES.index(layout[0][0]), 0, 0]
        back = mosaic.angle_images_from_mosaic(raw, layout)
        assert np.array_equal(back, imgs)
        st = mosaic.stokes_from_angle_images(back)
        assert np.allclose(st[:3], s[:3, ..., 0], rtol=0, atol=1e-12)
    # 16-bit integer mosaics survive unchanged
    raw16 = rng.integers(0, 65535, (8, 10), dtype=np.uint16)
    assert np.array_equal(mosaic.mosaic_from_angle_images(mosaic.angle_images_from_mosaic(raw16)), raw16)


def test_mosaic_rejects_bad_shapes():
    with pytest.raises(ValueError, match="even height and width"):
        mosaic.angle_images_from_mosaic(np.zeros((5, 4)))
    with pytest.raises(ValueError, match="layout"):
        mosaic.angle_images_from_mosaic(np.zeros((4, 4)), ((0, 0), (90, 135)))
    with pytest.raises(ValueError, match="images"):
        mosaic.stokes_from_angle_images(np.zeros((3, 2, 2)))
