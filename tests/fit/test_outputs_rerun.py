"""An edited fit.json given to ``fmbrdf-mi fit --from fit.json -o DIR`` is refused in one line
naming the file and the key (fmbrdf_mi.fit.outputs.rerun); before, unknown keys, wrong
types and a removed ``joint`` block ended in TypeError tracebacks.  No fit runs here: every record is
refused before one would start."""
import json

import pytest

from conftest import fit_record, one_line_error, run

from fmbrdf_mi.cli import main


def _set(d, key, value):
    *path, last = key.split(".")
    for p in path:
        d = d[int(p)] if p.isdigit() else d[p]
    if value is KeyError:
        del d[last]
    else:
        d[last] = value


@pytest.mark.parametrize("joint,key,value,words", [
    (False, "reproduce.arguments.bogus", 1, ["reproduce.arguments: unknown key(s) bogus", "valid: inputs"]),
    (False, "reproduce.arguments.inputs", 5, ["reproduce.arguments.inputs", "file name", "5"]),
    (False, "reproduce.arguments.inputs", KeyError, ["reproduce.arguments.inputs", "file name", "None"]),
    (False, "reproduce.kind", KeyError, ["reproduce.kind is missing", "older layout", "reproduce.command"]),
    (False, "reproduce.kind", "joint", ["reproduce.kind is 'joint'", "single, colour, manifest"]),
    (False, "reproduce.arguments.mask", [1], ["reproduce.arguments.mask", "file name"]),
    (False, "reproduce.arguments", 5, ["reproduce.arguments: expected a table"]),
    (False, "reproduce.cwd", 5, ["reproduce.cwd"]),
    (False, "reproduce.files_sha256", [1], ["reproduce.files_sha256"]),
    (False, "reproduce.arguments.model", [1], ["model", "fmbrdf"]),
    (False, "reproduce.arguments.starts", [1], ["starts", "integer"]),
    (False, "reproduce.arguments.bounds", 5, ["bounds", "NAME=LO:HI"]),
    (False, "reproduce.arguments.fixed", 5, ["fixed", "NAME=VALUE"]),
    (False, "reproduce.arguments.layout", 5, ["layout", "2x2"]),
    (False, "reproduce.arguments.conversion_gain", "2.4", ["conversion_gain"]),
    (True, "reproduce.kind", KeyError, ["reproduce.kind is missing", "older layout", "reproduce.command"]),
    (True, "reproduce.arguments.bogus", 1, ["reproduce.arguments: unknown key(s) bogus", "joint fit"]),
    (True, "reproduce.arguments.materials", 5, ["reproduce.arguments.materials", "file name", "5"]),
    (True, "reproduce.images", 5, ["joint-fit record is incomplete"]),
    (True, "reproduce.images.0.spec.input", 5, ["reproduce.images[0].spec: input", "file name"]),
    (True, "reproduce.images.0.spec.light", [[0, 0, 1]], ["reproduce.images[0].spec: light"]),
    (True, "reproduce.images.0.spec.power", "x", ["reproduce.images[0].spec: power"]),
    (True, "reproduce.images.0.spec.holdout", "no", ["reproduce.images[0].spec: holdout"]),
    (True, "reproduce.images.0.spec.options", 5, ["reproduce.images[0].spec: options"]),
    (True, "reproduce.images.0.spec.options.bogus", 1, ["options: unknown key(s) bogus"]),
    (True, "reproduce.images.0.spec.options.conversion_gain", "2.4",
     ["reproduce.images[0].spec: options: conversion_gain", "'2.4'"]),
])
def test_edited_fit_json_is_refused_in_one_line(tmp_path, capsys, joint, key, value, words):
    d = fit_record(tmp_path, joint)
    _set(d, key, value)
    path = tmp_path / "fit.json"
    path.write_text(json.dumps(d))
    rc = main(["fit", "--from", str(path), "-o", str(tmp_path / "out")])
    err = capsys.readouterr().err
    one_line_error(rc, err, "fit", *words)
    lines = err.strip().splitlines()
    if key.startswith("reproduce.arguments") and key.split(".")[-1] in ("bogus", "inputs", "mask", "arguments") \
            or "images" in key or key in ("reproduce.cwd", "reproduce.files_sha256", "reproduce.kind"):
        assert str(path) in lines[0]
    assert not (tmp_path / "out" / "fit.json").exists()


# ---------------------------------------------------------------- --from: records whose rerun cannot be verified
def _edit(d, tmp_path, what):
    rep = d["reproduce"]
    if what == "inputs":
        rep["arguments"]["inputs"] = str(tmp_path / "other.npy")
    elif what == "relative inputs":
        rep["arguments"]["inputs"] = "other.npy"
    elif what == "mask":
        rep["arguments"]["mask"] = str(tmp_path / "other.npy")
    elif what == "joint input":
        rep["images"][1]["spec"]["input"] = str(tmp_path / "other.npy")
    elif what == "joint mask":
        rep["images"][0]["spec"]["options"]["mask"] = str(tmp_path / "other.npy")
    elif what == "no hashes":
        del rep["files_sha256"]
    elif what == "refine":
        d.clear()
        d.update({"refine_normals": {"start": "ps"}, "reproduce": {"command": "fmbrdf-mi fit --authors OBJ "
                                                                               "--refine-normals -o out"}})
    elif what == "refine rounds":       # a record of the alternation rounds that --rounds set before the joint step
        d.clear()
        d.update({"refine_normals": {"start": "ps", "rounds": 2, "alternation": []},
                  "reproduce": {"command": "fmbrdf-mi fit --authors OBJ --refine-normals --rounds 2 -o out"}})
    return d


@pytest.mark.parametrize("joint,what,words", [
    (False, "inputs", ["other.npy", "no recorded SHA-256"]),
    (False, "relative inputs", ["other.npy", "no recorded SHA-256"]),
    (False, "mask", ["other.npy", "no recorded SHA-256"]),
    (True, "joint input", ["other.npy", "no recorded SHA-256"]),
    (True, "joint mask", ["other.npy", "no recorded SHA-256"]),
    (False, "no hashes", ["files_sha256", "cannot be verified"]),
    (True, "no hashes", ["files_sha256", "cannot be verified"]),
    (False, "refine", ["--refine-normals are not supported", "reproduce.command"]),
    (False, "refine rounds", ["--refine-normals are not supported", "--rounds 2 -o out)", "without --rounds"]),
])
def test_from_record_that_cannot_be_verified_is_refused(capsys, tmp_path, joint, what, words):
    """Before: a record pointing at another file reran on it (its hash was never recorded), a record
    without files_sha256 reran unverified, a --refine-normals record was 'written by an older fmbrdf-mi?'."""
    import json

    path = tmp_path / "fit.json"
    path.write_text(json.dumps(_edit(fit_record(tmp_path, joint), tmp_path, what)))
    rc, _, err = run(capsys, "fit", "--from", str(path), "-o", str(tmp_path / "out"))
    one_line_error(rc, err, "fit", str(path), *words)
    assert not (tmp_path / "out").exists()
