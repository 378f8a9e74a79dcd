"""The one field syntax of every command (raywave.cli.fields): --field Y | X,Y (repeatable), the list form
--fields, and the older forms where they are unambiguous (issue 45, item 5)."""

import argparse

import pytest

from raywave.cli.errors import CommandError
from raywave.cli.fields import add_field_arguments, field_list, single_field
from raywave.cli.main import build_parser, main


def _parse(argv, legacy=False):
    p = argparse.ArgumentParser()
    add_field_arguments(p, legacy_y_list=legacy)
    return p.parse_args(argv)


@pytest.mark.parametrize("argv,want", [
    ([], None),
    (["--field", "0"], [(0.0, 0.0)]),
    (["--field", "14"], [(0.0, 14.0)]),
    (["--field", "0,14"], [(0.0, 14.0)]),
    (["--field", "0", "--field", "0,14"], [(0.0, 0.0), (0.0, 14.0)]),
    (["--field", "3", "7"], [(3.0, 7.0)]),                       # the old `psf --field X Y`
    (["--field=-5,2"], [(-5.0, 2.0)]),
    (["--fields", "0", "7", "0,14"], [(0.0, 0.0), (0.0, 7.0), (0.0, 14.0)]),  # the old compare form
    (["--fields", "0,14", "0,20"], [(0.0, 14.0), (0.0, 20.0)]),
    (["--field", "1", "--fields", "2,3"], [(0.0, 1.0), (2.0, 3.0)]),
])
def test_field_forms(argv, want):
    assert field_list(_parse(argv)) == want


def test_the_old_layout_spot_list_is_y_values_and_a_lone_pair_says_how_it_was_read(capsys):
    assert field_list(_parse(["--fields", "0,10,14"], legacy=True)) == [(0.0, 0.0), (0.0, 10.0), (0.0, 14.0)]
    assert field_list(_parse(["--fields", "0 10 14"], legacy=True)) == [(0.0, 0.0), (0.0, 10.0), (0.0, 14.0)]
    assert field_list(_parse(["--fields", "0,10"], legacy=True)) == [(0.0, 10.0)]
    assert "--field 0 --field 10" in capsys.readouterr().err


@pytest.mark.parametrize("argv,match", [
    (["--field", "a"], "not a number"),
    (["--field", "1,2,3"], "not Y or X,Y"),
    (["--field", "1", "2", "3"], "one field per --field"),
    (["--field", "1,", ], "empty value"),
    (["--fields", "1,2,3"], "not Y or X,Y"),
])
def test_bad_fields_name_the_option(argv, match):
    with pytest.raises(CommandError, match=match):
        field_list(_parse(argv))


def test_a_one_field_command_refuses_several():
    assert single_field(_parse(["--field", "0,7"])) == (0.0, 7.0)
    assert single_field(_parse([])) == (0.0, 0.0)
    with pytest.raises(CommandError, match="takes one field, got 2"):
        single_field(_parse(["--field", "0", "--field", "7"]), command="psf")


@pytest.mark.parametrize("command", [["psf", "x"], ["compare", "x"], ["spot", "x"], ["layout", "x", "-o", "o.png"],
                                     ["doe", "report", "x"]])
def test_every_field_command_takes_the_same_syntax(command):
    args = build_parser().parse_args(command + ["--field", "0", "--field", "0,14"])
    assert field_list(args) == [(0.0, 0.0), (0.0, 14.0)]


def test_psf_field_x_y_comma_form_runs_and_angles_are_checked(capsys):
    assert main(["psf", "singlet", "--field", "0,95", "--ks", "8", "--rays", "8"]) == 2
    assert "within (-90, 90)" in capsys.readouterr().err


def test_spot_and_layout_take_the_new_and_old_forms(tmp_path, capsys):
    assert main(["spot", "cooke_triplet", "--field", "0", "--field", "14", "--json"]) == 0
    import json

    table = json.loads(capsys.readouterr().out)
    assert table["fields"] == [0.0, 14.0]
    assert main(["spot", "cooke_triplet", "--fields", "0,10,14", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["fields"] == [0.0, 10.0, 14.0]
    assert main(["layout", "cooke_triplet", "--fields", "0", "10", "-o", str(tmp_path / "lay")]) == 0
    assert (tmp_path / "lay" / "layout.png").is_file()
    assert main(["layout", "cooke_triplet", "--field", "3,10", "-o", str(tmp_path / "l.png")]) == 2
    assert "meridional" in capsys.readouterr().err
