"""Fitting Mueller BRDF tables: closed forms (the Lambertian), round trips within the reported intervals,
the noise estimates against the noise put in, and ``fmbrdf-mi fit-brdf`` on tables (outputs, bad input)."""
import json
import os

import numpy as np
import pytest

from fmbrdf_mi.brdf_fit import mueller as T
from fmbrdf_mi.brdf_fit import mueller_fit as F
from fmbrdf_mi.cli import main


def _table(tmp_path, model, params, noise_f, noise_m, seed, name="t.csv", geometries=None):
    w_in, w_out = geometries or F.goniometer_geometries()
    M = F.synthetic_table(model, params, w_in, w_out, noise_f, noise_m, seed)
    path = tmp_path / name
    if name.endswith(".npz"):
        T.write_plain(path, w_in, w_out, M, 0.633)
    else:
        T.write_scatmech(path, w_in, w_out, M, 0.633)
    return path, T.read_table(path)


def test_lambert_is_the_closed_form(tmp_path):
    """Log residuals: ln rho = mean ln(pi f); sigma_f the sample standard deviation of ln(pi f) (n - 1 degrees
    of freedom: the one parameter acts on f_r11 alone), the SE sigma_f / sqrt(n); sigma_m the RMS of the
    normalised elements (all non-zero by noise, none depending on the parameter: 15 n degrees of freedom)."""
    _, tab = _table(tmp_path, "lambert", {"reflectance": 0.4}, 0.05, 0.01, 1)
    r = F.fit_model("lambert", tab)
    n = len(tab)
    lr = np.log(np.pi * tab.f_r11)
    rho = np.exp(lr.mean())
    assert r.params["reflectance"] == pytest.approx(rho, rel=1e-6)
    rf = lr - lr.mean()
    sigma_f = np.sqrt(rf @ rf / (n - 1))
    assert r.noise["sigma_f"] == pytest.approx(sigma_f, rel=1e-4)
    assert r.se["reflectance"] == pytest.approx(rho * sigma_f / np.sqrt(n), rel=1e-3)
    m = tab.normalised.reshape(-1, 16)[:, 1:]
    assert r.noise["sigma_m"] == pytest.approx(np.sqrt(np.sum(m ** 2) / (15 * n)), rel=1e-4)
    assert r.converged


@pytest.mark.parametrize("name", ["t.csv", "t.npz"])
def test_pplastic_round_trip_within_intervals(tmp_path, name):
    truth = {"eta": 1.55, "alpha": 0.12, "specular_reflectance": 0.7, "diffuse_reflectance": 0.35}
    _, tab = _table(tmp_path, "pplastic", truth, 0.02, 0.01, 3, name)
    r = F.fit_model("pplastic", tab)
    assert r.converged
    for k, v in truth.items():
        assert abs(r.params[k] - v) < 4 * r.se[k], (k, r.params[k], v, r.se[k])
        lo, hi = r.interval[k]
        assert lo < r.params[k] < hi
    assert r.noise["sigma_f"] == pytest.approx(0.02, rel=0.15)
    assert r.noise["sigma_m"] == pytest.approx(0.01, rel=0.1)


def test_lambert_ts_round_trip_within_intervals(tmp_path):
    truth = {"eta": 1.6, "alpha": 0.25, "k_s": 0.5, "k_d": 0.3}
    _, tab = _table(tmp_path, "lambert_ts", truth, 0.02, 0.01, 7, "t.npz")
    r = F.fit_model("lambert_ts", tab)
    assert r.converged
    for k, v in truth.items():
        assert abs(r.params[k] - v) < 4 * r.se[k], (k, r.params[k], v, r.se[k])
    assert r.noise["sigma_f"] == pytest.approx(0.02, rel=0.15)


def test_kept_builds_change_no_number(tmp_path, monkeypatch):
    """The terms kept of the shape points a fit has built (what saves builds) are those a build at the same
    coordinates gives: the fit keeping none (a budget of 0 bytes) ends with the same numbers, bit for bit, after
    more builds."""
    truth = {"eta": 1.55, "alpha": 0.12, "specular_reflectance": 0.7, "diffuse_reflectance": 0.35}
    _, tab = _table(tmp_path, "pplastic", truth, 0.03, 0.01, 8, "t.npz")
    kept = F.fit_model("pplastic", tab)
    monkeypatch.setattr(F, "PARTS_KEPT_BYTES", 0)
    none = F.fit_model("pplastic", tab)
    assert none.builds > kept.builds
    for k in truth:
        assert kept.params[k] == none.params[k] and kept.se[k] == none.se[k]
        assert kept.interval[k] == none.interval[k]
    assert kept.noise == none.noise and kept.chi2 == none.chi2


def test_refinement_after_the_noise_estimate_reaches_the_optimum_of_its_weights(tmp_path):
    """The refit after the noise is estimated (started from the first optimum) ends where a fit with those sigmas
    given from the start ends: within a small fraction of the SE."""
    truth = {"eta": 1.55, "alpha": 0.12, "specular_reflectance": 0.7, "diffuse_reflectance": 0.35}
    _, tab = _table(tmp_path, "pplastic", truth, 0.05, 0.01, 4)
    r = F.fit_model("pplastic", tab)
    assert [h["stage"] for h in r.history].count("noise") == 2 and "trials" in r.history[-2]   # a refit ran
    given = F.fit_model("pplastic", tab, F.MuellerFitOptions(noise_f=r.noise["sigma_f"], noise_m=r.noise["sigma_m"]))
    assert r.converged and given.converged
    for k in truth:
        assert abs(r.params[k] - given.params[k]) < 0.1 * given.se[k], (k, r.params[k], given.params[k])
        assert r.se[k] == pytest.approx(given.se[k], rel=0.02)


def test_vanishing_elements_estimate_the_noise(tmp_path):
    _, tab = _table(tmp_path, "pplastic", {"eta": 1.5, "alpha": 0.2, "specular_reflectance": 1.0,
                                           "diffuse_reflectance": 0.3}, 0.02, 0.01, 4)
    s, n = F.vanishing_noise(tab)
    assert n == 3 * 16    # the in-plane rows of goniometer_geometries
    assert s == pytest.approx(0.01, rel=0.15)


def test_fmbrdf_round_trip_within_intervals(tmp_path):
    truth = {"eta": 1.5, "alpha": 0.2, "beta": 2.0, "kappa": 5.0, "k_s": 0.8, "k_b": 0.3}
    _, tab = _table(tmp_path, "fmbrdf", truth, 0.03, 0.01, 1)
    grid = {"fmbrdf": {"eta": (1.4,), "alpha": (0.1, 0.3), "beta": (1.5,), "kappa": (1.0,)}}   # the test's time
    r = F.fit_model("fmbrdf", tab, F.MuellerFitOptions(starts=1, start_grids=grid))
    assert r.converged
    for k, v in truth.items():
        assert abs(r.params[k] - v) < 4 * r.se[k], (k, r.params[k], v, r.se[k])


def test_command_fits_and_compares(tmp_path, capsys):
    truth = {"eta": 1.45, "alpha": 0.1, "specular_reflectance": 0.6, "diffuse_reflectance": 0.4}
    path, _ = _table(tmp_path, "pplastic", truth, 0.02, 0.01, 5)
    hold, _ = _table(tmp_path, "pplastic", truth, 0.02, 0.01, 6, "hold.npz", F.random_geometries(150, 2))
    out = tmp_path / "fit"
    assert main(["fit-brdf", str(path), "-o", str(out), "-q", "--models", "pplastic,lambert",
                 "--holdout", str(hold)]) == 0
    text = capsys.readouterr().out
    rows = [ln.split("\t") for ln in text.strip().splitlines()]
    assert rows[0][:3] == ["wavelength_um", "model", "set"] and len(rows) == 5
    held = {r[1]: r for r in rows[1:] if r[2] == "holdout"}
    # the true model predicts the held-out geometries to the noise; the Lambertian does not
    assert float(held["pplastic"][4]) < 0.02 and float(held["lambert"][4]) > 0.05
    assert float(held["pplastic"][5]) < float(held["lambert"][5])
    rep = json.load(open(out / "params.json"))
    assert rep["wavelengths"][0]["models"]["pplastic"]["noise"]["sigma_m"] > 0
    assert "Gaussian" in rep["noise_model"]
    assert rep["wavelengths"][0]["models"]["pplastic"]["interval_kind"] == dict.fromkeys(truth, F.INTERVAL_FISHER)
    for f in ("comparison.tsv", "mueller_panel_0.633.png", "residuals_0.633.png"):
        assert os.path.getsize(out / f) > 0
    assert main(["fit-brdf", str(path), "-o", str(out), "-q", "--models", "lambert"]) == 1   # exists: no --force
    assert "--force" in capsys.readouterr().err


@pytest.mark.parametrize("edit, where", [
    (lambda lines: lines.__setitem__(4, lines[4].replace(lines[4].split(",")[5], "nan", 1)), "row 5, column f_r11"),
    (lambda lines: lines.__setitem__(3, ",".join(lines[3].split(",")[:-1])), "row 4, column m44"),
    (lambda lines: lines.__setitem__(2, lines[2] + ",1.0"), "row 3, column 22 (extra)"),
    (lambda lines: lines.__setitem__(6, ",".join(["0.633", "91"] + lines[6].split(",")[2:])), "row 7, column thetai"),
])
def test_command_bad_table_one_line_nothing_written(tmp_path, capsys, edit, where):
    path, _ = _table(tmp_path, "lambert", {"reflectance": 0.3}, 0.0, 0.0, 0)
    lines = open(path).read().splitlines()
    edit(lines)
    open(path, "w").write("\n".join(lines) + "\n")
    out = tmp_path / "fit"
    assert main(["fit-brdf", str(path), "-o", str(out), "-q"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(path) in err and where in err, err
    assert not out.exists()


def test_command_bad_options(tmp_path, capsys):
    path, _ = _table(tmp_path, "lambert", {"reflectance": 0.3}, 0.0, 0.0, 0)
    assert main(["fit-brdf", str(path), "-o", str(tmp_path / "o"), "-q", "--models", "phong"]) == 1
    assert "phong" in capsys.readouterr().err
    assert main(["fit-brdf", str(path), "-o", str(tmp_path / "o"), "-q", "--noise-m", "-1"]) == 1
    assert "--noise-m" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_options_of_the_other_kind_are_refused(tmp_path, capsys):
    path, _ = _table(tmp_path, "lambert", {"reflectance": 0.3}, 0.0, 0.0, 0)
    assert main(["fit-brdf", str(path), "-o", str(tmp_path / "o"), "-q", "--jobs", "2"]) == 1
    assert "--jobs" in capsys.readouterr().err
    merl = tmp_path / "m.binary"
    merl.write_bytes(b"")
    assert main(["fit-brdf", str(merl), "-o", str(tmp_path / "o"), "-q", "--holdout", str(path)]) == 1
    assert "--holdout" in capsys.readouterr().err
    assert main(["fit-brdf", str(merl), "-o", str(tmp_path / "o"), "-q", "--share", "alpha"]) == 1
    assert "--share" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_each_wavelength_is_fitted_alone(tmp_path, capsys):
    """Two wavelengths of different materials in one file: each gets its own parameters and plots; a wavelength
    with too few rows is refused in one line naming the file and the wavelength, before anything is written."""
    w_in, w_out = F.goniometer_geometries(theta_i=(30.0, 50.0), phi_o=(0.0, 90.0))
    a = F.synthetic_table("lambert", {"reflectance": 0.2}, w_in, w_out, 0.02, 0.01, 1)
    b = F.synthetic_table("lambert", {"reflectance": 0.6}, w_in, w_out, 0.02, 0.01, 2)
    path = tmp_path / "two.csv"
    T.write_plain(path, np.concatenate([w_in, w_in]), np.concatenate([w_out, w_out]), np.concatenate([a, b]),
                  np.repeat([0.45, 0.65], len(w_in)))
    out = tmp_path / "fit"
    assert main(["fit-brdf", str(path), "-o", str(out), "-q", "--models", "lambert"]) == 0
    rep = json.load(open(out / "params.json"))
    rho = {w["wavelength_um"]: w["models"]["lambert"]["params"]["reflectance"] for w in rep["wavelengths"]}
    assert rho[0.45] == pytest.approx(0.2, rel=0.02) and rho[0.65] == pytest.approx(0.6, rel=0.02)
    assert (out / "mueller_panel_0.45.png").exists() and (out / "residuals_0.65.png").exists()
    capsys.readouterr()
    T.write_plain(path, np.concatenate([w_in, w_in[:3]]), np.concatenate([w_out, w_out[:3]]),
                  np.concatenate([a, b[:3]]), np.repeat([0.45, 0.65], [len(w_in), 3]))
    assert main(["fit-brdf", str(path), "-o", str(tmp_path / "few"), "-q", "--models", "lambert"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(path) in err and "0.65" in err, err
    assert not (tmp_path / "few").exists()


def _multi(tmp_path, model, truths, geometries=None, name="multi.npz", seed0=10):
    """One table, one wavelength per truth (each its own noise draw)."""
    w_in, w_out = geometries or F.goniometer_geometries()
    M = np.concatenate([F.synthetic_table(model, t, w_in, w_out, 0.03, 0.01, seed0 + k) for k, t in enumerate(truths)])
    wl = np.repeat(0.45 + 0.1 * np.arange(len(truths)), len(w_in))
    path = tmp_path / name
    T.write_plain(path, np.tile(w_in, (len(truths), 1)), np.tile(w_out, (len(truths), 1)), M, wl)
    return path, T.read_table(path)


def _combined_se(se):
    """The standard error of a parameter common to fits with standard errors ``se`` (inverse-variance sum)."""
    return 1.0 / np.sqrt(np.sum(1.0 / np.asarray(se) ** 2))


def test_shared_parameter_combines_the_wavelengths(tmp_path):
    """pplastic over three wavelengths, alpha common, eta and the albedos per wavelength: alpha's one value and
    its standard error the inverse-variance combination of the separate fits' (the joint Gauss-Newton covariance
    of independent blocks), about 1/sqrt(3) of one wavelength's; every estimate within 4 SE of its truth."""
    truths = [{"eta": e, "alpha": 0.12, "specular_reflectance": ks, "diffuse_reflectance": 0.35}
              for e, ks in ((1.6, 0.8), (1.5, 0.7), (1.4, 0.6))]
    _, tab = _multi(tmp_path, "pplastic", truths)
    res = F.fit_table(tab, F.MuellerFitOptions(models=("pplastic",), share=("alpha",)))
    rs = [d["pplastic"] for d in res.values()]
    assert len(rs) == 3 and all(r.converged and r.shared == ["alpha"] for r in rs)
    assert len({r.params["alpha"] for r in rs}) == 1 and len({r.se["alpha"] for r in rs}) == 1
    assert len({r.params["eta"] for r in rs}) == 3
    separate = [F.fit_model("pplastic", tab.at_wavelength(wl)) for wl in tab.wavelengths()]
    se_alone = [r.se["alpha"] for r in separate]
    assert rs[0].se["alpha"] == pytest.approx(_combined_se(se_alone), rel=0.05)
    assert rs[0].se["alpha"] == pytest.approx(np.mean(se_alone) / np.sqrt(3), rel=0.25)
    for r, t in zip(rs, truths):
        for k, v in t.items():
            assert abs(r.params[k] - v) < 4 * r.se[k], (k, r.params[k], v, r.se[k])
        assert r.noise["sigma_f"] == pytest.approx(0.03, rel=0.15) and r.noise["sigma_m"] == pytest.approx(0.01, rel=0.1)
        assert "alpha common to every wavelength" in r.noise["model"]


@pytest.mark.slow
def test_fmbrdf_shared_shape_over_wavelengths(tmp_path):
    """FMBRDF with alpha, beta, kappa common and eta, k_s, k_b per wavelength (a dispersive material): every
    estimate within 4 SE of its truth (as the single-wavelength round trips), and the common parameters'
    standard errors below every wavelength's own, about their inverse-variance combination."""
    truths = [{"eta": e, "alpha": 0.2, "beta": 2.0, "kappa": 5.0, "k_s": ks, "k_b": 0.3}
              for e, ks in ((1.55, 0.9), (1.5, 0.8), (1.45, 0.7))]
    _, tab = _multi(tmp_path, "fmbrdf", truths)
    grid = {"fmbrdf": {"eta": (1.4,), "alpha": (0.1, 0.3), "beta": (1.5,), "kappa": (1.0,)}}   # the test's time
    opts = F.MuellerFitOptions(models=("fmbrdf",), starts=1, start_grids=grid, share=("alpha", "beta", "kappa"))
    res = F.fit_table(tab, opts)
    rs = [d["fmbrdf"] for d in res.values()]
    assert all(r.converged for r in rs)
    sep = rs[0].history[0]["separate"]     # the separate fits the joint one starts from
    for r, t in zip(rs, truths):
        assert r.shared == ["alpha", "beta", "kappa"]
        for k, v in t.items():
            assert abs(r.params[k] - v) < 4 * r.se[k], (k, r.params[k], v, r.se[k])
    for k in ("alpha", "beta", "kappa"):
        assert rs[0].se[k] < min(sep[k]["se"]), (k, rs[0].se[k], sep[k]["se"])
        assert rs[0].se[k] == pytest.approx(_combined_se(sep[k]["se"]), rel=0.3), (k, rs[0].se[k], sep[k]["se"])


def test_command_shares_parameters(tmp_path, capsys):
    truths = [{"eta": e, "alpha": 0.1, "specular_reflectance": 0.6, "diffuse_reflectance": 0.4} for e in (1.5, 1.4)]
    geo = F.goniometer_geometries(theta_i=(30.0, 50.0), phi_o=(0.0, 90.0))
    path, _ = _multi(tmp_path, "pplastic", truths, geo)
    out = tmp_path / "fit"
    assert main(["fit-brdf", str(path), "-o", str(out), "-q", "--models", "pplastic,lambert",
                 "--share", "alpha"]) == 0
    rep = json.load(open(out / "params.json"))
    fits = [w["models"] for w in rep["wavelengths"]]
    assert [f["pplastic"]["shared"] for f in fits] == [["alpha"], ["alpha"]]
    assert [f["lambert"]["shared"] for f in fits] == [[], []]      # no alpha: per wavelength
    assert fits[0]["pplastic"]["params"]["alpha"] == fits[1]["pplastic"]["params"]["alpha"]
    capsys.readouterr()
    # a parameter no model has; one wavelength: one line each, nothing written
    assert main(["fit-brdf", str(path), "-o", str(tmp_path / "o"), "-q", "--models", "lambert", "--share",
                 "alpha"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--share" in err and "alpha" in err, err
    one, _ = _table(tmp_path, "pplastic", truths[0], 0.02, 0.01, 1)
    assert main(["fit-brdf", str(one), "-o", str(tmp_path / "o"), "-q", "--share", "alpha"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "one wavelength" in err and str(one) in err, err
    assert not (tmp_path / "o").exists()


def test_leverages_count_the_parameters_each_group_absorbs():
    """The hat matrix's diagonal summed per group: p in all for a full-rank J; a parameter acting on one group
    only is absorbed by that group; a vanishing column (a parameter at a bound) by none."""
    rng = np.random.default_rng(0)
    J = rng.standard_normal((50, 4))
    assert sum(F.leverages(J, (20, 30))) == pytest.approx(4.0)
    J = np.zeros((50, 3))
    J[:20, 0] = rng.standard_normal(20)          # acts on the first group only
    J[20:, 1] = rng.standard_normal(30)          # on the second only
    assert F.leverages(J, (20, 30)) == pytest.approx([1.0, 1.0])


class _Linear:
    """Weighted residuals A x - b: a least-squares problem of profile_limit's interface."""

    def __init__(self, A, b):
        self.A, self.b = A, b

    def fun(self, x):
        return self.A @ x - self.b

    def jac(self, x, columns=None):
        return self.A if columns is None else self.A[:, list(columns)]


@pytest.mark.parametrize("level", [0.95, 0.68])
def test_profile_limit_of_a_linear_model_at_its_bound_is_the_closed_form(level):
    """A linear model whose first parameter is bounded below by 0 and whose unconstrained optimum theta* lies
    below it: the fit ends at 0; the profiled cost is P* + (v - theta*)^2 / C_00 (C = (A^T A)^-1), so it rises
    above its value at the bound by q = z^2 at v = theta* + sqrt(theta*^2 + q C_00).  The Wald interval cut at
    the bound ends at z sqrt(C_00) instead (checked to be far from the answer, so that the check tells them
    apart)."""
    from statistics import NormalDist

    rng = np.random.default_rng(3)
    A = rng.standard_normal((40, 3))
    A[:, 1] += 0.6 * A[:, 0]                 # correlated with the bounded parameter
    b = A @ np.array([-1.5, 0.4, 2.0]) + rng.standard_normal(40)
    theta = np.linalg.lstsq(A, b, rcond=None)[0]
    assert theta[0] < 0
    C = np.linalg.inv(A.T @ A)
    at_bound = np.concatenate([[0.0], np.linalg.lstsq(A[:, 1:], b, rcond=None)[0]])
    z = NormalDist().inv_cdf(0.5 + level / 2)
    expected = theta[0] + np.sqrt(theta[0] ** 2 + z * z * C[0, 0])
    limit, points = F.profile_limit(_Linear(A, b), at_bound, 0, lambda v: v, 0.0, 100.0, z * np.sqrt(C[0, 0]),
                                    level, 60)
    tol = 0.01 * np.sqrt(C[0, 0])
    assert limit == pytest.approx(expected, abs=tol)
    assert abs(z * np.sqrt(C[0, 0]) - expected) > 10 * tol
    for v, rise in points:       # every profile point's rise as the closed form, to the refits' tolerance
        assert rise == pytest.approx(((v - theta[0]) ** 2 - theta[0] ** 2) / C[0, 0], abs=0.02)


def test_profile_limits_of_a_linear_model_near_its_bound_are_the_closed_form():
    """The unconstrained optimum theta* inside the bound but within z SE of it: the profiled cost rises by
    (v - theta*)^2 / C_00, so the upper end is theta* + z sqrt(C_00) and, towards the bound, the rise at the
    bound (theta*^2 / C_00 < z^2) leaves the bound as the lower end."""
    rng = np.random.default_rng(5)
    A = rng.standard_normal((40, 3))
    A[:, 2] += 0.5 * A[:, 0]
    b = A @ np.array([0.0, 1.0, -1.0]) + rng.standard_normal(40)
    C = np.linalg.inv(A.T @ A)
    se = np.sqrt(C[0, 0])
    b += A[:, 0] * (0.8 * se - np.linalg.lstsq(A, b, rcond=None)[0][0])    # theta*_0 = 0.8 SE
    theta = np.linalg.lstsq(A, b, rcond=None)[0]
    assert theta[0] == pytest.approx(0.8 * se)
    ref = F.profile_reference(_Linear(A, b), theta, 0, 60)
    upper, _ = F.profile_limit(_Linear(A, b), theta, 0, lambda v: v, theta[0], 100.0, 1.96 * se, 0.95, 60,
                               reference=ref)
    lower, points = F.profile_limit(_Linear(A, b), theta, 0, lambda v: v, theta[0], 0.0, -1.96 * se, 0.95, 60,
                                    reference=ref)
    assert upper == pytest.approx(theta[0] + 1.959964 * se, abs=0.01 * se)
    assert lower == 0.0 and points[0][0] == 0.0
    assert points[0][1] == pytest.approx(theta[0] ** 2 / C[0, 0], abs=0.02)


def test_profile_limit_reaches_the_other_bound_when_the_cost_stays_flat():
    """A parameter the data do not constrain (its column 1e-3 of the others'): the profile's rise stays below the
    quantile up to the other bound, which is then the limit."""
    rng = np.random.default_rng(4)
    A = rng.standard_normal((30, 2))
    A[:, 0] *= 1e-3
    b = A @ np.array([0.0, 1.0]) + rng.standard_normal(30)
    x = np.array([0.0, np.linalg.lstsq(A[:, 1:], b, rcond=None)[0][0]])
    limit, _ = F.profile_limit(_Linear(A, b), x, 0, lambda v: v, 0.0, 5.0, 0.5, 0.95, 60)
    assert limit == 5.0


def _profiled_cost(tab, params, kappa, sigma_f, sigma_m):
    """min over eta, alpha, beta, ln k_s, ln k_b of the weighted sum of squares with kappa held: an independent
    Gauss-Newton (central differences, step halving) on the model's terms of ``MuellerValues``."""
    from fmbrdf_mi.brdf_fit.mueller_values import MuellerValues, combine, polarised_variant

    m_obs = tab.normalised.reshape(-1, 16)[:, 1:]
    with polarised_variant():
        values = MuellerValues("fmbrdf", tab.w_in, tab.w_out)

        def residuals(u):
            M = combine(values.parts({"eta": u[0], "alpha": u[1], "beta": u[2], "kappa": kappa}), np.exp(u[3:]))
            f = M[:, 0, 0]
            rm = (M / f[:, None, None]).reshape(-1, 16)[:, 1:] - m_obs
            return np.concatenate([np.log(f / tab.f_r11) / sigma_f, rm.ravel() / sigma_m])

        u = np.array([params["eta"], params["alpha"], params["beta"], np.log(params["k_s"]), np.log(params["k_b"])])
        r = residuals(u)
        for _ in range(20):
            h = np.array([1e-4, 1e-4, 1e-3, 1e-5, 1e-5])
            J = np.stack([(residuals(u + e) - residuals(u - e)) / (2 * e.sum()) for e in np.diag(h)], axis=1)
            step = np.linalg.lstsq(J, -r, rcond=None)[0]
            for t in (1.0, 0.5, 0.25, 0.125):
                r_new = residuals(u + t * step)
                if r_new @ r_new < r @ r:
                    break
            if not r_new @ r_new < r @ r:
                break
            done = r @ r - r_new @ r_new < 1e-4
            u, r = u + t * step, r_new
            if done:
                break
    return float(r @ r)


def test_kappa_at_its_bound_gets_the_profile_likelihood_limit(tmp_path):
    """An FMBRDF fit that ends at kappa = 0: its interval is one-sided, from 0 to where the profiled cost (the
    other parameters refitted, with the fit's sigmas) has risen by z^2 = 3.84: an independent refit at 0.9 and
    1.1 times the reported limit finds the rise below and above it.  (The Wald interval cut at the bound ends at
    1.96 SE, outside that bracket on this table.)"""
    truth = {"eta": 1.5, "alpha": 0.2, "beta": 2.0, "kappa": 5.0, "k_s": 0.8, "k_b": 0.3}
    _, tab = _table(tmp_path, "fmbrdf", truth, 0.03, 0.01, 10, "t.npz")
    grid = {"fmbrdf": {"eta": (1.4,), "alpha": (0.1, 0.3), "beta": (1.5,), "kappa": (1.0,)}}   # the test's time
    r = F.fit_model("fmbrdf", tab, F.MuellerFitOptions(starts=1, start_grids=grid))
    assert r.converged and r.at_bound == ["kappa"]
    assert r.interval_kind["kappa"] == F.INTERVAL_PROFILE
    assert all(r.interval_kind[k] == F.INTERVAL_FISHER for k in r.params if k != "kappa")
    lo, limit = r.interval["kappa"]
    assert lo == 0.0
    sf, sm = r.noise["sigma_f"], r.noise["sigma_m"]
    c0 = _profiled_cost(tab, r.params, r.params["kappa"], sf, sm)
    below = _profiled_cost(tab, r.params, 0.9 * limit, sf, sm) - c0
    above = _profiled_cost(tab, r.params, 1.1 * limit, sf, sm) - c0
    assert below < 1.959964 ** 2 < above, (limit, below, above)
    wald = 1.959964 * r.se["kappa"]
    assert not 0.9 * limit < wald < 1.1 * limit, (limit, wald)
