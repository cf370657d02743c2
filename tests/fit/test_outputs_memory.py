"""The memory of ``fmbrdf-mi fit``'s output stage: the re-render of a whole frame for its figures
(:func:`fmbrdf_mi.fit.evaluate.predict.predict_image`) makes the frame's footprint directions a block of pixels
at a time, never all of them in float64 at once, and predicts the same image whatever the block size (each
pixel's prediction is its own elementwise computation)."""
import numpy as np
import pytest

from fmbrdf_mi.fit.evaluate import pixel_model, predict
from fmbrdf_mi.fit.inputs.observations import Observation
from fmbrdf_mi.synthetic.spheres import capture_observation, smooth_texture, textured_sphere

SHAPE = {"eta": 1.45, "alpha": 0.25, "beta": 1.0, "kappa": 10.0}


@pytest.fixture(scope="module")
def capture():
    """A raw capture of a textured sphere, 24 x 24 super-pixels, with the demosaicking footprint (K points a
    pixel), and per-pixel albedo maps (NaN off the object)."""
    res = 24
    ks, kb = smooth_texture(res)
    obs, _ = capture_observation(textured_sphere(SHAPE, ks, kb, res=res), seed=3)
    maps = {"k_s": np.where(obs.mask, ks, np.nan), "k_b": np.where(obs.mask, kb, np.nan)}
    return obs, maps


def test_the_re_render_makes_the_directions_a_block_at_a_time(capture, monkeypatch):
    obs, maps = capture
    k = len(obs.sample_geometry(np.zeros(1, np.int64))[2])
    assert k > 1, "the capture should have a footprint of several points a pixel"
    whole = predict.predict_image("fmbrdf", SHAPE, obs, maps=maps)
    pixels = int(obs.mask.sum())
    block = 7        # pixels a block: not a divisor of the pixel count, so the last block is a short one
    monkeypatch.setattr(pixel_model, "PIECE_DIRECTIONS", block * k)
    asked = []
    real = Observation.sample_geometry

    def recording(self, idx, footprint="own"):
        asked.append(len(idx))
        return real(self, idx, footprint)

    monkeypatch.setattr(Observation, "sample_geometry", recording)
    blocks = predict.predict_image("fmbrdf", SHAPE, obs, maps=maps)
    assert pixels > 10 * block and max(asked) <= block
    np.testing.assert_array_equal(blocks, whole)
    on = obs.mask & np.isfinite(obs.stokes[0])
    assert np.all(np.isfinite(blocks[:, on])) and np.all(blocks[:, ~obs.mask] == 0)
