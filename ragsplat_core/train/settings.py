"""A training config's fields set by name, as the development tools' `--set PARAM=VALUE` give them: the
numeric fields of `TrainConfig` and of its `DensifyConfig` (as `densify.FIELD`), and its word-valued choices
and switches (the variant and preset excepted: the tools' own options)."""

from __future__ import annotations

from dataclasses import fields

from ragsplat.errors import ConfigError
from ragsplat.train.config import DensifyConfig, TrainConfig, with_chosen

NUMBERS = ("float", "int", "float | None", "int | None")  # None: what the run derives (e.g. scene_scale)
# The word-valued choices (the config checks their values) and the switches (`detrend_albedo=true`).
WORDS = [f.name for f in fields(TrainConfig)
         if f.type in ("str", "bool") and f.name not in ("variant", "preset")]
PARAMS = [f.name for f in fields(TrainConfig) if f.type in NUMBERS] + WORDS + \
    [f"densify.{f.name}" for f in fields(DensifyConfig) if f.type in NUMBERS]


def typed(param: str, value: str | float) -> str | float:
    """`value` as `param` takes it: a word for a choice, else a float (`with_value` casts ints)."""
    return str(value) if param in WORDS else float(value)


def parse(items: list[str]) -> dict[str, str | float]:
    """`PARAM=VALUE` items as {param: value (`typed`)}. Raises ConfigError for an unknown or empty one."""
    fixed = {}
    for item in items:
        name, _, value = item.partition("=")
        if name not in PARAMS or not value:
            raise ConfigError(f"--set takes PARAM=VALUE with PARAM one of {', '.join(PARAMS)}; got {item!r}")
        fixed[name] = typed(name, value)
    return fixed


def switch(value: str) -> bool:
    if value not in ("true", "false"):
        raise ValueError(f"a switch is true or false, got {value!r}")
    return value == "true"


def with_value(cfg: TrainConfig, param: str, value: str | float) -> TrainConfig:
    """`cfg` with `param` (a field, or densify.FIELD) set to `value`, cast to the field's type
    (`config.with_chosen`)."""
    nested, _, name = param.rpartition(".")
    owner = DensifyConfig if nested == "densify" else TrainConfig
    kind = {f.name: f.type for f in fields(owner)}[name]
    cast = {"int": lambda v: int(float(v)), "float": float, "str": str,
            "bool": switch}[kind.removesuffix(" | None")]
    return with_chosen(cfg, {param: cast(value)})
