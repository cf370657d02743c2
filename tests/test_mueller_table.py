"""Mueller BRDF tables: the SCATMECH/NIST layout, the plain table, and the Stokes basis conversion.

References independent of the code under test: the closed-form Fresnel
amplitudes and a Jones-to-Mueller construction written here from SCATMECH's
documented Stokes convention (S1 = |Es|^2 - |Ep|^2, S2 = 2 Re(Es* Ep),
S3 = 2 Im(Es* Ep)); Mitsuba's ``mi.mueller.stokes_basis``,
``rotate_mueller_basis`` and ``specular_reflection``.
"""

import numpy as np
import pytest

from fmbrdf_mi.brdf_fit import mueller as T

D = np.diag([1.0, 1.0, 1.0, -1.0])


@pytest.fixture
def mi_pol():
    import mitsuba as mi

    before = mi.variant()
    mi.set_variant("scalar_spectral_polarized")
    yield mi
    if before is not None:
        mi.set_variant(before)


def _m(M):
    return np.array([[M[i, j] for j in range(4)] for i in range(4)], dtype=np.float64)


def stokes(E):
    Es, Ep = E
    z = np.conj(Es) * Ep
    return np.array([abs(Es) ** 2 + abs(Ep) ** 2, abs(Es) ** 2 - abs(Ep) ** 2, 2 * z.real, 2 * z.imag])


def jones_to_mueller(J):
    """The Mueller matrix of Jones matrix J, from four probe fields and SCATMECH's Stokes convention."""
    probes = [np.array(v, complex) for v in ([1, 0], [0, 1], [1 / np.sqrt(2), 1 / np.sqrt(2)],
                                             [1 / np.sqrt(2), 1j / np.sqrt(2)])]
    S_in = np.array([stokes(e) for e in probes]).T
    S_out = np.array([stokes(J @ e) for e in probes]).T
    return S_out @ np.linalg.inv(S_in)


def fresnel(cos_i, N):
    """Reflection amplitudes (r_s, r_p) in the {s, p, k} bases with p = k x s (r_p = -r_s at normal incidence)."""
    cos_t = np.sqrt(1 - (1 - cos_i ** 2) / N ** 2 + 0j)
    return (cos_i - N * cos_t) / (cos_i + N * cos_t), (N * cos_i - cos_t) / (N * cos_i + cos_t)


def random_mueller(rng, n):
    """Physical Mueller matrices: sums of three Jones-derived (non-depolarising) ones with random weights."""
    out = np.zeros((n, 4, 4))
    for k in range(n):
        for _ in range(3):
            J = rng.normal(size=(2, 2)) + 1j * rng.normal(size=(2, 2))
            out[k] += rng.uniform(0.1, 1) * jones_to_mueller(J)
    return out


def random_dirs(rng, n):
    t = np.radians(rng.uniform(1, 85, n))
    p = rng.uniform(0, 2 * np.pi, n)
    return np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=1)


def test_stokes_basis_is_mitsubas(mi_pol):
    rng = np.random.default_rng(1)
    k = np.concatenate([random_dirs(rng, 20), -random_dirs(rng, 20)])
    ours = T.stokes_basis(k)
    for kk, x in zip(k, ours):
        np.testing.assert_allclose(np.array(mi_pol.mueller.stokes_basis(mi_pol.Vector3f(*kk))), x, atol=2e-6)


def test_conversion_is_mitsubas_rotate_mueller_basis(mi_pol):
    """sp_to_package = rotate_mueller_basis(D M D, -w_in, s_in -> stokes_basis, w_out, s_out -> stokes_basis)."""
    mi = mi_pol
    rng = np.random.default_rng(2)
    w_in, w_out = random_dirs(rng, 12), random_dirs(rng, 12)
    M = rng.normal(size=(12, 4, 4))
    ours = T.sp_to_package(M, w_in, w_out)
    for k in range(12):
        ki, ko = -w_in[k], w_out[k]
        si = np.cross([0, 0, 1.0], ki)
        so = np.cross([0, 0, 1.0], ko)
        si, so = si / np.linalg.norm(si), so / np.linalg.norm(so)
        V = mi.Vector3f
        ref = mi.mueller.rotate_mueller_basis(mi.Matrix4f(D @ M[k] @ D), V(*ki), V(*si),
                                              mi.mueller.stokes_basis(V(*ki)), V(*ko), V(*so),
                                              mi.mueller.stokes_basis(V(*ko)))
        np.testing.assert_allclose(_m(ref), ours[k], atol=2e-5)
    np.testing.assert_allclose(T.package_to_sp(ours, w_in, w_out), M, atol=1e-12)


def test_metal_reflection_fixes_the_sign_of_s3(mi_pol):
    """A metal's reflection from its Jones matrix in SCATMECH's convention, converted, is Mitsuba's own
    specular_reflection in Mitsuba's bases (its M23 = -M32 pins the sign of S3)."""
    mi = mi_pol
    N = 0.2 + 3.0j
    for th, ph in ((35.0, 0.0), (60.0, 130.0), (10.0, 250.0)):
        w_in = T.directions(np.array([th]), np.array([ph]))
        w_out = w_in * np.array([-1, -1, 1])           # the mirror direction
        rs, rp = fresnel(np.cos(np.radians(th)), N)
        M_sp = jones_to_mueller(np.diag([rs, rp]))
        assert abs(M_sp[2, 3]) > 0.01                      # a real linear-circular coupling
        ours = T.sp_to_package(M_sp[None], w_in, w_out)[0]
        F = mi.mueller.specular_reflection(mi.Float(np.cos(np.radians(th))), mi.Complex2f(N.real, N.imag))
        V = mi.Vector3f
        ki, ko = -w_in[0], w_out[0]
        si, so = np.cross([0, 0, 1.0], ki), np.cross([0, 0, 1.0], ko)
        ref = mi.mueller.rotate_mueller_basis(F, V(*ki), V(*(si / np.linalg.norm(si))), mi.mueller.stokes_basis(V(*ki)),
                                              V(*ko), V(*(so / np.linalg.norm(so))), mi.mueller.stokes_basis(V(*ko)))
        np.testing.assert_allclose(ours, _m(ref), atol=2e-6)


def _write_rows(path, rows, header=None):
    with open(path, "w") as f:
        f.write((header or ",".join(T.SCATMECH_COLUMNS)) + "\n")
        for r in rows:
            f.write(",".join(repr(float(v)) for v in r) + "\n")


def _dielectric_rows(n=1.5):
    """SCATMECH rows of the specular reflection of a dielectric (Mueller from the closed-form amplitudes), in
    several planes of incidence, written in SCATMECH's angles: the source at (thetai, phi), the viewer at
    the mirror direction."""
    rows, geo = [], []
    for th, ph in ((30.0, 0.0), (-50.0, 0.0), (45.0, 70.0), (70.0, 200.0), (20.0, 300.0)):
        rs, rp = fresnel(np.cos(np.radians(abs(th))), n)
        M = jones_to_mueller(np.diag([rs, rp]))
        f11 = M[0, 0]
        t_out, p_out = -th, ph                      # the mirror of (th, ph)
        rows.append([0.633, th, ph, t_out, p_out, f11 * 1e3] + list((M / f11).ravel()[1:]))
        geo.append((th, ph, t_out, p_out, M))
    return rows, geo


def test_dielectric_specular_reflection_reads_s_polarised(tmp_path):
    path = tmp_path / "fresnel.csv"
    rows, geo = _dielectric_rows()
    _write_rows(path, rows)
    tab = T.read_scatmech(path)
    assert len(tab) == len(rows)
    for k, (th, ph, t_out, p_out, M) in enumerate(geo):
        w_in, w_out = T.directions(th, ph), T.directions(t_out, p_out)
        np.testing.assert_allclose(tab.w_in[k], w_in, atol=1e-12)
        np.testing.assert_allclose(tab.w_out[k], w_out, atol=1e-12)
        np.testing.assert_allclose(w_out, w_in * [-1, -1, 1], atol=1e-12)   # specular
        S = tab.mueller[k] @ np.array([1.0, 0, 0, 0])
        assert np.hypot(S[1], S[2]) / S[0] > 0.05
        chi = 0.5 * np.arctan2(S[2], S[1])
        x = T.stokes_basis(w_out)
        y = np.cross(w_out, x)
        e = np.cos(chi) * x + np.sin(chi) * y                 # the direction of the electric field
        s_out = np.cross([0, 0, 1.0], w_out)
        s_out /= np.linalg.norm(s_out)
        assert abs(e @ s_out) == pytest.approx(1.0, abs=1e-9)  # perpendicular to the plane of incidence
        assert np.isclose(tab.mueller[k, 0, 0], 1e3 * M[0, 0])


def test_scatmech_table_reads_back_exactly(tmp_path, mi_pol):
    """A table written by hand in SCATMECH's bases from a known Mueller BRDF (here a generic matrix per row)
    reads back as that BRDF in Mitsuba's bases, and writes back the same numbers."""
    mi = mi_pol
    rng = np.random.default_rng(3)
    n = 25
    th_i, ph_i = rng.uniform(-80, 80, n), rng.uniform(-360, 360, n)
    th_o, ph_o = rng.uniform(-80, 80, n), rng.uniform(0, 360, n)
    Mn = random_mueller(rng, n)
    Mn /= Mn[:, :1, :1]
    f11 = rng.uniform(0.01, 30, n)
    wl = np.where(np.arange(n) < 12, 0.532, 0.633)
    rows = np.column_stack([wl, th_i, ph_i, th_o, ph_o, f11, Mn.reshape(n, 16)[:, 1:]])
    path = tmp_path / "t.csv"
    _write_rows(path, rows, header="lambda thetai phi thetar phir BRDF " + " ".join(T.SCATMECH_COLUMNS[6:]))
    # blank-separated header, comma-separated rows: not one layout, refused
    with pytest.raises(T.MuellerTableError):
        T.read_scatmech(path)
    _write_rows(path, rows)
    tab = T.read_table(path)
    assert tab.kind == "scatmech" and tab.wavelengths() == [0.532, 0.633]
    assert len(tab.at_wavelength(0.633)) == n - 12
    for k in range(n):
        ki = -T.directions(th_i[k], ph_i[k])
        ko = T.directions(th_o[k], ph_o[k])
        si, so = np.cross([0, 0, 1.0], ki), np.cross([0, 0, 1.0], ko)
        V = mi.Vector3f
        ref = mi.mueller.rotate_mueller_basis(mi.Matrix4f(D @ (f11[k] * Mn[k]) @ D), V(*ki),
                                              V(*(si / np.linalg.norm(si))), mi.mueller.stokes_basis(V(*ki)),
                                              V(*ko), V(*(so / np.linalg.norm(so))), mi.mueller.stokes_basis(V(*ko)))
        np.testing.assert_allclose(tab.mueller[k], _m(ref), rtol=2e-5, atol=2e-5 * f11[k])
    out = tmp_path / "back.csv"
    T.write_scatmech(out, tab.w_in, tab.w_out, tab.mueller, tab.wavelength)
    back = T.read_scatmech(out)
    np.testing.assert_allclose(back.mueller, tab.mueller, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(back.w_in, tab.w_in, atol=1e-12)


@pytest.mark.parametrize("name", ["plain.npz", "plain.csv"])
def test_plain_table_round_trip(tmp_path, name):
    rng = np.random.default_rng(4)
    n = 10
    w_in, w_out = random_dirs(rng, n), random_dirs(rng, n)
    M = random_mueller(rng, n)
    T.write_plain(tmp_path / name, w_in, w_out, M, 0.55)
    tab = T.read_table(tmp_path / name)
    assert tab.kind == "plain" and tab.wavelengths() == [0.55]
    np.testing.assert_array_equal(tab.mueller, M)
    np.testing.assert_allclose(tab.w_in, w_in, atol=1e-15)


def test_plain_csv_angles(tmp_path):
    path = tmp_path / "a.csv"
    M = np.eye(4) * 0.2
    with open(path, "w") as f:
        f.write("theta_in,phi_in,theta_out,phi_out," + ",".join(T.PLAIN_MUELLER) + "\n")
        f.write("-30,0,45,90," + ",".join(repr(float(v)) for v in M.ravel()) + "\n")
    tab = T.read_table(path)
    np.testing.assert_allclose(tab.w_in[0], [-0.5, 0, np.sqrt(0.75)], atol=1e-12)
    np.testing.assert_allclose(tab.w_out[0], [0, np.sqrt(0.5), np.sqrt(0.5)], atol=1e-12)
    assert np.isnan(tab.wavelengths()[0])


GOOD = [0.633, 30, 0, 20, 10, 0.5] + [0.0] * 15


def _bad(tmp_path, rows, header=None):
    path = tmp_path / "bad.csv"
    _write_rows(path, rows, header)
    with pytest.raises(T.MuellerTableError) as e:
        T.read_table(path)
    msg = str(e.value)
    assert "\n" not in msg and str(path) in msg
    return msg


@pytest.mark.parametrize("change, row, column", [
    (lambda r: r.__setitem__(5, float("nan")), 3, "f_r11"),
    (lambda r: r.__setitem__(1, 95.0), 3, "thetai"),
    (lambda r: r.__setitem__(3, -90.0), 3, "thetar"),
    (lambda r: r.__setitem__(4, 400.0), 3, "phir"),
    (lambda r: r.__setitem__(0, 0.0), 3, "lambda"),
    (lambda r: r.__setitem__(5, -1.0), 3, "f_r11"),
    (lambda r: r.__setitem__(6 + 4, 1.4), 3, "m22"),                      # |m22| > 1
    (lambda r: (r.__setitem__(6, 0.8), r.__setitem__(7, 0.8)), 3, "m12"),  # diattenuation > 1
])
def test_bad_rows(tmp_path, change, row, column):
    bad = list(GOOD)
    change(bad)
    msg = _bad(tmp_path, [GOOD, bad])
    assert f"row {row}, column {column}" in msg, msg


def test_bad_layouts(tmp_path):
    assert "row 3, column m44" in _bad(tmp_path, [GOOD, GOOD[:-1]])
    assert "row 2, column 22 (extra)" in _bad(tmp_path, [GOOD + [1.0]])
    assert "row 1, column 20" in _bad(tmp_path, [GOOD[:-1]], header=",".join(T.SCATMECH_COLUMNS[:-1]))
    path = tmp_path / "x.csv"
    with open(path, "w") as f:
        f.write(",".join(T.SCATMECH_COLUMNS) + "\n0.6,abc" + ",0" * 19 + "\n,30,0,20,10,0.5" + ",0" * 15 + "\n")
    with pytest.raises(T.MuellerTableError, match=r"row 2, column thetai: 'abc' is not a number"):
        T.read_table(path)
    with open(path, "w") as f:
        f.write(",".join(T.SCATMECH_COLUMNS) + "\n,30,0,20,10,0.5" + ",0" * 15 + "\n")
    with pytest.raises(T.MuellerTableError, match=r"row 2, column lambda: empty"):
        T.read_table(path)
    with open(path, "w") as f:
        f.write(",".join(T.SCATMECH_COLUMNS) + "\n")
    with pytest.raises(T.MuellerTableError, match="no rows"):
        T.read_table(path)


def test_bad_plain(tmp_path):
    path = tmp_path / "p.npz"
    np.savez(path, w_in=np.array([[0, 0, 1.0]]), w_out=np.array([[0, 0.6, 0.8]]), mueller=np.zeros((1, 4, 3)))
    with pytest.raises(T.MuellerTableError, match="column mueller: shape"):
        T.read_table(path)
    np.savez(path, w_in=np.array([[0, 0, 1.0]]), w_out=np.array([[0, 0.6, 0.8]]), mueller=np.eye(4)[None],
             extra=np.zeros(1))
    with pytest.raises(T.MuellerTableError, match="column extra"):
        T.read_table(path)
    np.savez(path, w_in=np.array([[0, 0, 1.0]]), w_out=np.array([[0, 0.8, -0.6]]), mueller=np.eye(4)[None])
    with pytest.raises(T.MuellerTableError, match="row 0, column w_out_z"):
        T.read_table(path)
    np.savez(path, w_in=np.array([[0, 0, 2.0]]), w_out=np.array([[0, 0.6, 0.8]]), mueller=np.eye(4)[None])
    with pytest.raises(T.MuellerTableError, match="row 0, column w_in: direction of length 2"):
        T.read_table(path)
