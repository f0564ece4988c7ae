"""`lsu web` (and the ``web_server`` executable that `lsu launch ... web:=true` starts).

rclpy runs in its own context and thread (`WebGraph` over `LsuScanner`); uvicorn runs the FastAPI
app on the main thread's event loop. Ctrl-C / SIGTERM stop uvicorn, then a laser the hardware panel
holds is switched off and the graph client is closed.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from pathlib import Path
from typing import Any

from .security import access_for, is_loopback, load_or_make_token, token_file

DEFAULT_PORT = 8080


def serve(args: argparse.Namespace) -> int:
    import uvicorn

    from lsu_scan import rosenv

    rosenv.apply_defaults()
    from .app import WebConfig, create_app
    from .graph import WebGraph
    from .outbox import Outbox

    token: str | None = None
    if args.require_token or not is_loopback(args.host):
        path = Path(args.token_file) if args.token_file else token_file()
        try:
            token, made = load_or_make_token(path, renew=args.new_token)
        except PermissionError as exc:
            print(f"lsu web: {exc}", file=sys.stderr)
            return 2
        if made:
            print(f"lsu web: a new token was made and stored in {path} (0600); it is shown this once:\n  {token}\n"
                  f"open http://{args.host}:{args.port}/?token={token} once in each browser (it then keeps a "
                  f"cookie), or type the token at /login", flush=True)
        else:
            print(f"lsu web: the token is in {path} (0600): type it at /login; --new-token makes another",
                  flush=True)
    elif args.new_token:
        print("lsu web: --new-token has no effect on a loopback address (no token needed)", file=sys.stderr)
    outbox = Outbox()
    graph = WebGraph(outbox, image_max_hz=args.image_max_hz, wait_s=args.wait)
    config = WebConfig(args.host, args.port, access_for(args.host, token),
                       Path(args.scans).expanduser().resolve() if args.scans else None)
    app = create_app(graph, config, outbox)
    server = uvicorn.Server(uvicorn.Config(app, host=args.host, port=args.port, log_level="warning",
                                           access_log=False, ws_max_size=1 << 20, lifespan="off"))
    def announce() -> None:  # once uvicorn listens, so whoever reads the line can connect at once
        while not server.started and not server.should_exit:
            time.sleep(0.05)
        if server.started:
            print(f"lsu web: open http://{'127.0.0.1' if args.host == '0.0.0.0' else args.host}:{args.port}/ "
                  f"(Ctrl-C stops)", flush=True)

    threading.Thread(target=announce, daemon=True).start()
    try:
        server.run()
    finally:
        if graph.laser_hold is not None:
            try:
                graph.laser_off("the web server stopped")
            except Exception as exc:  # noqa: BLE001 - closing anyway; the driver's own shutdown switches it off
                print(f"lsu web: could not switch the laser off at exit: {exc}", file=sys.stderr)
        graph.close()
    return 0 if server.started else 1


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--host", default="127.0.0.1",
                   help="address to listen on (default 127.0.0.1: this machine only, no token; any other address "
                        "needs the token, see README 'The web page')")
    p.add_argument("--port", type=int, default=DEFAULT_PORT, help=f"HTTP port (default {DEFAULT_PORT})")
    p.add_argument("--scans", default="", metavar="DIR",
                   help="the scan folders' parent (default: scan_coordinator's output_dir parameter)")
    p.add_argument("--image-max-hz", type=float, default=2.0, metavar="HZ",
                   help="live camera images sent per side and second at most (default 2; 0: none)")
    p.add_argument("--require-token", action="store_true",
                   help="ask for the token on a loopback address too (a PC other people log in to)")
    p.add_argument("--token-file", default="", metavar="FILE", help="where the token is kept (default "
                   "$XDG_CONFIG_HOME/lsu/web_token)")
    p.add_argument("--new-token", action="store_true", help="make a new token (the old one stops working)")
    p.add_argument("--show-token", action="store_true", help="print the stored token and exit")
    p.add_argument("--wait", type=float, default=15.0, help="wait for the graph's servers [s] (default 15)")


def cmd_web(args: argparse.Namespace) -> int:
    if args.show_token:
        path = Path(args.token_file) if args.token_file else token_file()
        if not path.is_file():
            print(f"lsu web: no token yet ({path}); one is made when the page is served on a non-loopback address",
                  file=sys.stderr)
            return 1
        print(path.read_text().strip())
        return 0
    return serve(args)


def register(sub: argparse._SubParsersAction[Any]) -> None:
    """Add `web` to the `lsu` parser."""
    p = sub.add_parser("web", help="the web page for the person at the scanner (start, watch, stop, download, ...)",
                       description="Serve the LSU page over HTTP: unit status, scans with live images and points, "
                                   "the scan library with downloads, faces, calibration, a hardware test panel. A "
                                   "client of the running graph (lsu launch sim); same as `lsu launch sim web:=true`.")
    add_arguments(p)
    p.set_defaults(func=cmd_web)


def main(argv: list[str] | None = None) -> int:
    """``web_server``: `lsu web` as a launch-file executable (the ROS arguments the launcher appends are ignored)."""
    from lsu_common.interrupts import accept_interrupts
    argv = list(sys.argv[1:] if argv is None else argv)
    if "--ros-args" in argv:
        argv = argv[:argv.index("--ros-args")]
    p = argparse.ArgumentParser(prog="web_server")
    add_arguments(p)
    try:
        accept_interrupts()  # a Ctrl-C held during start-up (launcher) ends the server here
        return cmd_web(p.parse_args(argv))
    except KeyboardInterrupt:
        return 0


if __name__ == "__main__":
    sys.exit(main())
