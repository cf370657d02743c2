"""Progress lines of a fit carry time-left estimates, and ``progress=False`` prints nothing."""
import re

import pytest

from fmbrdf_mi.fit.api.fitting import fit
from fmbrdf_mi.fit.solve.optimise import time_left
from fmbrdf_mi.sensor.camera import CameraModel
from fmbrdf_mi.synthetic.spheres import capture_observation, ideal_sphere

TRUE = {"eta": 1.5, "alpha": 0.15, "beta": 0.8, "kappa": 10.0, "k_s": 0.6, "r_k": 1.0}
LEFT = re.compile(r"~\d+(\.\d)? s left")


def test_time_left_is_the_measured_rate_times_what_remains():
    assert time_left(6.0, 3, 10, "in x") == "~14 s left in x"             # 2 s per unit, 7 units
    assert time_left(1.0, 4, 6, "in x", bound=True) == "at most ~0.5 s left in x"
    assert time_left(5.0, 0, 6, "in x") == ""                              # nothing measured yet


@pytest.fixture(scope="module")
def lines():
    cam = CameraModel(full_well=10000.0, read_noise=2.5, bits=12)
    obs = capture_observation(ideal_sphere(TRUE, res=12, light=(0.45, 0.35, 1.0)), cam, seed=2)[0]
    out = []
    fit(obs, loss="likelihood", fixed={"beta": 0.8, "kappa": 10.0}, starts=2, max_iter=6, rounds=1, intervals="profile",
        progress=out.append)
    return out


@pytest.mark.parametrize("stage", [r"^\[search\] stage 1", r"^\[lm \d\] iter", r"^\[fit\] start 2/2",
                                   r"^\[fit\] interval check: \w+ done, 1/"])
def test_each_long_stage_reports_the_time_left(lines, stage):
    hits = [ln for ln in lines if re.search(stage, ln)]
    assert hits, f"no progress line for {stage}"
    assert any(LEFT.search(ln) for ln in hits), hits


def test_quiet_fit_prints_nothing(capsys):
    cam = CameraModel(full_well=10000.0, read_noise=2.5, bits=12)
    obs = capture_observation(ideal_sphere(TRUE, res=12, light=(0.45, 0.35, 1.0)), cam, seed=2)[0]
    fit(obs, loss="likelihood", starts=1, max_iter=3, rounds=1, intervals="profile", progress=False)
    captured = capsys.readouterr()
    assert captured.err == "" and captured.out == ""


def test_mirrored_layout_check_announces_its_time_from_the_first_fit(capsys):
    """The mirrored-layout check refits silently; its announcement carries the first fit's measured time."""
    from fmbrdf_mi.fit.cli import layout_check as LC

    report = {"models": {"fmbrdf": {"objective": "likelihood", "loss_terms": {"chi2": 800.0, "samples": 320},
                                    "converged": True, "uncertainty": {"misfit": True}, "timings": {"total": 42.4}}},
              "reproduce": {"images": [{"settings": {"demosaic": "bilinear", "layout": [[90, 135], [45, 0]]}}]}}
    assert LC.mirrored_layout_hint(report, {"model": "fmbrdf"}, lambda **kw: report, progress=True) is None
    assert "~42 s" in capsys.readouterr().err
