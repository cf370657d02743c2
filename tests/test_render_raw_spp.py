"""``render --raw`` renders with at least RAW_MIN_SPP samples per pixel unless --spp is given.

At the scene's default sample count the renderer's Monte Carlo noise (which no camera has, and which the
fit's camera-noise model does not know) biases kappa (docs/benchmarks/coverage.md).  Checked through what
the files record: the raw sidecar's and the EXR's sample counts.
"""
import json

import pytest

from fmbrdf_mi.cli import main
from fmbrdf_mi.render import RAW_MIN_SPP


@pytest.mark.parametrize("extra, raw, want", [
    ([], True, RAW_MIN_SPP),          # --raw without --spp: at least RAW_MIN_SPP
    (["--spp", "2"], True, 2),        # the user's --spp wins
    ([], False, 64),                  # no --raw: the scene's own 64
])
def test_raw_render_sample_count(tmp_path, capsys, extra, raw, want):
    out = tmp_path / "x.exr"
    args = ["render", str(out), "--variant", "llvm_ad_mono_polarized", "--res", "8", "--no-previews",
            *(["--raw"] if raw else []), *extra]
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert f"{want} spp" in printed, printed
    if raw:
        side = json.loads((tmp_path / "x_raw.json").read_text())
        assert side["parameters"]["spp"] == want and side["spp"] == want
