import contextlib
import os
import signal
import sys

import numpy as np
import pytest

HERE = os.path.dirname(os.path.abspath(__file__))

# The Ctrl-C tests send SIGINT to a command, which must start with SIGINT's default action; a shell that starts
# the suite in the background (`cmd &` without job control, as CI runners and nohup do) starts it with SIGINT
# ignored, and a child inherits an ignored signal (a handled one is reset to the default at exec).
if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)
sys.path.insert(0, HERE)
sys.path.insert(0, os.path.join(os.path.dirname(HERE), "tools"))


#: The ``variant`` fixture's variant: FMBRDF_MI_TEST_VARIANT=cuda_ad_mono_polarized runs the tests that take it
#: on a GPU (against the same NumPy references).
TEST_VARIANT = os.environ.get("FMBRDF_MI_TEST_VARIANT", "llvm_ad_mono_polarized")


@pytest.fixture
def variant():
    """Polarised monochrome variant with the plugin registered (float32 JIT; :data:`TEST_VARIANT`)."""
    import mitsuba as mi

    mi.set_variant(TEST_VARIANT)
    import fmbrdf_mi

    fmbrdf_mi.register()
    return mi


def make(mi, **kw):
    d = {"type": "fmbrdf", "k_s": 1.0, "k_b": 1.0}
    d.update(kw)
    return mi.load_dict(d)


def make_float32(mi, **kw):
    """:func:`make` with float32 tables: by default (``tables="compact"``) the
    plugin stores every Mueller ratio in 16-bit fixed point when no gradients
    are wanted (within 3.1e-5 of M00), whose rounding would swamp a central
    difference with a small step."""
    return make(mi, tables="float32", **kw)


def small_sphere_paths(light, spp, res=24, seed=3):
    """A res x res render of the built-in sphere (unit albedos, stokes over direct) and its
    usable pixels, with a RenderEvaluator and a PixelEvaluator of FMBRDF on those pixels:
    the two differentiable paths of the fit, on the same object.
    Returns (scene, obs, idx, render_evaluator, pixel_evaluator)."""
    import mitsuba as mi

    from fmbrdf_mi import scene as S
    from fmbrdf_mi.fit import FitOptions, Observation, usable_pixels
    from fmbrdf_mi.fit.evaluate.models import FMBRDF
    from fmbrdf_mi.fit.evaluate.pixel_model import PixelEvaluator, RenderEvaluator, set_variant

    set_variant()
    scene = mi.load_dict(S.sphere_scene({"k_s": 1.0, "k_b": 1.0}, light_dir=light, irradiance=1.0,
                                        resolution=res, spp=spp))
    n, v, m = S.sphere_geometry(res)
    obs = Observation(np.ones((3, res, res)), m, n, v, light)
    idx = usable_pixels(obs, FitOptions(erode=1))
    rev = RenderEvaluator(FMBRDF, scene, "sphere.bsdf", idx, spp=spp, seed=seed)
    pev = PixelEvaluator(FMBRDF, n.reshape(-1, 3)[idx], v.reshape(-1, 3)[idx], light)
    return scene, obs, idx, rev, pev


def fresnel_T(theta, eta):
    """(T_s, T_p) at incidence angle theta (independent NumPy formula)."""
    c = np.cos(theta)
    ct = np.sqrt(1 - np.sin(theta) ** 2 / eta ** 2)
    rs = (c - eta * ct) / (c + eta * ct)
    rp = (eta * c - ct) / (eta * c + ct)
    return 1 - rs ** 2, 1 - rp ** 2


@contextlib.contextmanager
def figures_not_drawn(keep=()):
    """Within it, figures are built but neither laid out nor drawn: matplotlib's ``Figure.savefig`` leaves an
    empty file under the name it is given, except for the file names in ``keep`` (drawn, not laid out).  For
    the tests of commands that read none of the figures they write, only which files there are (laying out
    and rasterising is much of a small fit command's time); the figures' content is tested elsewhere."""
    from unittest import mock

    from matplotlib.figure import Figure

    draw = Figure.savefig

    def savefig(self, fname, *args, **kwargs):
        if not isinstance(fname, (str, os.PathLike)) or os.path.basename(fname) in keep:
            return draw(self, fname, *args, **kwargs)
        open(fname, "wb").close()

    with mock.patch.object(Figure, "savefig", savefig), \
            mock.patch.object(Figure, "tight_layout", lambda self, *args, **kwargs: None):
        yield


@pytest.fixture
def no_figures():
    """:func:`figures_not_drawn` for the whole test."""
    with figures_not_drawn():
        yield


# ---------------------------------------------------------------- the commands' one-line errors
def run(capsys, *argv):
    """``fmbrdf-mi ARGV`` in this process: (exit status, stdout, stderr)."""
    from fmbrdf_mi import cli

    rc = cli.main(list(argv))
    out, err = capsys.readouterr()
    return rc, out, err


@pytest.fixture
def a_file(tmp_path):
    """A regular file where a command's output directory (or a folder above it) is named."""
    f = tmp_path / "plain_file"
    f.write_text("not a directory")
    return f


def textured_capture(shape, res, seed, amplitude=0.3, light=(-0.5, 0.5, 1.0)):
    """One image of a ``res`` x ``res`` sphere with the smooth texture under the default camera's noise
    (``seed``): the per-pixel fits' test capture."""
    from fmbrdf_mi.sensor.camera import CameraModel
    from fmbrdf_mi.synthetic.spheres import capture_observation, smooth_texture, textured_sphere

    ks, kb = smooth_texture(res, amplitude=amplitude)
    return capture_observation(textured_sphere(shape, ks, kb, res=res, light=light), CameraModel(), seed=seed)[0]


def one_line_error(rc, err, command, *words):
    """A user error as the project promises it: exit status 1, one line ``fmbrdf-mi COMMAND: error: ...``
    naming each of ``words``, no traceback."""
    assert rc == 1, err
    assert "Traceback" not in err, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"fmbrdf-mi {command}: error: "), err
    for w in words:
        assert w in lines[0], (w, lines[0])


def fit_record(tmp_path, joint=False):
    """A fit.json record (single image, or a 2-image manifest when ``joint``) of a fit of raw.npy with its
    SHA-256 recorded; other.npy lies beside it, never hashed (the ``--from`` checks' test inputs)."""
    import hashlib

    np.save(tmp_path / "raw.npy", np.full((16, 16), 100.0))
    np.save(tmp_path / "other.npy", np.full((16, 16), 200.0))
    hashes = {str(tmp_path / "raw.npy"): hashlib.sha256((tmp_path / "raw.npy").read_bytes()).hexdigest()}
    if not joint:
        args = {"inputs": str(tmp_path / "raw.npy"), "sphere": "8,8,6", "light": [0, 0, 1], "model": "fmbrdf",
                "max_iter": 1, "starts": 1}
        return {"reproduce": {"kind": "single", "command": "fmbrdf-mi fit ...", "cwd": str(tmp_path),
                              "arguments": args, "files_sha256": hashes}}
    spec = {"input": str(tmp_path / "raw.npy"), "light": [0, 0, 1], "power": 1.0, "holdout": False, "name": "a",
            "options": {"sphere": "8,8,6"}}
    images = [{"name": n, "spec": dict(spec, name=n, light=light)} for n, light in (("a", [0, 0, 1]), ("b", [0.3, 0, 1]))]
    return {"reproduce": {"kind": "manifest", "command": "fmbrdf-mi fit ...", "cwd": str(tmp_path),
                          "arguments": {"model": "fmbrdf", "max_iter": 1, "free_power": False},
                          "images": images, "files_sha256": hashes}}


def start_command(*argv, **kw):
    """``python -m fmbrdf_mi ARGV`` in a new process group (so that a test can send it SIGINT), this checkout
    first on its path, Dr.Jit on one thread; stdout and stderr piped as text."""
    import subprocess

    env = dict(os.environ, PYTHONPATH=os.path.dirname(HERE) + os.pathsep + os.environ.get("PYTHONPATH", ""),
               DRJIT_NUM_THREADS="1")
    return subprocess.Popen([sys.executable, "-m", "fmbrdf_mi", *argv], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True, **kw)


def finish_command(proc, timeout):
    """(exit status, stderr) of ``proc`` within ``timeout`` seconds; None as the status if it is still
    running then (its whole process group is killed)."""
    import signal
    import subprocess

    try:
        _, err = proc.communicate(timeout=timeout)
        return proc.returncode, err
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        _, err = proc.communicate()
        return None, err


# ---------------------------------------------------------------- the two tiers
#: The slow tier (``python -m pytest -q tests -m slow``; ``.ci/run`` runs both tiers): coverage loops over
#: noise seeds, end-to-end refinements, the documentation's code and tutorials.  Node-id prefixes, marked
#: here in one place so that the fast tier's budget is tuned in one file; tests may also carry
#: ``@pytest.mark.slow`` themselves.  An entry naming a test that a collected file does not define is an error
#: (a renamed test would otherwise move silently into the fast tier).
SLOW = (
    "tests/test_docs.py",
    "tests/fit/test_objectives_likelihood.py::test_likelihood_intervals_cover_the_truth",
    "tests/fit/test_objectives_likelihood.py::test_paper_loss_sandwich_intervals_cover_the_truth",
    "tests/fit/test_uncertainty_incidental.py::test_sandwich_matches_the_spread_over_noise_draws",
    "tests/fit/test_albedo_prior.py::test_chi2_degrees_of_freedom_rule_by_simulation",
    "tests/fit/test_inputs_authors.py::test_manifest_and_repeated_light_give_the_authors_fit",
    "tests/fit/test_api_joint.py::test_one_image_is_the_list_of_one",
    "tests/fit/test_api_normal_joint.py::test_joint_lowers_the_energy_monotonically_to_a_minimum_near_the_truth",
    "tests/fit/test_api_normal_joint.py::test_refine_normals_command",
    "tests/fit/test_layout_check.py::test_a_swapped_capture_is_named",
    "tests/fit/test_problem_free_power.py::test_free_powers_are_recovered_and_fixed_powers_bias_the_fit",
    "tests/fit/test_api_fitting_quadrature.py",
    "tests/fit/test_uncertainty_profile.py::test_a_parameter_at_its_bound_gets_a_profile_end_an_independent_fit_confirms",
    "tests/fit/test_uncertainty_profile.py::test_cli_intervals_option_is_recorded_and_rerun",
    "tests/fit/test_uncertainty_profile.py::test_intervals_profile_gives_every_end_from_the_profile_a_brute_force_profile_confirms",
    "tests/fit/test_inputs_authors.py::test_joint_fits_rerun_from_fit_json",
    "tests/fit/test_cli_materials.py::test_manifest_with_materials",
    "tests/fit/test_cli_materials.py::test_command_fits_two_materials_and_reruns",
    "tests/fit/test_api_colour_per_pixel.py::test_joint_command_relights_a_held_out_mosaic_with_the_maps",
    "tests/fit/test_api_colour.py::test_colour_fit_recovers_per_channel_albedos",
    "tests/fit/test_uncertainty_misfit.py::test_misfit_with_free_powers_and_per_pixel_albedos",
    "tests/fit/test_uncertainty_misfit.py::test_misfit_of_the_normal_refinement",
    "tests/fit/test_outputs_colour_joint.py::test_fit_cli_colour_joint_manifest",
    "tests/fit/test_outputs_colour_joint.py::test_joint_colour_fit_of_one_image_twice_halves_the_variance",
    "tests/test_fit_brdf.py::test_jobs_run_in_worker_processes_with_the_same_results",
    "tests/fit/test_outputs_writer.py::test_ctrl_c_in_the_write_phase_keeps_the_earlier_output",
    "tests/fit/test_solve_explore.py::test_explored_fit_ends_at_the_all_pixel_optimum",
    "tests/fit/test_solve_explore.py::test_the_subsample_estimate_is_never_returned",
    "tests/fit/test_solve_explore.py::test_progress_says_where_each_phase_runs",
    "tests/fit/test_solve_explore.py::test_below_the_threshold_the_fit_is_the_plain_one",
    "tests/test_mueller_fit.py::test_kappa_at_its_bound_gets_the_profile_likelihood_limit",
    "tests/test_synthetic_mesh_object.py::test_a_noise_free_capture_is_fitted_to_the_truth",
    "tests/test_reference.py::test_eval_matches_reference[mat1]",
    "tests/test_reference.py::test_eval_matches_reference[mat2]",
    "tests/test_reference.py::test_eval_matches_reference[mat3]",
    "tests/fit/test_uncertainty_profile.py::test_fit_reports_the_kind_of_every_interval",
)


def pytest_collection_modifyitems(config, items):
    root = os.path.dirname(HERE)
    defined = {}        # file -> the names its module defines (a selection by node id collects only some tests)
    for item in items:
        node = os.path.relpath(str(item.path), root).replace(os.sep, "/") + item.nodeid[item.nodeid.find("::"):]
        if getattr(item, "module", None) is not None:
            defined.setdefault(node.split("::")[0], set(vars(item.module)))
        for prefix in SLOW:
            if node == prefix or node.startswith(prefix + "::") or node.startswith(prefix + "["):
                item.add_marker(pytest.mark.slow)
    stale = [p for p in SLOW if "::" in p and p.split("::")[0] in defined
             and p.split("::")[1].split("[")[0] not in defined[p.split("::")[0]]]
    if stale:
        raise pytest.UsageError("tests/conftest.py SLOW names a test its file does not define: " + ", ".join(stale))
