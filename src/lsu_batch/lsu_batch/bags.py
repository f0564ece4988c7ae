"""Which bags a batch processes, and the output folder each one gets (pure: paths only)."""

from __future__ import annotations

import hashlib
from collections.abc import Iterable, Sequence
from pathlib import Path

__all__ = ["find_bags", "output_names"]

_BAG_FILES = (".mcap", ".db3")


def _is_bag_dir(path: Path) -> bool:
    return (path / "metadata.yaml").is_file()


def find_bags(inputs: Sequence[str | Path], skip: Iterable[Path] = ()) -> list[Path]:
    """Every bag named by ``inputs``: a bag folder (with ``metadata.yaml``), a bag file (.mcap/.db3), or a folder
    searched for them (a bag folder's own storage files are not counted again); sorted, no duplicates.

    ``skip``: folders not searched (the batch's own output). Raises FileNotFoundError naming a missing input.
    """
    skipped = {p.resolve() for p in skip}
    found: dict[Path, None] = {}
    for item in inputs:
        path = Path(item)
        if not path.exists():
            raise FileNotFoundError(f"'{item}' does not exist: give bag folders, bag files (.mcap/.db3) or folders "
                                    f"that hold them")
        if path.is_file() or _is_bag_dir(path):
            found[path.resolve()] = None
            continue
        for candidate in sorted(path.rglob("*")):
            resolved = candidate.resolve()
            if any(resolved == s or s in resolved.parents for s in skipped):
                continue
            if candidate.is_dir() and _is_bag_dir(candidate):
                found[resolved] = None
            elif candidate.is_file() and candidate.suffix in _BAG_FILES and not _is_bag_dir(candidate.parent):
                found[resolved] = None
    return sorted(found)


def _base_name(bag: Path) -> str:
    """``scans/<id>/bag`` -> ``<id>`` (how `lsu scan --record` lays scans out); else the folder or file stem."""
    if bag.is_file():
        bag = bag.with_suffix("") if not _is_bag_dir(bag.parent) else bag.parent
    name = bag.parent.name if bag.name == "bag" and bag.parent.name else bag.name
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name).lstrip(".") or "bag"


def output_names(bags: Sequence[Path]) -> dict[Path, str]:
    """bag -> its folder name under the output folder; stable for the same inputs (a rerun finds its folders).

    Bags whose names collide get a short hash of their path appended.
    """
    bases = {bag: _base_name(bag) for bag in bags}
    counts: dict[str, int] = {}
    for base in bases.values():
        counts[base] = counts.get(base, 0) + 1
    return {bag: base if counts[base] == 1 else f"{base}-{hashlib.sha1(str(bag).encode()).hexdigest()[:8]}"
            for bag, base in bases.items()}
