"""`lsu launch`'s way out says how each node ended: a node that crashes while stopping (a signal the launcher did
not send) is named and fails the launch; one that ends cleanly is not mentioned."""

from __future__ import annotations

import io
import sys
import textwrap
import threading
import time

import pytest

from lsu_tools.launch_file import LaunchDescription, NodeSpec
from lsu_tools.launcher import Launcher

# a stand-in node: on SIGINT it ends cleanly ("clean") or dies of a segmentation fault ("crash"); like every
# LSU executable it accepts SIGINT (which the launcher holds back during start-up) once its handler is in place.
# "early": a Ctrl-C arrives while it is still starting (before its handler): held, it is taken by the handler.
NODE = textwrap.dedent("""
    import os, signal, sys, time
    def on_int(*_):
        if sys.argv[1] == "crash":
            signal.signal(signal.SIGSEGV, signal.SIG_DFL)
            os.kill(os.getpid(), signal.SIGSEGV)
        if sys.argv[1] == "early":
            print("stopped by its handler", flush=True)
        sys.exit(0)
    if sys.argv[1] == "early":
        print("up", flush=True)
        os.kill(os.getpid(), signal.SIGINT)
    signal.signal(signal.SIGINT, on_int)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    print("up", flush=True)
    while True:
        time.sleep(0.05)
""")


def _run(tmp_path, modes: list[str]) -> tuple[int, str]:
    script = tmp_path / "node.py"
    script.write_text(NODE)
    specs = [NodeSpec("lsu_tools", "selftest_talker", name=f"{mode}_node") for mode in modes]
    out = io.StringIO()
    launcher = Launcher(LaunchDescription(tmp_path / "x.launch.yaml", {}, specs), out=out)
    for child, mode in zip(launcher.children, modes):
        child.command = [sys.executable, str(script), mode]

    def stop_when_up() -> None:  # the launcher's run() is the main thread's (it installs signal handlers)
        end = time.monotonic() + 60
        while out.getvalue().count("] up") < len(modes) and time.monotonic() < end:
            time.sleep(0.05)
        launcher.request_shutdown("test")

    threading.Thread(target=stop_when_up, daemon=True).start()
    code = launcher.run()
    return code, out.getvalue()


def test_a_node_crashing_while_stopping_is_named_and_fails_the_launch(tmp_path):
    code, text = _run(tmp_path, ["clean", "crash"])
    assert code == 1, text
    assert "crash_node crashed while stopping (signal SIGSEGV" in text, text
    assert "clean_node" not in text.split("shutting down")[-1], text


def test_nodes_ending_cleanly_leave_the_launch_successful(tmp_path):
    code, text = _run(tmp_path, ["clean", "clean"])
    assert code == 0 and "while stopping" not in text, text


def test_a_ctrl_c_during_a_nodes_start_up_waits_for_its_handler(tmp_path):
    """Without the launcher holding SIGINT the signal would end the node before its handler (a traceback and exit
    code 1 here; "Fatal Python error: init_import_site" and SIGABRT inside the interpreter's own start-up)."""
    code, text = _run(tmp_path, ["early"])
    assert "[early_node] stopped by its handler" in text, text
    # it may end before or after the launcher's own shutdown (its Ctrl-C is its own): either way cleanly
    assert code == 0 and "Traceback" not in text and "crashed" not in text, text
    assert "exit code" not in text or "early_node ended (exit code 0)" in text, text


def test_run_node_takes_a_ctrl_c_held_during_start_up(tmp_path):
    """A node started with SIGINT blocked and pending (what the launcher's start-up hold leaves) ends cleanly once
    rclpy's handler is in place, rather than running on deaf to it."""
    import subprocess

    program = textwrap.dedent("""
        import os, signal, sys
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        os.kill(os.getpid(), signal.SIGINT)  # pending: arrived during start-up
        from lsu_tools.selftest import talker_main
        sys.exit(talker_main([]))
    """)
    done = subprocess.run([sys.executable, "-c", program], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "Traceback" not in done.stderr, done.stderr


@pytest.mark.timeout(60)
def test_ctrl_c_while_the_run_loop_holds_its_events_lock_neither_hangs_nor_is_lost():
    # a signal handler runs in the main thread between two bytecodes, possibly while that thread holds the
    # lock inside the shutdown Event (in its wait); the handler setting that Event then waited for a lock
    # its own thread held: the launcher hung until killed (`stop` returned None in the restart test)
    import signal as _signal
    from pathlib import Path as _Path

    out = io.StringIO()
    launcher = Launcher(LaunchDescription(_Path("none.launch.yaml"), {}, []), out=out)
    with launcher._shutdown._cond:  # type: ignore[attr-defined]  # what Event.wait holds for a moment, as the loop waits 0.05 s at a time
        launcher._on_signal(_signal.SIGINT, None)
    assert launcher.run() == 0  # the loop acts on it: no node, so it ends at once
    assert "shutting down: received SIGINT" in out.getvalue()
