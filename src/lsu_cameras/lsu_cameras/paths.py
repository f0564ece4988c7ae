"""Where the workspace's config lives (same rule as the `lsu` command)."""

from __future__ import annotations

import os
from pathlib import Path


def workspace_root() -> Path:
    """The checkout this package runs from (editable install), or LSU_WORKSPACE."""
    if os.environ.get("LSU_WORKSPACE"):
        return Path(os.environ["LSU_WORKSPACE"])
    return Path(__file__).resolve().parents[3]


def config_dir() -> Path:
    """Folder with parameters, calibration, profiles (LSU_CONFIG_DIR overrides)."""
    return Path(os.environ.get("LSU_CONFIG_DIR", workspace_root() / "config"))
