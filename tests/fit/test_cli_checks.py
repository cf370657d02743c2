"""The command line's one table of which options each mode refuses or needs (fmbrdf_mi/fit/cli/command.py).

Every row of the table is exercised: each refused option, given alone, is
named in a one-line error for its mode, and the options that are not given
are not named; each option that needs another is refused without it.  End
to end, a refused combination stops ``fmbrdf-mi fit`` before any file is read
(the input named does not exist) with exit status 1 and no output directory.
"""
from __future__ import annotations

import argparse
import os

import pytest

from fmbrdf_mi.fit.cli.command import NEEDS, REFUSED, check_needs, given, named, refuse
from fmbrdf_mi.fit.cli.command import add_fit_arguments
from fmbrdf_mi.fit.errors import InputError

#: how to give each option of OPTIONS on the command line
GIVE = {"--baselines": ["--baselines"], "--relight": ["--relight", "b.exr"], "--path": ["--path", "render"],
        "--optimizer": ["--optimizer", "adam"], "--init": ["--init", "eta=1.5"], "--loss": ["--loss", "paper"],
        "--layout": ["--layout", "0,45,90,135"], "--dark-level": ["--dark-level", "3"],
        "--footprint": ["--footprint", "box"], "--free-power": ["--free-power"],
        "--area-points": ["--area-points", "3"], "--channel": ["--channel", "R"], "--light": ["--light", "0,0,1"],
        "--albedo": ["--albedo", "per-pixel"], "--materials": ["--materials", "labels.png"],
        "--albedo-smooth": ["--albedo-smooth", "0.1"], "--demosaic": ["--demosaic", "superpixel"],
        "--tol": ["--tol", "0.01"], "--time-limit": ["--time-limit", "5"],
        "--relight-light": ["--relight-light", "0,0,1"], "--relight-irradiance": ["--relight-irradiance", "2"]}
NEED_GIVE = {"--relight-light": ["--relight-light", "0,0,1"], "--holdout": ["--holdout", "1"],
             "--normals-start": ["--normals-start", "sphere"], "--smooth": ["--smooth", "0.5"],
             "--power-start": ["--power-start", "given"]}


def parse(argv):
    p = argparse.ArgumentParser()
    add_fit_arguments(p)
    return p.parse_args(["-o", "out", *argv])


def test_every_option_of_the_table_can_be_given():
    assert set(GIVE) == {f for flags, _, _ in REFUSED.values() for f in flags} and set(NEED_GIVE) == set(NEEDS)
    none = parse(["a.png"])
    for flag in GIVE:
        assert not given(none, flag), flag
        assert given(parse(["a.png", *GIVE[flag]]), flag), flag


@pytest.mark.parametrize("mode", sorted(REFUSED))
def test_each_refused_option_is_named_alone(mode):
    flags, head, _ = REFUSED[mode]
    refuse(parse(["a.png"]), mode)          # nothing refused given: no error
    for flag in flags:
        with pytest.raises(InputError) as e:
            refuse(parse(["a.png", *GIVE[flag]]), mode)
        msg = str(e.value)
        assert msg.startswith(head + ": ") and "\n" not in msg
        assert msg[len(head) + 2:].split(" not supported")[0].split(", ") == [named(parse(["a.png", *GIVE[flag]]),
                                                                                     flag)]


@pytest.mark.parametrize("flag", sorted(NEEDS))
def test_options_that_need_another(flag):
    check_needs(parse(["a.png"]))
    with pytest.raises(InputError, match=f"^{flag} needs "):
        check_needs(parse(["a.png", *NEED_GIVE[flag]]))


def test_refused_before_any_file_is_read(tmp_path, capsys):
    from fmbrdf_mi.cli import main

    out = tmp_path / "out"
    code = main(["fit", "--manifest", str(tmp_path / "missing.toml"), "--refine-normals", "--baselines", "-o",
                 str(out)])
    err = capsys.readouterr().err
    assert code == 1 and "--refine-normals: --baselines not supported" in err and "missing.toml" not in err
    assert not os.path.exists(out)


def test_defaults_table_matches_the_parser():
    """checks.DEFAULTS (what --from tells given options by) is the parser's: no option is 'given' by
    default, and each option given is named."""
    from fmbrdf_mi.fit.cli.command import DEFAULTS, given_options

    p = argparse.ArgumentParser()
    add_fit_arguments(p)
    defaults = {a.dest: a.default for a in p._actions if a.dest != "help"}
    assert {k: v for k, v in defaults.items() if k in DEFAULTS} == DEFAULTS
    assert all(v in (None, False) for k, v in defaults.items() if k not in DEFAULTS), defaults
    assert given_options(parse([])) == []
    assert given_options(parse(["--max-pixels", "0", "--seed", "0", "--channel", "R"])) == ["--channel", "--max-pixels"]


def test_colour_mosaics_take_per_pixel_albedos_not_materials():
    """Per-pixel albedo maps are fitted on colour mosaics (per period and channel, issue 25): --albedo is no longer
    refused there; several materials still are, and the normal refinement still refuses --albedo."""
    refuse(parse(["a.png", "--albedo", "per-pixel"]), "colour")
    assert "--albedo" not in REFUSED["colour"][0] and "--materials" in REFUSED["colour"][0]
    with pytest.raises(InputError, match="^colour polarisation mosaic: --materials not supported"):
        refuse(parse(["a.png", "--albedo", "per-pixel", "--materials", "labels.png"]), "colour")
    with pytest.raises(InputError, match="^--refine-normals: --albedo per-pixel not supported"):
        refuse(parse(["a.png", "--albedo", "per-pixel"]), "refine")


def test_every_option_is_on_the_command_line_with_its_help():
    """The parser is generated from the schema: every option with a flag is there, each with a help text."""
    from fmbrdf_mi.fit.api.options import OPTIONS

    p = argparse.ArgumentParser()
    add_fit_arguments(p)
    actions = {a.dest: a for a in p._actions if a.dest != "help"}
    assert set(actions) == {o.name for o in OPTIONS if o.flag is not None}
    assert all(a.help and "%(" not in (a.help % {"default": a.default}) for a in actions.values())
    assert actions["fixed"].option_strings == ["--fix"] and actions["from_json"].option_strings == ["--from"]


def test_typed_options_counts_values_at_their_default():
    """--from tells what was typed from the command line itself: an option typed at its default value counts
    (a value compared with the default would miss it), a repeated option too."""
    from fmbrdf_mi.fit.cli.command import typed_options

    typed = typed_options(["a.png", "--albedo", "shared", "--fix", "kappa=0", "--fix", "eta=1.5", "--baselines",
                           "-o", "x"])
    assert sorted(typed) == ["albedo", "baselines", "fixed", "inputs", "out"]
    assert sorted(typed_options(["--from", "f.json", "-o", "x"])) == ["from_json", "inputs", "out"]


def test_writing_functions_refuse_an_unknown_option(tmp_path):
    """fit_files / fit_colour_files take the schema's options of their record: a misspelt one is one line naming
    it (before: a TypeError of the signature), and nothing is read or written."""
    from fmbrdf_mi.fit.outputs.colour import fit_colour_files
    from fmbrdf_mi.fit.outputs.single import fit_files

    with pytest.raises(InputError, match=r"^fit_files\(\): unknown option\(s\) albedo_smoth \(valid: inputs, "):
        fit_files(str(tmp_path / "missing.exr"), str(tmp_path / "out"), albedo_smoth=0.1)
    with pytest.raises(InputError, match=r"^fit_colour_files\(\): unknown option\(s\) loss "):
        fit_colour_files(str(tmp_path / "missing.png"), str(tmp_path / "out"), loss="paper")
    assert not (tmp_path / "out").exists()
