"""``safelane env show``: the resolved environment configuration."""

from __future__ import annotations

import sys

import yaml

from safelane.cli.common import PresetOpt, SetOpt, ShieldOpt, cli_errors, resolve_config
from safelane.config import config_to_dict


@cli_errors
def env_show(preset: PresetOpt = "fast", sets: SetOpt = None, shield: ShieldOpt = None) -> None:
    """Print the resolved environment configuration as YAML."""
    cfg = resolve_config(preset, sets, shield)
    sys.stdout.write(yaml.safe_dump(config_to_dict(cfg), sort_keys=False))
