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
