"""``fmbrdf-mi fit-brdf`` (fmbrdf_mi/brdf_fit): the unpolarised evaluation variant, the coarse-to-fine start
grid, progress lines, the batch mode (several files or a directory, ``--jobs``), the batch options with one
file, and Ctrl-C stopping a batch (a real SIGINT to a subprocess).

Full-size MERL files (35 MB) are written into tmp_path; fits use a small start grid and a few thousand bins.
"""
import json
import os
import signal
import struct
import subprocess
import time

import numpy as np
import pytest

from fmbrdf_mi.brdf_fit import merl

from conftest import figures_not_drawn, finish_command, one_line_error, run, start_command

TRUE = {"eta": 1.55, "alpha": 0.23, "beta": 1.7, "kappa": 15.0, "k_s": [0.5, 0.6, 0.7], "k_b": [0.3, 0.1, 0.05]}
OTHER = {"eta": 1.35, "alpha": 0.08, "beta": 0.9, "kappa": 4.0, "k_s": [1.0, 0.9, 0.8], "k_b": [0.2, 0.3, 0.4]}


def _small_options(cls=None, **kw):
    from fmbrdf_mi.brdf_fit.fitting import BRDFFitOptions

    cls = cls or BRDFFitOptions
    d = dict(eta_grid=(1.3, 1.7), alpha_grid=(0.05, 0.15, 0.5), beta_grid=(1.0, 2.5), max_samples=3000,
             starts=1, max_evals=30)
    d.update(kw)
    return cls(**d)


@pytest.fixture
def small_fits(monkeypatch):
    """fit-brdf's options replaced by the small ones (the CLI's --samples etc. still apply)."""
    from fmbrdf_mi.brdf_fit import fitting

    cls = fitting.BRDFFitOptions
    monkeypatch.setattr(fitting, "BRDFFitOptions",
                        lambda **kw: _small_options(cls, **{k: v for k, v in kw.items() if k != "starts"}))


@pytest.fixture(scope="module")
def two_files(tmp_path_factory):
    from fmbrdf_mi.brdf_fit.fitting import model_brdf

    d = tmp_path_factory.mktemp("merl")
    merl.write_merl(d / "alpha.binary", model_brdf(TRUE))
    merl.write_merl(d / "beta.binary", model_brdf(OTHER))
    return d


def test_values_are_the_polarised_variants_m00_bit_for_bit():
    """values.py evaluates in llvm_ad_mono (unpolarised tables, 3x faster builds): the same M00 as the
    polarised fit variant, every bit, and the caller's variant is the same afterwards."""
    import drjit as dr
    import mitsuba as mi

    from fmbrdf_mi.brdf_fit.values import FMBRDFValues
    from fmbrdf_mi.fit.evaluate.pixel_model import set_variant

    set_variant()
    before = mi.variant()
    rng = np.random.default_rng(3)
    w_in, w_out = merl.half_diff_to_dirs(rng.uniform(0, 1.4, 3000) ** 2, rng.uniform(0, 1.4, 3000),
                                         rng.uniform(0, np.pi, 3000))
    keep = (w_in[:, 2] > 0.01) & (w_out[:, 2] > 0.01)
    w_in, w_out = w_in[keep], w_out[keep]
    ev = FMBRDFValues(w_in, w_out)
    assert mi.variant() == before
    bsdf = mi.load_dict({"type": "fmbrdf", "k_s": 1.0, "k_b": 1.0, "tables": "float32"})
    params = mi.traverse(bsdf)
    si = dr.zeros(mi.SurfaceInteraction3f, len(w_in))
    si.wi = mi.Vector3f(*(mi.Float(w_out[:, k].astype(np.float32)) for k in range(3)))
    wo = mi.Vector3f(*(mi.Float(w_in[:, k].astype(np.float32)) for k in range(3)))
    for shape in ({"eta": 1.55, "alpha": 0.23, "beta": 1.7, "kappa": 15.0},
                  {"eta": 1.9, "alpha": 1.5, "beta": 4.0, "kappa": 0.0}):
        S, B = ev.parts(shape)
        assert mi.variant() == before
        for k, v in shape.items():
            params[k] = v
        params.update()
        for flag, mine in ((mi.BSDFFlags.GlossyReflection, S), (mi.BSDFFlags.DiffuseReflection, B)):
            ctx = mi.BSDFContext()
            ctx.type_mask = +flag
            m00 = np.asarray(bsdf.eval(ctx, si, wo)[0, 0], dtype=np.float64).reshape(-1) / w_in[:, 2]
            np.testing.assert_array_equal(mine, m00)


def test_grid_search_finds_the_best_points_in_fewer_evaluations():
    """The coarse-to-fine search on an error with two valleys, the best one's lowest point between coarse
    points (odd indices) and its coarse points all worse than the other valley's: looked into all the same
    (the coarse lattice's local minima seed the search, one per valley)."""
    from fmbrdf_mi.brdf_fit.fitting import coarse_points, grid_search

    dims = (8, 8, 5)
    lows = [((3, 5, 1), 0.0), ((6, 1, 3), 0.002)]

    def error(p):
        return min(v + 0.01 * sum((a - b) ** 2 for a, b in zip(p, q)) for q, v in lows)

    full = grid_search(dims, error, 3, "full")
    local = grid_search(dims, error, 3, "local")
    rank = lambda d: sorted(d, key=lambda p: (d[p], np.ravel_multi_index(p, dims)))
    assert len(full) == 320 and len(local) < 200
    assert rank(local)[:3] == rank(full)[:3]
    assert (3, 5, 1) not in coarse_points(dims) and min(error(p) for p in coarse_points(dims)) == pytest.approx(0.022)
    with pytest.raises(ValueError, match="full"):
        grid_search(dims, error, 3, "nearby")


def test_local_and_full_grid_give_the_same_fit(two_files):
    from fmbrdf_mi.brdf_fit.fitting import fit_brdf

    data = merl.read_merl(two_files / "beta.binary")
    grid = dict(eta_grid=(1.2, 1.3, 1.5, 1.7, 1.9), alpha_grid=(0.02, 0.05, 0.1, 0.2, 0.5), max_evals=8)
    a = fit_brdf(data, _small_options(grid_search="local", **grid))
    b = fit_brdf(data, _small_options(grid_search="full", **grid))
    assert a.history[0]["points"] < b.history[0]["points"] == 50
    assert a.params == b.params and a.log_rmse_all == b.log_rmse_all


def test_progress_lines_estimate_the_time_left():
    from fmbrdf_mi.brdf_fit.fitting import Progress

    lines = []
    bar = Progress(lines.append, "start grid point", 4, every=0.0)
    for k in range(1, 5):
        bar.step(k, "best 0.1")
    assert len(lines) == 4 and all("s left" in s for s in lines[:3]) and "left" not in lines[3]
    assert lines[0].startswith("[fit-brdf] start grid point 1/4, best 0.1; ")
    bounded = []
    Progress(bounded.append, "evaluation", 10, every=0.0, bound=True).step(2)
    assert "at most about" in bounded[0]


def test_progress_goes_to_stderr_and_quiet_silences_it(tmp_path, capsys, two_files, small_fits, monkeypatch,
                                                       no_figures):
    from fmbrdf_mi.brdf_fit import fitting
    from fmbrdf_mi.cli import main

    monkeypatch.setattr(fitting.Progress, "__init__", _eager(fitting.Progress.__init__))
    assert main(["fit-brdf", str(two_files / "alpha.binary"), "-o", str(tmp_path / "a")]) == 0
    out, err = capsys.readouterr()
    assert "start grid point" in err and "s left" in err and "evaluation" in err and "[fit-brdf]" not in out
    assert main(["fit-brdf", str(two_files / "alpha.binary"), "-o", str(tmp_path / "b"), "-q"]) == 0
    out, err = capsys.readouterr()
    assert err == "" and out.count("\n") == 1


def _eager(init):
    def patched(self, *a, **k):
        init(self, *a, **k)
        self.every = 0.0
    return patched


def _params(path):
    d = json.loads(open(path).read())
    return d["params"], d["log10_rmse"], d["n_samples"]


def test_a_batch_gives_the_single_runs_results(tmp_path, capsys, two_files, small_fits):
    from fmbrdf_mi.cli import main

    with figures_not_drawn():      # the single runs' slices.png is not read here
        for name in ("alpha", "beta"):
            assert main(["fit-brdf", str(two_files / f"{name}.binary"), "-q", "-o",
                         str(tmp_path / "single" / name)]) == 0
    capsys.readouterr()
    assert main(["fit-brdf", str(two_files), "-q", "-o", str(tmp_path / "batch")]) == 0
    out, err = capsys.readouterr()
    for name in ("alpha", "beta"):
        assert _params(tmp_path / "batch" / name / "params.json") == _params(tmp_path / "single" / name / "params.json")
        assert (tmp_path / "batch" / name / "slices.png").stat().st_size > 10_000
    table = (tmp_path / "batch" / "summary.tsv").read_text()
    assert table == out
    rows = [r.split("\t") for r in table.strip().splitlines()]
    assert rows[0][:2] == ["material", "status"] and [r[:2] for r in rows[1:]] == [["alpha", "ok"], ["beta", "ok"]]
    assert float(rows[1][2]) == pytest.approx(TRUE["eta"], rel=1e-3)


def test_a_corrupt_file_is_named_and_the_others_are_fitted(tmp_path, capsys, two_files, small_fits, no_figures):
    from fmbrdf_mi.cli import main

    bad = tmp_path / "broken.binary"
    bad.write_bytes(struct.pack("<3i", 90, 90, 180) + bytes(800))
    rc = main(["fit-brdf", str(bad), str(two_files / "alpha.binary"), "-q", "-o", str(tmp_path / "fits")])
    out, err = capsys.readouterr()
    assert rc == 1 and "Traceback" not in err
    assert any(str(bad) in line and "truncated" in line for line in err.splitlines()), err
    assert "alpha" not in err
    assert (tmp_path / "fits" / "alpha" / "params.json").exists() and not (tmp_path / "fits" / "broken").exists()
    rows = dict(r.split("\t")[:2] for r in out.strip().splitlines()[1:])
    assert rows == {"broken": "failed", "alpha": "ok"}


def test_a_batch_overwrites_nothing_without_force(tmp_path, capsys, two_files, small_fits, no_figures):
    from fmbrdf_mi.cli import main

    out = tmp_path / "fits"
    assert main(["fit-brdf", str(two_files), "-q", "-o", str(out)]) == 0
    stamp = {p: os.stat(p).st_mtime_ns for p in out.rglob("*") if p.is_file()}
    capsys.readouterr()
    # the summary: refused before anything is fitted
    assert main(["fit-brdf", str(two_files), "-q", "-o", str(out)]) == 1
    assert "summary.tsv exists; pass --force" in capsys.readouterr().err
    os.remove(out / "summary.tsv")
    stamp.pop(out / "summary.tsv")
    # each material: named, not fitted, not overwritten
    assert main(["fit-brdf", str(two_files), "-q", "-o", str(out)]) == 1
    err = capsys.readouterr().err
    assert all(f"{out / n / 'params.json'} exists; pass --force" in err for n in ("alpha", "beta")), err
    assert {p: os.stat(p).st_mtime_ns for p in stamp} == stamp
    # resuming: the existing ones are skipped, listed, and the summary is written again
    assert main(["fit-brdf", str(two_files), "-q", "-o", str(out), "--skip-existing"]) == 0
    table = capsys.readouterr().out
    assert table.count("skipped (exists)") == 2 and {p: os.stat(p).st_mtime_ns for p in stamp} == stamp


def test_jobs_run_in_worker_processes_with_the_same_results(tmp_path, capsys, two_files):
    """--jobs 2: spawned workers (no monkeypatching there: the default grid, few samples and evaluations)."""
    from fmbrdf_mi.cli import main

    small = ["--samples", "500", "--starts", "1", "--max-evals", "3", "-q"]
    with figures_not_drawn():      # this process's fits: their slices.png is not read here
        assert main(["fit-brdf", str(two_files), "-o", str(tmp_path / "one"), *small]) in (0, 3)
    assert main(["fit-brdf", str(two_files), "-o", str(tmp_path / "two"), "--jobs", "2", *small]) in (0, 3)
    capsys.readouterr()
    for name in ("alpha", "beta"):
        assert _params(tmp_path / "two" / name / "params.json") == _params(tmp_path / "one" / name / "params.json")
    assert main(["fit-brdf", str(two_files), "--jobs", "0"]) == 1
    assert "--jobs" in capsys.readouterr().err


# ---------------------------------------------------------------- batch options with one file
def test_fit_brdf_force_with_skip_existing_refused(capsys, tmp_path):
    """Before: both taken, --force winning silently for one file and overwriting for a batch."""
    rc, _, err = run(capsys, "fit-brdf", str(tmp_path / "missing.binary"), "--force", "--skip-existing")
    one_line_error(rc, err, "fit-brdf", "--force and --skip-existing")


def _fitted(tmp_path):
    """A MERL file name and its output directory holding a params.json (an earlier fit)."""
    path = tmp_path / "gold.binary"
    path.write_bytes(b"")
    out = tmp_path / "gold_fit"
    out.mkdir()
    report = {"params": {"eta": 1.5, "alpha": 0.2, "beta": 1.0, "kappa": 3.0, "k_s": [1, 1, 1], "k_b": [1, 1, 1]},
              "at_bound": [], "log10_rmse": {"all_usable_bins": 0.1}, "n_usable_bins": 10}
    (out / "params.json").write_text(json.dumps(report))
    return path, out


def test_fit_brdf_skip_existing_with_one_file_skips_it(capsys, tmp_path):
    """Before: one FILE with --skip-existing was refused as existing (pass --force) although its fit exists."""
    path, out = _fitted(tmp_path)
    stamp = os.stat(out / "params.json").st_mtime_ns
    rc, stdout, err = run(capsys, "fit-brdf", str(path), "--skip-existing", "-q")
    assert rc == 0, err
    assert "gold: eta 1.5" in stdout and "skipped" in stdout and os.stat(out / "params.json").st_mtime_ns == stamp


def test_fit_brdf_jobs_with_one_file_says_what_it_does(capsys, tmp_path):
    """Before: --jobs dropped silently with one FILE; now one line says it is fitted in this process."""
    path, _ = _fitted(tmp_path)
    rc, _, err = run(capsys, "fit-brdf", str(path), "--skip-existing", "--jobs", "3", "-q")
    assert rc == 0 and "--jobs 3: one FILE is fitted in this process" in err


# ---------------------------------------------------------------- --jobs: Ctrl-C


@pytest.fixture(scope="module")
def merl_files(tmp_path_factory):
    import numpy as np

    from fmbrdf_mi.brdf_fit import merl
    from fmbrdf_mi.brdf_fit.fitting import model_brdf

    d = tmp_path_factory.mktemp("merl")
    table = model_brdf({"eta": 1.55, "alpha": 0.23, "beta": 1.7, "kappa": 15.0, "k_s": [0.5, 0.6, 0.7],
                        "k_b": [0.3, 0.1, 0.05]})
    table = table * np.exp(0.2 * np.random.default_rng(1).standard_normal(table.shape))   # not fitted exactly
    for name in ("a", "b", "c", "d"):
        merl.write_merl(d / f"{name}.binary", table)
    return d


def test_ctrl_c_stops_a_fit_brdf_batch_promptly(tmp_path, merl_files):
    out = tmp_path / "fits"
    (out / "a").mkdir(parents=True)
    (out / "a" / "params.json").write_text('{"earlier": true}')
    (out / "a" / "slices.png").write_bytes(b"earlier")
    proc = start_command("fit-brdf", str(merl_files), "-o", str(out), "--jobs", "2", "--force", "--full-grid",
                  "--samples", "400000")
    line = "-"
    while line and "[fit-brdf] batch of" not in line:   # the batch's first line: the workers start now
        line = proc.stderr.readline()
    assert "[fit-brdf] batch of 4 materials" in line, line
    time.sleep(4)                            # the workers are fitting (each fit takes far longer)
    assert proc.poll() is None, "the batch ended before it was interrupted"
    proc.send_signal(signal.SIGINT)
    t0 = time.time()
    try:
        proc.wait(45)
    except subprocess.TimeoutExpired:    # what is still running, for the failure's message
        ps = subprocess.run(["ps", "-o", "pid,stat,wchan:24,etime,args", "-g", str(proc.pid)], capture_output=True,
                            text=True).stdout
    rc, err = finish_command(proc, 1)
    assert rc is not None, f"the batch went on fitting after Ctrl-C:\n{ps}\n{err[-3000:]}"
    assert rc != 0 and time.time() - t0 < 47
    assert (out / "a" / "params.json").read_text() == '{"earlier": true}'
    assert (out / "a" / "slices.png").read_bytes() == b"earlier"
    left = sorted(os.path.relpath(os.path.join(dp, f), out) for dp, ds, fs in os.walk(out) for f in fs + ds)
    assert left == ["a", os.path.join("a", "params.json"), os.path.join("a", "slices.png")], left
    assert not os.path.exists(out / "summary.tsv")
