"""A component's settings (``model.field_options``, ``encoding_options``, ``attenuation_options``,
``selector_options``) given wrong, in a config file or on the command line: one line ``error: ...``
that names the setting and the fix, exit status 2, never a traceback."""

import dataclasses
import json

import pytest

from kneas_method import registry
from kneas_method.cli import train as train_cli
from kneas_method.config import to_dict
from kneas_method.errors import ConfigError
from kneas_method.model import build_component, check_options

GROUPS = ["field_options", "encoding_options", "attenuation_options", "selector_options"]

# (what a config file holds at model.<group>, words the one line must hold besides the group's name)
FILE_SHAPES = [
    ([""], ["must be"]),                      # the fuzz test's example: an option list holding an empty string
    (["num_levels=8"], ["must be"]),          # a command-line habit written into a file
    ([], ["must be"]),
    ("", ["must be"]),
    ("num_levels 8", ["must be"]),
    ({"": 1}, ["empty name"]),
    ({" ": 1}, ["empty name"]),
    ({"no_such_setting": 1}, ["unknown setting", "no_such_setting"]),
    ({"hidden_dim": "wide"}, ["hidden_dim"]),  # a wrong type, on a setting the group may or may not have
    ({"hidden_dim": [1, 2]}, ["hidden_dim"]),
]


def dry_run(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        train_cli.main(argv)
    out = capsys.readouterr()
    return exc.value.code, out.out, out.err


def assert_one_line_error(code, out, err, words):
    assert code == 2, (code, out, err)
    assert "Traceback" not in out + err
    line = err.strip()
    assert line.startswith("error:") and len(line.splitlines()) == 1, err
    for word in words:
        assert word in line, (word, line)


@pytest.fixture(scope="module")
def base_config():
    return to_dict(dataclasses.replace(registry.load("methods", "k-neas").config, method="k-neas", preset="tiny"))


@pytest.mark.parametrize("group", GROUPS)
@pytest.mark.parametrize("value,words", FILE_SHAPES, ids=[json.dumps(s[0]) for s in FILE_SHAPES])
def test_config_file_with_malformed_options(base_config, tmp_path, capsys, group, value, words):
    cfg = json.loads(json.dumps(base_config))
    cfg["model"][group] = value
    path = tmp_path / "config.json"
    path.write_text(json.dumps(cfg))
    code, out, err = dry_run(["--config", str(path), "--dry-run"], capsys)
    assert_one_line_error(code, out, err, [group, *words])


@pytest.mark.parametrize("group", GROUPS)
def test_config_file_with_a_setting_given_twice(base_config, tmp_path, capsys, group):
    text = json.dumps(base_config).replace(f'"{group}": ', f'"{group}": {{"num_levels": 4, "num_levels": 5}}, "_": ', 1)
    text = text.replace('"_": null,', "").replace('"_": {},', "")
    path = tmp_path / "config.json"
    path.write_text(text)
    code, out, err = dry_run(["--config", str(path), "--dry-run"], capsys)
    assert_one_line_error(code, out, err, ["'num_levels' is given twice", "keep one"])


CLI_SHAPES = [
    ([""], ["empty setting name", "NAME VALUE"]),
    (["num_levels"], ["'num_levels' has no value", "NAME VALUE"]),
    (["num_levels=8"], ["NAME VALUE with a space", "num_levels 8"]),
    (["num_levels", "4", "num_levels", "5"], ["num_levels more than once", "keep one"]),
    (["hidden_dim", "4", "num_levels"], ["'num_levels' has no value"]),
]


@pytest.mark.parametrize("group", GROUPS)
@pytest.mark.parametrize("values,words", CLI_SHAPES, ids=[" ".join(s[0]) or "''" for s in CLI_SHAPES])
def test_command_line_with_malformed_options(capsys, group, values, words):
    flag = "--model." + group.replace("_", "-")
    code, out, err = dry_run(["k-neas", "--preset", "tiny", "--dry-run", flag, *values], capsys)
    assert_one_line_error(code, out, err, [flag, *words])


@pytest.mark.parametrize("flag,values,words", [
    ("--model.encoding-options", ["num_levels", "many"], ["model.encoding_options.num_levels", "integer", "'many'"]),
    ("--model.attenuation-options", ["hidden_dim", "1.5"], ["model.attenuation_options.hidden_dim", "integer"]),
    ("--model.field-options", ["no_such", "1"], ["unknown setting model.field_options.no_such", "known settings"]),
    ("--model.selector-options", ["a", "1"], ["unknown setting model.selector_options.a", "takes no settings"]),
])
def test_command_line_options_of_the_wrong_name_or_type(capsys, flag, values, words):
    code, out, err = dry_run(["k-neas", "--preset", "tiny", "--dry-run", flag, *values], capsys)
    assert_one_line_error(code, out, err, words)


def test_well_formed_options_still_apply(capsys):
    code, out, err = dry_run(["k-neas", "--preset", "tiny", "--dry-run", "--model.encoding-options", "num_levels", "3",
                              "--model.attenuation-options", "hidden_dim", "8"], capsys)
    assert code == 0, err
    assert '"num_levels":3' in out


@pytest.mark.parametrize("options", [[""], "", ["a", "b"], {"": 1}, {"  ": 1}, {"num_levels": [4]}, {1: 2}])
def test_check_options_refuses_every_malformed_shape(options):
    with pytest.raises(ConfigError, match="model.encoding_options"):
        check_options(options, "model.encoding_options")


def test_build_component_refuses_a_list_instead_of_settings():
    with pytest.raises(ConfigError, match=r"model.field_options must be settings by name"):
        build_component("fields", "sdf", [""], where="model.field_options")
