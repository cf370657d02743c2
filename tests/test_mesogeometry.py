"""The mesogeometry experiment's pieces: the rendered Oren-Nayar plane, the Lambert and Oren-Nayar fits, input errors."""
import math

import numpy as np
import pytest

from fmbrdf_mi import mesogeometry as M


def test_rendered_plane_matches_the_closed_form(variant):
    """A Mitsuba render (orthographic camera filled by the plane, directional light) against
    E cos(theta_L) f of an independent NumPy transcription of the paper's formulas (test_oren_nayar)."""
    from test_oren_nayar import ref_brdf

    ang = np.array([-70.0, -30.0, 0.0, 25.0, 30.0, 60.0])
    obs = M.render_oren_nayar_plane(0.5, 0.7, 30.0, ang, irradiance=2.0, res=8, spp=1)
    ti = math.radians(30.0)
    to = np.radians(np.abs(ang))
    dphi = np.where(ang >= 0, 0.0, math.pi)  # coplanar: same side as the light or opposite
    want = 2.0 * math.cos(ti) * ref_brdf(ti, to, dphi, 0.5, 0.7, "full")
    # uniform plane, no shadows: every pixel sees the same radiance; float32 rendering
    np.testing.assert_allclose(obs, want, rtol=1e-5)


def test_lambert_and_oren_nayar_fits_recover_their_own_data(variant):
    ang = np.arange(-75.0, 76.0, 15.0)
    on = M.oren_nayar_intensity(ang, 20.0, 0.45, 0.6)
    f = M.fit_oren_nayar(ang, on, 20.0)
    assert f.params["sigma"] == pytest.approx(0.45, rel=1e-4) and f.params["rho"] == pytest.approx(0.6, rel=1e-4)
    assert f.rmse < 1e-6
    lam = np.full(len(ang), 0.3 * math.cos(math.radians(20.0)) / math.pi)
    g = M.fit_lambert(ang, lam, 20.0)
    assert g.params["k"] == pytest.approx(0.3, rel=1e-12) and g.rmse < 1e-12
    # Lambert on Oren-Nayar data: its error is the relative spread of the data about their mean
    h = M.fit_lambert(ang, on, 20.0)
    assert h.rmse == pytest.approx(np.std(on) / np.mean(on), rel=1e-9)


@pytest.mark.parametrize("text,msg", [
    ("angle,value\n0,1\n", "header row naming"),
    ("camera_angle_deg,intensity\n0,1\n10,x\n", "must be numbers"),
    ("camera_angle_deg,intensity\n0,1\n10,1\n20,1\n", "at least 4"),
    ("camera_angle_deg,intensity\n0,1\n10,1\n20,1\n95,1\n", "within (-89, 89)"),
    ("camera_angle_deg,intensity\n0,1\n10,1\n20,-1\n30,1\n", "> 0"),
])
def test_bad_csv_gives_one_line(tmp_path, capsys, text, msg):
    from mesogeometry import main

    p = tmp_path / "in.csv"
    p.write_text(text)
    assert main(["--csv", str(p), "-o", str(tmp_path / "x.png")]) == 1
    err = capsys.readouterr().err.strip()
    assert msg in err and err.count("\n") == 0, err
    assert not (tmp_path / "x.png").exists()
