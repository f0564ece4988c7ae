"""The LSU configuration files as package data, and the one rule that finds them.

Launch files, node parameters, calibration, camera profiles, the Fast DDS profile, the
simulated rig and its heads are one tree (launch files name parameter and calibration files
relative to themselves). The repository's ``config/`` folder is its source: this package's
``data`` is a link to it, so an editable install reads the checkout's files and a built wheel
carries copies of them. ``LSU_CONFIG_DIR`` points everything at another tree of the same layout.
"""

from __future__ import annotations

import os
from importlib import resources
from pathlib import Path

__all__ = ["CONFIG_VAR", "config_dir"]

CONFIG_VAR = "LSU_CONFIG_DIR"


def config_dir() -> Path:
    """Folder with ``launch/``, ``params/``, ``calibration/``, ``profiles/``, ``dds/``, ``sim_rig.yaml``, ``heads/``.

    ``$LSU_CONFIG_DIR`` when set, else the installed package data.
    """
    override = os.environ.get(CONFIG_VAR)
    if override:
        return Path(override)
    # a package installed as files (wheel or editable), never zipped (setup.py: zip_safe=False)
    return Path(str(resources.files(__name__).joinpath("data")))
