"""`lsu render` (registered through the ``lsu.commands`` entry point): simulated pairs and their truth."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any


def cmd_render(args: argparse.Namespace) -> int:
    """Render one simulated pair (+ ground truth) into a folder."""
    import cv2

    from . import CarriageState, SimulatedRig, build_scene, load_rig

    geometry = load_rig(args.rig)
    scene = build_scene(args.scene, geometry, distance_m=args.distance, yaw_deg=args.yaw, pitch_deg=args.pitch)
    rig = SimulatedRig(geometry, scene, seed=args.seed)
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    positions = args.position or [geometry.center_step]
    for k, position in enumerate(positions):
        state = CarriageState(float(position), laser_on=not args.laser_off, stopped_at_s=0.0 if args.vibration else None,
                              vibration_amplitude_steps=args.vibration, vibration_tau_s=args.tau,
                              vibration_freq_hz=args.freq)
        frame = rig.render(state, capture_time_s=args.after_stop if args.vibration else None, seed=args.seed + k,
                           with_truth=not args.laser_off)
        name = f"{k:03d}"
        for side, image in (("left", frame.left), ("right", frame.right)):
            if not cv2.imwrite(str(out / f"{side}_{name}.png"), image):
                raise OSError(f"cannot write {out / f'{side}_{name}.png'}")
        if frame.truth is not None:
            frame.truth.to_npz(out / f"truth_{name}.npz")
        print(f"{out}/left_{name}.png right_{name}.png" + (f" truth_{name}.npz" if frame.truth else "")
              + f"  (position {position} steps)")
    return 0


def register(subparsers: Any) -> None:
    """Add `render` to the `lsu` command."""
    r = subparsers.add_parser("render", help="render simulated stereo pairs with ground truth",
                              description="Render pairs of the simulated rig (config/sim_rig.yaml) and their exact "
                                          "laser ground truth (truth_NNN.npz).")
    r.add_argument("--scene", default="head", help="plane | sphere | board | head | head:SEED | person | person:SEED (a realistic person) | mesh file")
    r.add_argument("--position", type=float, nargs="*", help="carriage position(s) [steps] (default: centre)")
    r.add_argument("--distance", type=float, default=None, help="subject distance [m] (default from the rig)")
    r.add_argument("--yaw", type=float, default=0.0, help="head or person yaw [deg]")
    r.add_argument("--pitch", type=float, default=0.0, help="head or person pitch [deg]")
    r.add_argument("--laser-off", action="store_true", help="render without the laser (texture/calibration frame)")
    r.add_argument("--vibration", type=float, default=0.0, help="post-stop vibration amplitude [steps]")
    r.add_argument("--after-stop", type=float, default=0.005, help="exposure start after the stop [s]")
    r.add_argument("--tau", type=float, default=0.06, help="vibration decay [s]")
    r.add_argument("--freq", type=float, default=25.0, help="vibration frequency [Hz]")
    r.add_argument("--seed", type=int, default=0, help="noise seed")
    r.add_argument("--rig", default=None, help="rig YAML (default config/sim_rig.yaml)")
    r.add_argument("-o", "--output", required=True, help="output directory")
    r.set_defaults(func=_guard(cmd_render))




def _guard(func: Any) -> Any:
    """Turn the simulator's expected errors into the one-line errors `lsu` prints (ValueError family)."""

    def run(args: argparse.Namespace) -> int:
        # imported here, not at registration: the simulator pulls in open3d (~1.3 s on every `lsu` call)
        from . import RigConfigError, SceneError

        try:
            return func(args)
        except (RigConfigError, SceneError) as exc:
            print(f"lsu {args.command}: error: {exc}", file=sys.stderr)
            return 2

    return run
