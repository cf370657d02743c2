"""Several materials per scene in the dataset generator (issue 25): ``shape.labels`` (a uv label image) and one
``[[material]]`` table per label.  Inside each material's pixels a sample equals the same sample rendered with
that material alone; the true label map and each material's parameters are written with the sample; bad configs
are refused in one line naming the key, before anything is written."""
import copy
import json

import numpy as np
import pytest

from conftest import one_line_error
from fmbrdf_mi.dataset import DatasetConfigError, generate, load_config, read_sample

A = {"eta": 1.5, "alpha": 0.2, "kappa": 5.0, "k_s": 0.8, "r_k": 0.6}
B = {"eta": 1.9, "alpha": 0.45, "beta": 1.2, "kappa": 40.0, "k_s": 0.5, "k_b": 0.9}

# every material value a constant: constants draw nothing from the sample's generator, so a config with one
# material of these values draws the same shape, pose, camera, light and render seed (checked below)
BASE = {
    "samples": 3, "seed": 5,
    "render": {"resolution": 32, "spp": 4, "variant": "llvm_ad_mono_polarized"},
    "shape": {"type": {"choice": ["sphere", "cube"]}, "rotate": True},
    "camera": {"elevation": {"uniform": [-30, 30]}, "azimuth": {"uniform": [-180, 180]}},
    "light": {"direction": {"cone": {"axis": [0, 0, 1], "angle": 40}}, "irradiance": {"uniform": [2, 4]}},
}


def _uv(path, m=2):
    """u in [0, 0.5): material 0, u in [0.5, 1): material 1 (and a third band for m = 3)."""
    from fmbrdf_mi.fit.inputs.labels import write_labels

    lab = np.zeros((16, 48), int)
    for k in range(1, m):
        lab[:, k * 48 // m:] = k
    write_labels(path, lab)


def _several(**shape):
    cfg = copy.deepcopy(BASE)
    cfg["shape"].update({"labels": "uv.png"}, **shape)
    cfg["material"] = [dict(A), dict(B)]
    return cfg


def _alone(material):
    cfg = copy.deepcopy(BASE)
    cfg["material"] = dict(material)
    return cfg


def _interior(lab, m):
    """Pixels whose label and all 8 neighbours' labels are m: no pixel footprint reaches another material."""
    h, w = lab.shape
    pad = np.pad(lab, 1, constant_values=-1)
    inside = np.ones_like(lab, bool)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            inside &= pad[1 + dy:h + 1 + dy, 1 + dx:w + 1 + dx] == m
    return inside


def test_two_material_samples_equal_each_material_alone(tmp_path):
    """Each sample (spheres and cubes, random rotation, camera and light) of a two-material dataset equals, on
    the interior pixels of each material's label, the sample of the dataset of that material alone (plain
    ``fmbrdf`` BSDF, no blend, no label image): the same Mitsuba sampler seed and sample count, so the only
    difference allowed is float rounding (relative 1e-5; the blend weight there is exactly 0 or 1).  Each
    material covers interior pixels in every sample, over 100 in all."""
    _uv(tmp_path / "uv.png")
    generate(_several(), tmp_path / "two", base_dir=tmp_path, progress=False)
    generate(_alone(A), tmp_path / "a", base_dir=tmp_path, progress=False)
    generate(_alone(B), tmp_path / "b", base_dir=tmp_path, progress=False)
    shapes, covered = set(), [0, 0]
    for i in range(3):
        two = read_sample(tmp_path / "two", i)
        lab = two["labels"]
        shapes.add(two["label"]["shape"]["type"])
        assert np.array_equal(lab >= 0, two["mask"])
        for m, ref in ((0, "a"), (1, "b")):
            one = read_sample(tmp_path / ref, i)
            # the same draw apart from the material: geometry, light and render seed
            for key in ("camera", "light", "render", "shape"):
                assert one["label"][key] == two["label"][key], key
            np.testing.assert_array_equal(one["mask"], two["mask"])
            inside = _interior(lab, m)
            assert inside.sum() >= 5, (i, m, inside.sum())
            covered[m] += int(inside.sum())
            ref_px = one["stokes"][:3, inside]
            assert ref_px[0].max() > 0
            np.testing.assert_allclose(two["stokes"][:3, inside], ref_px, rtol=1e-5,
                                       atol=1e-7 * one["stokes"][0].max())
        # and not the other material's render: the comparison can fail
        other = read_sample(tmp_path / "b", i)["stokes"][0, _interior(lab, 0)]
        assert np.max(np.abs(other - two["stokes"][0, _interior(lab, 0)])) > 1e-2 * other.max()
    assert shapes == {"sphere", "cube"} and min(covered) >= 100, covered


def test_metadata_and_labels_round_trip(tmp_path):
    """Per-material parameters drawn per sample are in the sample's label (= the config's draw), the label map
    PNG reads back through the fit's ``--materials`` reader as the map, its pixel counts are in the label,
    dataset.json records the uv label image and its SHA-256, the manifest lists the label files."""
    import hashlib

    from fmbrdf_mi.fit.inputs.labels import read_labels

    _uv(tmp_path / "uv.png", 3)
    cfg = _several()
    cfg["samples"] = 2
    cfg["shape"]["type"] = "sphere"
    cfg["material"] = [{"eta": {"uniform": [1.3, 1.6]}, "alpha": {"loguniform": [0.05, 0.5]}},
                       {"eta": {"uniform": [1.7, 2.2]}, "r_k": {"uniform": [0.1, 2.0]}},
                       {"k_b": 0.3}]
    generate(cfg, tmp_path / "out", base_dir=tmp_path, progress=False)
    loaded = load_config(cfg, base_dir=tmp_path)
    manifest = [json.loads(x) for x in (tmp_path / "out" / "manifest.jsonl").read_text().splitlines()]
    etas = []
    for i in range(2):
        s = read_sample(tmp_path / "out", i)
        label = s["label"]
        assert label == manifest[i] and "material" not in label
        assert label["materials"] == loaded.draw(i)["materials"]
        assert set(label["materials"][2]) == {"eta", "alpha", "beta", "kappa", "k_s", "k_b"}
        assert 1.3 <= label["materials"][0]["eta"] < 1.6 and 1.7 <= label["materials"][1]["eta"] < 2.2
        etas.append(label["materials"][0]["eta"])
        lab = read_labels(tmp_path / "out" / label["files"]["labels"])
        np.testing.assert_array_equal(lab, s["labels"])
        assert label["labels"] == {"uv_labels": "uv.png", "pixels": [int(np.sum(lab == m)) for m in range(3)]}
        assert all(c > 0 for c in label["labels"]["pixels"]) and np.array_equal(lab >= 0, s["mask"])
    assert etas[0] != etas[1]
    record = json.loads((tmp_path / "out" / "dataset.json").read_text())
    assert record["config"]["shape"]["labels"] == "uv.png"
    assert record["config"]["shape"]["labels_sha256"] == hashlib.sha256((tmp_path / "uv.png").read_bytes()).hexdigest()
    assert len(record["config"]["material"]) == 3 and "labels" in record["conventions"]


def test_single_material_config_is_unchanged():
    """Without shape.labels the config, its canonical form and its draws are as before (a resumed dataset's
    dataset.json still matches): the material stays a table and draws the same values."""
    cfg = load_config(_alone(A))
    assert cfg.canonical()["material"] == {k: v for k, v in A.items()} | {"beta": 2.0}
    assert "labels" not in cfg.canonical()["shape"] and "materials" not in cfg.draw(0)
    assert cfg.draw(0)["material"] == dict(A, beta=2.0)


@pytest.mark.parametrize("change,message", [
    ({"shape.labels": "missing.png"}, "shape.labels: label image 'missing.png' not found"),
    ({"shape.labels": "uv.txt"}, "shape.labels: expected a uv label image file name (.png or .npy"),
    ({"material": [A, B, B]}, "shape.labels: uv.png has 2 materials (labels 0 .. 1) but material lists 3"),
    ({"material": A}, "material: shape.labels uv.png has 2 materials (labels 0 .. 1): give material as 2"),
    ({"shape.labels": None}, "material: several materials ([[material]] tables, a list) need shape.labels"),
    ({"material": [A, dict(B, eta={"uniform": [1.5, 3.5]})]}, "material[1].eta.uniform: high 3.5 outside (1, 3]"),
    ({"material": [dict(A, k_s=-1), B]}, "material[0].k_s: -1 outside [0, inf)"),
    ({"material": [A, dict(B, r_k=0.5)]}, "material[1]: give the body albedo as k_b or as r_k"),
    ({"material": [A, dict(B, etta=1.5)]}, "material[1].etta: unknown key"),
    ({"shape.labels": "gap.png", "material": [A, B, B]}, "shape.labels: gap.png has no texel of material 1"),
    ({"shape.labels": "hole.png"}, "every texel of the shape's uv needs a material"),
])
def test_bad_material_configs_name_the_key(tmp_path, change, message):
    from fmbrdf_mi.fit.inputs.labels import write_labels

    _uv(tmp_path / "uv.png")
    gap = np.zeros((4, 4), int)
    gap[:, 2:] = 2
    write_labels(tmp_path / "gap.png", gap)
    hole = np.zeros((4, 4), int)
    hole[0, 0], hole[:, 2:] = -1, 1
    write_labels(tmp_path / "hole.png", hole)
    cfg = _several()
    for key, value in change.items():
        if key == "shape.labels":
            if value is None:
                del cfg["shape"]["labels"]
            else:
                cfg["shape"]["labels"] = value
        else:
            cfg[key] = value
    with pytest.raises(DatasetConfigError) as err:
        load_config(cfg, base_dir=tmp_path)
    assert message in str(err.value)
    assert "\n" not in str(err.value)


def test_command_line_bad_materials_is_one_line_and_writes_nothing(tmp_path, capsys):
    from fmbrdf_mi.cli import main

    _uv(tmp_path / "uv.png", 3)
    cfg = _several()
    (tmp_path / "c.json").write_text(json.dumps(cfg))
    rc = main(["dataset", "--config", str(tmp_path / "c.json"), "--out", str(tmp_path / "out"), "-q"])
    one_line_error(rc, capsys.readouterr().err, "dataset", "shape.labels", "3 materials", "material lists 2")
    assert not (tmp_path / "out").exists()
    # a mesh without uv coordinates: refused before anything is written
    (tmp_path / "tri.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    _uv(tmp_path / "uv.png")
    cfg["shape"]["type"] = "tri.obj"
    with pytest.raises(ValueError, match="shape.labels: mesh 'tri.obj' has no uv coordinates"):
        generate(cfg, tmp_path / "out", base_dir=tmp_path, progress=False)
    assert not (tmp_path / "out").exists()
