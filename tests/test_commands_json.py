"""The one reader of ``--params-json`` (and ``--fit-json``, ``bench fit --params``)."""

from __future__ import annotations

import json

import pytest

from surfphase.cli import main
from surfphase.commands import read_json_object

PARAMS = {"voxels": 80, "frames": [0, 1], "name": "a b"}


def test_inline_json_text():
    assert read_json_object(json.dumps(PARAMS)) == PARAMS
    assert read_json_object("  " + json.dumps(PARAMS)) == PARAMS


def test_empty_or_missing_gives_an_empty_object():
    assert read_json_object(None) == {}
    assert read_json_object("") == {}


@pytest.mark.parametrize("name", ["params.json", "params.txt", "params"])
def test_path_of_a_json_file(tmp_path, name):
    path = tmp_path / name
    path.write_text(json.dumps(PARAMS))
    assert read_json_object(str(path)) == PARAMS


def test_a_json_file_whose_name_begins_with_a_brace(tmp_path, monkeypatch):
    # As the prior's reader did: a .json file is read whatever its name looks like.
    monkeypatch.chdir(tmp_path)
    (tmp_path / "{odd}.json").write_text(json.dumps(PARAMS))
    assert read_json_object("{odd}.json") == PARAMS


def test_inline_object_is_never_taken_for_a_path(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    text = json.dumps({"a": 1})
    (tmp_path / text).write_text(json.dumps({"b": 2}))
    assert read_json_object(text) == {"a": 1}


def test_a_long_inline_value_is_not_looked_up_as_a_path():
    text = json.dumps(list(range(400)))  # longer than a file name may be
    with pytest.raises(ValueError, match=r"^--params-json: expected a JSON object$"):
        read_json_object(text)


@pytest.mark.parametrize("text", ["{'a': 1}", "{", "nope", "params.json"])
def test_bad_json_names_the_option(text):
    with pytest.raises(ValueError, match=r"^--params-json: not valid JSON \("):
        read_json_object(text)
    with pytest.raises(ValueError, match=r"^--fit-json: not valid JSON \("):
        read_json_object(text, "--fit-json")


def test_bad_json_in_a_file_names_the_option(tmp_path):
    path = tmp_path / "params.json"
    path.write_text("{'a': 1}")
    with pytest.raises(ValueError, match=r"^--params-json: not valid JSON \("):
        read_json_object(str(path))


@pytest.mark.parametrize("text", ["[1]", "3", '"x"', "null"])
def test_not_an_object(text):
    with pytest.raises(ValueError, match=r"^--params-json: expected a JSON object$"):
        read_json_object(text)
    with pytest.raises(ValueError, match=r"^--params: expected a JSON object of fit parameters$"):
        read_json_object(text, "--params", "fit parameters")


def test_commands_report_the_option(tmp_path, capsys):
    rc = main(["mesh", "--fit", "f", "--ingest", "i", "--out", "o", "--params-json", "[1]"])
    err = capsys.readouterr().err
    assert rc == 2 and "--params-json: expected a JSON object of mesh parameters" in err
    rc = main(["mesh", "--fit", "f", "--ingest", "i", "--out", "o", "--params-json", "{x"])
    assert rc == 2 and "--params-json: not valid JSON (" in capsys.readouterr().err
