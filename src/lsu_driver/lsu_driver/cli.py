"""`lsu gp32 ...`: run the emulator, talk to a unit by hand, inject faults."""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import time

import serial

from . import protocol as p
from .client import PORT_ERRORS
from .emulator import EmulatorConfig, Faults, Gp32Emulator, send_control


def _open(port: str, baud: int) -> serial.Serial:
    try:
        return serial.Serial(port, baud, timeout=0.05)
    except (serial.SerialException, OSError) as exc:
        raise FileNotFoundError(f"cannot open {port} ({exc}); is the emulator running (lsu gp32 emulate) or the "
                                "adapter plugged in?") from None


def _describe(raw: bytes) -> str:
    try:
        line = p.parse_line(raw)
    except p.MalformedLine as exc:
        return f"?? {exc}"
    kind = "event" if p.is_event(line) else "reply"
    return f"{raw.decode('ascii', 'replace').strip():<36} ({kind})"


def cmd_emulate(args: argparse.Namespace) -> int:
    config = EmulatorConfig(track_steps=args.track, rate_steps_per_s=args.rate,
                            start_position_steps=args.start_position, watchdog_ms=args.watchdog,
                            protocol_version=args.protocol, clock_drift_ppm=args.clock_drift_ppm)
    faults = Faults(garbage_probability=args.garbage, drop_probability=args.drop,
                    reply_delay_s=args.late_ms / 1000.0, stalled=args.stall, seed=args.seed)
    if not args.no_ros:
        from lsu_common.node import run_node

        from .emulator_node import Gp32EmulatorNode

        overrides = ["--ros-args", "-p", f"link:={args.link}", "-p", f"track_steps:={args.track}",
                     "-p", f"rate_steps_per_s:={args.rate}", "-p", f"start_position_steps:={float(args.start_position)}",
                     "-p", f"watchdog_ms:={args.watchdog}", "-p", f"fault_garbage_probability:={float(args.garbage)}",
                     "-p", f"fault_drop_probability:={float(args.drop)}", "-p", f"fault_reply_delay_ms:={args.late_ms}",
                     "-p", f"fault_stalled:={str(args.stall).lower()}", "-p", f"fault_seed:={args.seed}",
                     "-p", f"protocol_version:={args.protocol}", "-p", f"clock_drift_ppm:={float(args.clock_drift_ppm)}"]
        if args.control:
            overrides += ["-p", f"control:={args.control}"]
        def started(node: Gp32EmulatorNode) -> None:
            print(f"GP32 emulator: {node.emulator.device_path} -> {args.link} (control "
                  f"{node.emulator.control_path}); publishing /lsu/sim/truth; Ctrl-C stops", flush=True)

        return run_node(lambda: Gp32EmulatorNode(cli_args=overrides), [], on_started=started)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    with Gp32Emulator(config, faults, link=args.link, control=args.control or f"{args.link}.ctl") as emu:
        print(f"GP32 emulator: {emu.device_path} -> {args.link} (control {emu.control_path}); Ctrl-C stops",
              flush=True)
        try:
            while not stop.wait(0.2):
                pass
        except KeyboardInterrupt:
            pass
    return 0


def cmd_send(args: argparse.Namespace) -> int:
    ser = _open(args.port, args.baud)
    failed = False
    with ser:
        ser.reset_input_buffer()
        for command in args.commands:
            ser.write(command.encode("ascii", "replace") + b"\n")
            print(f"> {command}")
            wait_for_event = args.wait and command[:1].upper() in ("G", "M", "H")
            deadline = time.monotonic() + args.timeout
            got_reply = False
            buffer = b""
            while time.monotonic() < deadline:
                buffer += ser.read(max(1, ser.in_waiting))
                while b"\n" in buffer:
                    raw, buffer = buffer.split(b"\n", 1)
                    if not raw.strip():
                        continue
                    print("< " + _describe(raw + b"\n"))
                    try:
                        line = p.parse_line(raw + b"\n")
                    except p.MalformedLine:
                        continue
                    if not p.is_event(line):
                        got_reply = True
                        failed |= isinstance(line, p.Err)
                    if got_reply and (not wait_for_event or isinstance(line, (p.Done, p.HomeDone))):
                        deadline = 0.0
                        break
            if not got_reply:
                print(f"no reply to '{command}' within {args.timeout:g} s", file=sys.stderr)
                failed = True
    return 1 if failed else 0


def cmd_console(args: argparse.Namespace) -> int:
    ser = _open(args.port, args.baud)
    stop = threading.Event()

    def reader() -> None:
        buffer = b""
        while not stop.is_set():
            try:
                buffer += ser.read(max(1, ser.in_waiting))
            except PORT_ERRORS as exc:
                print(f"\n[port lost: {exc}]", flush=True)
                stop.set()
                return
            while b"\n" in buffer:
                raw, buffer = buffer.split(b"\n", 1)
                if raw.strip():
                    print("< " + _describe(raw + b"\n"), flush=True)

    print(f"connected to {args.port} at {args.baud} baud; type commands (? P L1 L0 G235 M+10 H C X S200 W2000), "
          "Ctrl-D quits", flush=True)
    thread = threading.Thread(target=reader, daemon=True)
    thread.start()
    try:
        for line in sys.stdin:
            if stop.is_set():
                break
            if line.strip():
                ser.write(line.strip().encode("ascii", "replace") + b"\n")
    except KeyboardInterrupt:
        pass
    finally:
        stop.set()
        thread.join(timeout=1.0)
        ser.close()
    return 0


def cmd_fault(args: argparse.Namespace) -> int:
    request: dict
    kind = args.kind
    value: str | None = args.value
    if kind == "garbage":
        request = {"fault": "garbage", "bytes": int(value or 16)}
    elif kind == "garbage-rate":
        request = {"fault": "garbage_rate", "probability": float(value or 0.2)}
    elif kind == "drop":
        request = {"fault": "drop", "probability": float(value or 0.1)}
    elif kind == "late":
        request = {"fault": "late", "delay_ms": float(value or 500)}
    elif kind == "reset":
        request = {"fault": "reset"}
    elif kind == "stall":
        request = {"fault": "stall", "on": (value or "on") in ("on", "1", "true")}
    elif kind == "unplug":
        request = {"fault": "unplug", "duration_s": float(value or 1.0)}
    elif kind == "clear":
        request = {"fault": "clear"}
    else:
        request = {"get": "truth"}
    try:
        answer = send_control(args.control, request)
    except OSError as exc:
        raise FileNotFoundError(f"cannot reach the emulator's control socket {args.control} ({exc}); "
                                "is `lsu gp32 emulate` running?") from None
    print(json.dumps(answer, indent=2))
    return 0 if answer.get("ok") else 1


def cmd_firmware_build(args: argparse.Namespace) -> int:
    from .firmware import FirmwareUnavailable, build

    try:
        made = build(baud=args.baud)
    except FirmwareUnavailable as exc:
        print(f"lsu gp32 firmware build: error: {exc}", file=sys.stderr)
        return 2
    print(f"GP32 firmware ({args.baud} baud) in {made.directory}:\n"
          f"  {made.s19.name}  for the unit (monitor-mode loader), {made.size.flash_bytes} B flash of 32768, "
          f"{made.size.ram_bytes} B RAM of 512 (+{made.size.stack_bytes} B stack)\n"
          f"  {made.hex.name}  the same as Intel HEX\n"
          f"  {made.sim_image.name}  for the simulator (lsu gp32 firmware run)")
    return 0


def cmd_firmware_run(args: argparse.Namespace) -> int:
    from .firmware import FirmwareUnavailable, Gp32Firmware, build

    config = EmulatorConfig(track_steps=args.track, start_position_steps=args.start_position)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:
        image = build().sim_image
        with Gp32Firmware(config, link=args.link, control=args.control or f"{args.link}.ctl", image=image) as unit:
            print(f"GP32 firmware in the HC08 simulator: {unit.device_path} -> {args.link} "
                  f"(control {unit.control_path}); Ctrl-C stops", flush=True)
            try:
                while not stop.wait(0.2):
                    pass
            except KeyboardInterrupt:
                pass
    except FirmwareUnavailable as exc:
        print(f"lsu gp32 firmware run: error: {exc}", file=sys.stderr)
        return 2
    return 0


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add `lsu gp32 emulate|send|console|fault|firmware`."""
    gp32 = sub.add_parser("gp32", help="GP32 unit: emulator, console, raw commands, faults").add_subparsers(
        dest="verb", required=True)
    p_em = gp32.add_parser("emulate", help="run a GP32 emulator behind a pty (prints the device path)")
    p_em.add_argument("--link", default="/tmp/lsu-gp32", help="stable symlink to the pty (default /tmp/lsu-gp32)")
    p_em.add_argument("--control", default="", help="control socket for faults (default LINK.ctl)")
    p_em.add_argument("--track", type=int, default=470, help="physical track [steps]")
    p_em.add_argument("--rate", type=int, default=200, help="power-on step rate [steps/s]")
    p_em.add_argument("--start-position", type=float, default=123.0, help="carriage position at power-on [steps]")
    p_em.add_argument("--watchdog", type=int, default=2000, help="power-on laser watchdog [ms]")
    p_em.add_argument("--garbage", type=float, default=0.0, help="chance of garbage bytes before each line")
    p_em.add_argument("--drop", type=float, default=0.0, help="chance that each sent byte is lost")
    p_em.add_argument("--late-ms", type=int, default=0, help="delay every sent line [ms]")
    p_em.add_argument("--stall", action="store_true", help="the motor does not move")
    p_em.add_argument("--seed", type=int, default=0, help="seed of the fault random generator")
    p_em.add_argument("--protocol", type=int, choices=p.SUPPORTED_VERSIONS, default=p.PROTOCOL_VERSION,
                      help="GP32 protocol the unit speaks (1: the v1 firmware, without the device clock)")
    p_em.add_argument("--clock-drift-ppm", type=float, default=150.0,
                      help="how much faster the unit's millisecond clock runs than the host's [ppm]")
    p_em.add_argument("--no-ros", action="store_true", help="do not publish /lsu/sim/truth")
    p_em.set_defaults(func=cmd_emulate)
    p_send = gp32.add_parser("send", help="send commands and print replies and events: lsu gp32 send PORT ? P G235")
    p_send.add_argument("port")
    p_send.add_argument("commands", nargs="+", metavar="CMD")
    p_send.add_argument("--baud", type=int, default=115200)
    p_send.add_argument("--timeout", type=float, default=2.0, help="seconds to wait per command")
    p_send.add_argument("--wait", action="store_true", help="for G/M/H also wait for !DONE / !HOME")
    p_send.set_defaults(func=cmd_send)
    p_con = gp32.add_parser("console", help="interactive: type commands, see replies and events")
    p_con.add_argument("port")
    p_con.add_argument("--baud", type=int, default=115200)
    p_con.set_defaults(func=cmd_console)
    p_fault = gp32.add_parser("fault", help="inject a fault into a running emulator (or read its truth)")
    p_fault.add_argument("kind", choices=["garbage", "garbage-rate", "drop", "late", "reset", "stall", "unplug",
                                          "clear", "truth"])
    p_fault.add_argument("value", nargs="?", help="bytes / probability / ms / on|off / seconds")
    p_fault.add_argument("--control", default="/tmp/lsu-gp32.ctl", help="control socket (default /tmp/lsu-gp32.ctl)")
    p_fault.set_defaults(func=cmd_fault)
    p_fw = gp32.add_parser("firmware", help="the unit's own firmware (firmware/gp32): build it, run it in the "
                                            "HC08 simulator").add_subparsers(dest="fw_verb", required=True)
    p_fwb = p_fw.add_parser("build", help="compile with SDCC: S19/HEX for the GP32 and the simulator image")
    p_fwb.add_argument("--baud", type=int, choices=[9600, 115200], default=9600, help="SCI rate of the real unit")
    p_fwb.set_defaults(func=cmd_firmware_build)
    p_fwr = p_fw.add_parser("run", help="run the firmware in shc08 with a simulated board behind a pty "
                                        "(like emulate; use `lsu launch sim unit:=firmware` for /lsu/sim/truth)")
    p_fwr.add_argument("--link", default="/tmp/lsu-gp32", help="stable symlink to the pty (default /tmp/lsu-gp32)")
    p_fwr.add_argument("--control", default="", help="control socket for reset/stall/truth (default LINK.ctl)")
    p_fwr.add_argument("--track", type=int, default=470, help="physical track [steps]")
    p_fwr.add_argument("--start-position", type=float, default=123.0, help="carriage position at power-on [steps]")
    p_fwr.set_defaults(func=cmd_firmware_run)


__all__: list[str] = ["register"]
