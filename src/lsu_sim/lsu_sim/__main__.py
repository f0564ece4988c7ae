"""`python -m lsu_sim [--rig sim_rig.yaml] --write-calibration DIR`: the rig's true calibration files."""

from __future__ import annotations

import argparse
import sys

from .geometry import RigConfigError, load_rig, write_true_calibration


def main(argv: list[str] | None = None) -> int:
    """Write left.yaml/right.yaml/stereo.yaml from the simulated rig's geometry."""
    parser = argparse.ArgumentParser(prog="python -m lsu_sim", description=__doc__)
    parser.add_argument("--rig", default=None, help="sim rig YAML (default: config/sim_rig.yaml)")
    parser.add_argument("--write-calibration", metavar="DIR", required=True, help="output directory")
    args = parser.parse_args(argv)
    try:
        write_true_calibration(load_rig(args.rig), args.write_calibration)
    except RigConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {args.write_calibration}/left.yaml, right.yaml, stereo.yaml")
    return 0


if __name__ == "__main__":
    sys.exit(main())
