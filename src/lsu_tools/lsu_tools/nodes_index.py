"""Which executables and node classes the installed LSU packages provide (no rclpy import).

A package's executables are its `console_scripts` entry points (they land in the venv's
bin folder); the same names under the `lsu.nodes` group point at the Node classes, so
`lsu run` can build every node of a launch file in one process.
"""

from __future__ import annotations

import importlib.metadata as metadata
import shutil
import sys
from pathlib import Path

NODE_GROUP = "lsu.nodes"
COMMAND_GROUP = "lsu.commands"


def _distribution(package: str) -> metadata.Distribution | None:
    try:
        return metadata.distribution(package)
    except metadata.PackageNotFoundError:
        return None


def _entry_points(package: str, group: str) -> dict[str, metadata.EntryPoint]:
    dist = _distribution(package)
    if dist is None:
        return {}
    return {ep.name: ep for ep in dist.entry_points if ep.group == group}


def known_packages() -> list[str]:
    """Installed distributions that provide nodes or executables, named like ROS packages."""
    names = set()
    for dist in metadata.distributions():
        if any(ep.group in (NODE_GROUP, "console_scripts") for ep in dist.entry_points):
            name = dist.metadata["Name"]
            if name and name.replace("-", "_").startswith("lsu_"):
                names.add(name.replace("-", "_"))
    return sorted(names)


def executables(package: str) -> list[str]:
    """Executable names of ``package`` (empty when the package is not installed)."""
    return sorted(_entry_points(package, "console_scripts"))


def resolve_executable(package: str, executable: str) -> Path:
    """Path of ``executable`` of ``package``.

    Raises:
        LookupError: the package is not installed or has no such executable; the message
            lists what exists.
    """
    if _distribution(package) is None:
        raise LookupError(
            f"unknown package '{package}' (installed LSU packages: {', '.join(known_packages()) or 'none'}; "
            "run `make setup` if one is missing)"
        )
    if executable not in _entry_points(package, "console_scripts"):
        have = ", ".join(executables(package)) or "none"
        raise LookupError(f"package '{package}' has no executable '{executable}' (it has: {have})")
    candidate = Path(sys.executable).parent / executable
    if candidate.exists():
        return candidate
    found = shutil.which(executable)
    if found is None:
        raise LookupError(
            f"executable '{executable}' of '{package}' is declared but not installed in {candidate.parent}; "
            "run `make setup`"
        )
    return Path(found)


def node_class(package: str, executable: str) -> type:
    """The Node class behind ``package``/``executable`` for in-process use (`lsu run`).

    Raises:
        LookupError: no ``lsu.nodes`` entry point of that name.
    """
    eps = _entry_points(package, NODE_GROUP)
    if executable not in eps:
        resolve_executable(package, executable)  # a clearer message when the package is unknown
        raise LookupError(
            f"'{package}/{executable}' cannot run in-process: it declares no '{NODE_GROUP}' entry point "
            f"(in-process nodes of {package}: {', '.join(sorted(eps)) or 'none'})"
        )
    return eps[executable].load()


def command_plugins() -> list[metadata.EntryPoint]:
    """`lsu` subcommands contributed by other packages (group ``lsu.commands``)."""
    return sorted(metadata.entry_points(group=COMMAND_GROUP), key=lambda ep: ep.name)
