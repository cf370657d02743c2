"""The one result type (fmbrdf_mi/fit/result.py): what fit.json gets from it, and the reads older code used.

Every mode returns a :class:`FitResult`; ``to_json`` must write exactly the
keys fit.json had before the result types were merged (a single-image fit:
the fields without ``pixels``; a joint fit: those plus ``images`` and, with
free powers, ``powers``), so the files a user's scripts read do not change.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from fmbrdf_mi.fit.result import FitResult, json_default

SINGLE_KEYS = ["model", "params", "loss", "loss_terms", "std_errors", "history", "stop_reason", "n_pixels",
               "n_outliers", "timings", "options", "weakly_identified", "converged", "objective", "uncertainty",
               "noise", "pixels_excluded", "starts"]


def _result(**kw):
    base = dict(model="fmbrdf", params={"eta": 1.5, "k_s": np.float64(0.8)}, loss=1.0, loss_terms={"chi2": 1.0},
                std_errors={"eta": 0.01}, history=[], stop_reason="ok", n_pixels=10, n_outliers=0,
                timings={"total": 1.0}, options={"model": "fmbrdf"}, pixels=np.arange(10))
    base.update(kw)
    return FitResult(**base)


def test_single_image_json_keys_in_order():
    d = _result().to_json()
    assert list(d) == SINGLE_KEYS
    json.dumps(d, default=json_default)      # serialisable


def test_joint_and_free_power_json_keys():
    images = [{"name": "a", "n_pixels": 5}, {"name": "b", "n_pixels": 5}]
    d = _result(images=images, pixels=[np.arange(5), np.arange(5)]).to_json()
    assert list(d) == SINGLE_KEYS + ["images"] and d["images"] == images
    d = _result(images=images, powers={"values": [1.0, 0.6]}).to_json()
    assert list(d) == SINGLE_KEYS + ["images", "powers"]


def test_arrays_and_details_stay_out_of_the_json():
    n = np.zeros((4, 4, 3))
    r = _result(normals=n, mask=np.ones((4, 4), bool), details={"chi2_per_dof": 1.1, "internal": {"a_s": [1.0]}})
    d = r.to_json()
    assert not {"normals", "mask", "details", "pixels"} & set(d)
    assert r.normals is n and r.pixels is not None     # to_json leaves the result itself untouched


def test_dict_style_reads_fields_then_details():
    r = _result(details={"chi2_per_dof": 1.1}, channels=["R", "G", "B"])
    assert r["params"] is r.params and r["channels"] == ["R", "G", "B"] and r["chi2_per_dof"] == 1.1
    with pytest.raises(KeyError):
        r["nothing"]
