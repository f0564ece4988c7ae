"""`lsu view`: the live view on its own, next to a graph that is already running."""

from __future__ import annotations

import argparse
from typing import Any


def cmd_view(args: argparse.Namespace) -> int:
    from rclpy.parameter import Parameter

    from lsu_common.node import run_node

    from .node import FoxgloveBridgeNode

    def make() -> FoxgloveBridgeNode:
        try:
            return FoxgloveBridgeNode(parameter_overrides=[
                Parameter("host", value=args.host), Parameter("port", value=args.port),
                Parameter("image_max_hz", value=float(args.image_max_hz))])
        except RuntimeError as exc:  # the port is taken: a one-line error of `lsu`
            raise ValueError(str(exc)) from None

    def started(node: FoxgloveBridgeNode) -> None:
        print(f"lsu view: open Foxglove (app or https://app.foxglove.dev), 'Open connection' > "
              f"'Foxglove WebSocket' > {node.url}; Ctrl-C stops", flush=True)

    return run_node(make, [], on_started=started)


def register(sub: argparse._SubParsersAction[Any]) -> None:
    """Add `view` to the `lsu` parser."""
    p = sub.add_parser("view", help="live view: a Foxglove WebSocket server offering the graph's topics",
                       description="Start the foxglove_bridge node: every topic of the graph (images, laser lines, "
                                   "points, scan cloud, mesh, scanner state) offered to the Foxglove app over "
                                   "ws://HOST:PORT, CDR passed through. Same as `lsu launch sim view:=true` adds.")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to listen on (default 127.0.0.1: this machine only; 0.0.0.0: every interface)")
    p.add_argument("--port", type=int, default=8765, help="WebSocket port (default 8765; 0: any free port)")
    p.add_argument("--image-max-hz", type=float, default=5.0, metavar="HZ",
                   help="images sent per topic and second at most (default 5; 0: all)")
    p.set_defaults(func=cmd_view)
