"""``fmbrdf-mi fit``'s output stage: past a few seconds, a line per file written with the time left, as
``fmbrdf-mi render`` prints them (one helper, :class:`fmbrdf_mi._paths.StageProgress`); none under ``-q``.  The
clock is a fake one that advances one second per reading, so the lines are known exactly."""
import functools
import io

import pytest

from fmbrdf_mi import _paths
from fmbrdf_mi.cli import main
from fmbrdf_mi.fit.outputs import job

#: The files of a per-pixel fit of one image, in the order the command writes them (fit.json last).
WRITTEN = ["profiles.png", "images.png", "history.png", "fitted_stokes.exr", "fit.json"]


@pytest.fixture(scope="module")
def stokes_exr(tmp_path_factory):
    path = str(tmp_path_factory.mktemp("capture") / "sphere.exr")
    assert main(["render", "--res", "32", "--spp", "4", "-q", path]) == 0
    return path


def fake_progress(monkeypatch):
    """The fit's writing progress on a clock that reads 0, 1, 2, ... seconds; returns its stream."""
    stream, now = io.StringIO(), iter(range(1000))
    monkeypatch.setattr(job, "StageProgress", functools.partial(_paths.StageProgress, stream=stream,
                                                                clock=lambda: float(next(now))))
    return stream


def test_the_output_stage_gives_a_line_per_file_with_the_time_left(tmp_path, stokes_exr, monkeypatch, no_figures):
    stream = fake_progress(monkeypatch)
    assert main(["fit", stokes_exr, "--starts", "1", "-o", str(tmp_path / "fit")]) == 0
    n = len(WRITTEN)
    # step k is read at k seconds: silent up to the 2 s delay, then the mean second per step times those left
    expected = [f"writing: {k}/{n} {name}, {k:.1f} s ({'done' if k == n else f'about {n - k} s left'})"
                for k, name in enumerate(WRITTEN, start=1) if k > 2]
    assert stream.getvalue().splitlines() == expected
    assert sorted(p.name for p in (tmp_path / "fit").iterdir()) == sorted(WRITTEN)


def test_the_output_stage_is_silent_under_quiet(tmp_path, stokes_exr, monkeypatch, no_figures):
    stream = fake_progress(monkeypatch)
    assert main(["fit", stokes_exr, "--starts", "1", "-q", "-o", str(tmp_path / "fit")]) == 0
    assert stream.getvalue() == ""


def test_the_albedo_maps_count_as_a_step_each(tmp_path):
    """A per-pixel fit's maps (written for the single-image, joint and colour fits alike) are steps too."""
    from types import SimpleNamespace

    import numpy as np

    from fmbrdf_mi.fit.outputs.single import write_maps
    from fmbrdf_mi.fit.outputs.job import MAP_OUTPUTS

    k = np.full((4, 5), 0.5)
    k[0, 0] = np.nan
    res = SimpleNamespace(maps={"k_s": k, "k_b": k, "k_s_se": k / 10, "k_b_se": k / 10, "identified": k > 0},
                          params={"eta": 1.5}, albedo={"pixels": 19, "identified_fraction": 1.0})
    steps, report = [], {}
    write_maps(res, "fmbrdf", str(tmp_path), report, wrote=steps.append)
    assert [p.rsplit("/", 1)[1] for p in steps] == list(MAP_OUTPUTS)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(MAP_OUTPUTS)
