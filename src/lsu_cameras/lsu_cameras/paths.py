"""Where the config lives: lsu_config's one rule (its package data, LSU_CONFIG_DIR overrides)."""

from __future__ import annotations

from lsu_config import config_dir

__all__ = ["config_dir"]
