"""Stage settings: named confs, KEY=VALUE overrides, the CLI's options and the workflow schema."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import yaml

from dmais_pipe import cli
from dmais_pipe.errors import DmaisError
from dmais_pipe.stages import configure, evaluate, export, extrinsics, intrinsics, markers, pose, report

STAGES = {"markers": markers, "intrinsics": intrinsics, "extrinsics": extrinsics, "pose": pose,
          "evaluate": evaluate, "export": export, "report": report}
SCHEMA = Path(__file__).resolve().parents[1] / "workflow" / "schemas" / "config.schema.yaml"


def test_overrides_are_typed_like_the_defaults():
    conf = configure(pose.CONFS, "robust", ["refine=false", "robust-threshold-px = 7.5"], "pose")
    assert conf == pose.Conf(robust=True, refine=False, robust_threshold_px=7.5)
    assert configure(intrinsics.CONFS, "paper", ["methods=ours, dlt_lm"]).methods == ("ours", "dlt_lm")
    assert configure(extrinsics.CONFS, "paper", ["use_priors=No"]).use_priors is False
    assert pose.CONFS["paper"] == pose.Conf()  # a named conf is never changed by an override


@pytest.mark.parametrize("name, overrides, message", [
    ("fast", [], "pose: unknown conf 'fast'; named confs: paper, robust"),
    ("paper", ["robustt=1"], "pose: setting 'robustt=1' is not KEY=VALUE with KEY one of robust, refine"),
    ("paper", ["robust"], "is not KEY=VALUE"),
    ("paper", ["robust=maybe"], "pose: setting robust: 'maybe' is not a bool"),
    ("paper", ["robust_threshold_px=ten"], "pose: setting robust_threshold_px: 'ten' is not a float"),
    ("paper", ["robust_threshold_px=nan"], "is not a number"),
])
def test_bad_settings_name_the_stage_and_the_setting(name, overrides, message):
    with pytest.raises(DmaisError, match=message.replace("(", r"\(")):
        configure(pose.CONFS, name, overrides, "pose")


def test_the_cli_options_set_the_conf_and_a_bad_setting_is_one_line(tmp_path, capsys):
    args = cli._parser().parse_args(["pose", "d", "--out", "r", "--robust", "--set", "robust_threshold_px=5"])
    assert cli._conf(args, pose, ("robust", args.robust or None)) == pose.Conf(robust=True, robust_threshold_px=5.0)
    args = cli._parser().parse_args(["extrinsics", "d", "--out", "r", "--conf", "no_priors", "--backend", "scipy"])
    assert cli._conf(args, extrinsics, ("backend", args.backend)) == extrinsics.Conf(use_priors=False, backend="scipy")
    assert cli.main(["evaluate", str(tmp_path), "--out", str(tmp_path), "--set", "flag_factor=x"]) == 2
    err = capsys.readouterr().err  # the settings are checked before the dataset is read
    assert err == "dmais evaluate: error: evaluate: setting flag_factor: 'x' is not a float\n"


def test_the_workflow_schema_knows_every_setting_and_named_conf():
    properties = yaml.safe_load(SCHEMA.read_text())["properties"]
    for stage, module in STAGES.items():
        section = properties[stage]["properties"]
        assert set(section) == {"conf"} | {f.name for f in dataclasses.fields(module.Conf)}, stage
        assert section["conf"]["enum"] == list(module.CONFS), stage
        assert next(iter(module.CONFS.values())) == module.Conf(), stage  # the first named conf is the default
        assert section["conf"]["default"] == next(iter(module.CONFS)), stage


def test_the_schema_states_each_settings_default_description_and_range_as_the_code():
    properties = yaml.safe_load(SCHEMA.read_text())["properties"]
    for stage, module in STAGES.items():
        for field in dataclasses.fields(module.Conf):
            entry, where = properties[stage]["properties"][field.name], f"{stage}.{field.name}"
            default = field.default
            assert entry["default"] == (list(default) if isinstance(default, tuple) else default), where
            assert " ".join(entry["description"].split()) == field.metadata["help"], where
            assert entry.get("minimum") == field.metadata["minimum"], where
            assert entry.get("exclusiveMinimum") == field.metadata["above"], where


def test_help_lists_every_setting_with_its_default_and_the_named_confs(capsys):
    with pytest.raises(SystemExit):
        cli.main(["pose", "--help"])
    text = capsys.readouterr().out
    assert "robust_threshold_px" in text and "[20.0]" in text
    assert "robust               robust=true, refine=true" in text
    with pytest.raises(SystemExit):
        cli.main(["--version"])
    assert capsys.readouterr().out.startswith("dmais 0.")


@pytest.mark.parametrize("stage, item, message", [
    (markers, "identify_min_inliers=2", "markers: setting identify_min_inliers: 2 is below its minimum 3"),
    (extrinsics, "center_sigma_m=0", "extrinsics: setting center_sigma_m: 0.0 must be above 0"),
    (pose, "robust_threshold_px=-1", "pose: setting robust_threshold_px: -1.0 must be above 0"),
])
def test_a_setting_out_of_its_range_is_refused(stage, item, message):
    with pytest.raises(DmaisError, match=message):
        configure(stage.CONFS, next(iter(stage.CONFS)), [item], stage.__name__.rsplit(".", 1)[1])
