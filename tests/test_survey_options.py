"""`ragsplat survey`'s options come from `SurveyConfig`'s fields: each option's default is its field's and
its help starts with the field's help, and the command with no option builds the config's defaults."""

import argparse
from dataclasses import MISSING, fields
from pathlib import Path

from ragsplat.cli import survey
from ragsplat.survey.stages.base import SurveyConfig


def parser():
    p = argparse.ArgumentParser(prog="ragsplat survey")
    survey.add_arguments(p)
    return p


def test_each_option_s_default_and_help_are_its_field_s():
    actions = {a.dest: a for a in parser()._actions}
    helped = [f for f in fields(SurveyConfig) if "help" in f.metadata]
    assert len(helped) >= 27
    for f in helped:
        action = actions[f.name]
        assert action.help.startswith(f.metadata["help"]), f.name
        assert f.default is MISSING or action.default == f.default, f.name
    text = parser().format_help()  # every %(default)s expands
    assert "default 0.01)" in text and "%(" not in text


def test_no_option_builds_the_config_s_defaults():
    args = parser().parse_args(["photos", "--out", "run"])
    given = {f.name: getattr(args, f.name) for f in fields(SurveyConfig) if f.name != "culls"}
    assert SurveyConfig(**given) == SurveyConfig(images=Path("photos"), out=Path("run"))


def test_train_and_the_culls_take_their_help_from_their_configs(tmp_path):
    """`ragsplat train`'s options for TrainConfig's fields and every command's culls (ExtractConfig's): the
    field's help; unset, None, so the preset's (the run's, the evaluation's) value holds."""
    from ragsplat.cli import train
    from ragsplat.cli.args import CULLS, cull_arguments
    from ragsplat.surface import ExtractConfig
    from ragsplat.train.config import TrainConfig

    p = argparse.ArgumentParser(prog="ragsplat train")
    train.add_arguments(p)
    actions = {a.dest: a for a in p._actions}
    helped = [f for f in fields(TrainConfig) if "help" in f.metadata]
    assert len(helped) >= 17
    for f in helped:
        assert actions[f.name].help.startswith(f.metadata["help"]), f.name
    args = p.parse_args(["--data", str(tmp_path), "--out", str(tmp_path / "run")])
    given = {f.name for f in helped if getattr(args, f.name) is not None}
    assert given == {"variant", "preset", "seed"}  # the rest: the preset's
    assert (args.variant, args.preset, args.seed) == (TrainConfig.variant, TrainConfig.preset, 0)
    assert p.parse_args(["--data", str(tmp_path), "--out", "r", "--n", "1.34"]).water_n == 1.34

    p = argparse.ArgumentParser()
    cull_arguments(p)
    actions = {a.dest: a for a in p._actions}
    for f in fields(ExtractConfig):
        assert (f.name in CULLS) == ("help" in f.metadata), f.name
        if f.name in CULLS:
            assert actions[f.name].help == f.metadata["help"] and actions[f.name].default is None
