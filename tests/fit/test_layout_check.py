"""Issue 24, "a mirrored polariser layout goes unnoticed": after a raw-mosaic likelihood fit with a poor chi^2,
``fmbrdf-mi fit`` fits the mirrored layout (45 and 135 deg swapped) too and, when it explains the data much
better, says so in one line naming ``--layout``.  Before: the swapped capture was fitted to nonsense without a
word."""
import json

import pytest

from conftest import run

from fmbrdf_mi.fit.cli import layout_check as LC


def _report(objective="likelihood", chi2=800.0, samples=320, converged=True, misfit=True, demosaic="bilinear",
            layout=((90, 135), (45, 0))):
    return {"models": {"fmbrdf": {"objective": objective, "loss_terms": {"chi2": chi2, "samples": samples},
                                  "converged": converged, "uncertainty": {"misfit": misfit}}},
            "reproduce": {"images": [{"settings": {"demosaic": demosaic, "layout": [list(r) for r in layout]}}]}}


def test_mirrored_layout_swaps_45_and_135():
    assert LC.mirrored(((90, 45), (135, 0))) == ((90, 135), (45, 0))
    assert LC.mirrored(LC.mirrored(((0, 45), (135, 90)))) == ((0, 45), (135, 90))
    assert LC.layout_text(((90, 135), (45, 0))) == "90,135,45,0"


@pytest.mark.parametrize("kw,want", [
    ({}, True),
    ({"misfit": False, "converged": False}, True),           # stopped before convergence
    ({"misfit": False}, False),                              # converged, no misfit
    ({"chi2": 400.0}, False),                                # chi^2 per sample 1.25: near 1, not poor
    ({"objective": "paper"}, False),                         # not the likelihood
    ({"demosaic": None}, False),                             # not a raw mosaic (angle images, Stokes EXR)
])
def test_which_fits_are_checked(kw, want):
    assert LC.needs_check(_report(**kw), "fmbrdf") is want


def test_a_fit_of_the_right_layout_is_not_refitted():
    def no_fit(**kw):
        raise AssertionError("refitted")

    assert LC.mirrored_layout_hint(_report(chi2=380.0), {"model": "fmbrdf"}, no_fit, progress=False) is None


def test_a_swapped_capture_is_named(capsys, tmp_path, no_figures):
    """A raw render of the built-in sphere decoded with 45 and 135 swapped (--layout 90,135,45,0): chi^2 per
    sample 2.5, against 1.2 for the right layout, which the line names."""
    rc, _, err = run(capsys, "render", str(tmp_path / "c.exr"), "--no-previews", "-q", "--variant",
                     "llvm_ad_mono_polarized", "--res", "32", "--spp", "16", "--raw", "--raw-seed", "1")
    assert rc == 0, err
    out = tmp_path / "fit"
    rc, _, err = run(capsys, "fit", str(tmp_path / "c_raw.png"), "--layout", "90,135,45,0", "--max-iter", "10",
                     "--intervals", "fisher", "-o", str(out), "-q")
    assert rc in (0, 3), err
    lines = [ln for ln in err.splitlines() if "mirrored polariser layout" in ln]
    assert len(lines) == 1, err
    assert "rerun with --layout 90,45,135,0" in lines[0] and "45 and 135 deg swapped" in lines[0]
    # the first fit's outputs are those of the layout given; the mirrored fit left nothing behind
    rep = json.loads((out / "fit.json").read_text())
    assert rep["reproduce"]["images"][0]["settings"]["layout"] == [[90, 135], [45, 0]]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.exr", "c_raw.json", "c_raw.png", "fit"]
