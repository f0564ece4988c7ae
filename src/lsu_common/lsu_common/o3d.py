"""open3d without its plotly viewer at import time.

open3d's package ``__init__`` imports ``open3d.visualization.draw_plotly``, which imports dash and plotly
(about 0.6 s CPU, seconds on a loaded host) in every process that uses open3d, though LSU never draws
with plotly. :func:`defer_plotly_viewer`, called where an LSU process starts (every node, the `lsu`
command, the test plugin), puts a stand-in for that one module into ``sys.modules`` before open3d is
imported: its functions load the real module when first called and any other name is looked up there,
so open3d behaves as before, only the cost moves to the first plotly drawing (never, in LSU).
"""

from __future__ import annotations

import importlib.util
import sys
import types
from typing import Any

PLOTLY_MODULE = "open3d.visualization.draw_plotly"
#: the names open3d.visualization imports from that module
PLOTLY_NAMES = ("get_plotly_fig", "draw_plotly", "draw_plotly_server")


def _real_module() -> types.ModuleType:
    """Load open3d's own draw_plotly module (replacing the stand-in) and return it."""
    current = sys.modules.get(PLOTLY_MODULE)
    if current is not None and not getattr(current, "_lsu_stand_in", False):
        return current
    import open3d.visualization

    spec = importlib.util.spec_from_file_location(PLOTLY_MODULE, open3d.visualization.__path__[0] + "/draw_plotly.py")
    if spec is None or spec.loader is None:
        raise ImportError(f"cannot find {PLOTLY_MODULE} in {open3d.visualization.__path__[0]}")
    module = importlib.util.module_from_spec(spec)
    sys.modules[PLOTLY_MODULE] = module
    spec.loader.exec_module(module)
    return module


def _deferred(name: str) -> Any:
    def call(*args: Any, **kwargs: Any) -> Any:
        return getattr(_real_module(), name)(*args, **kwargs)

    call.__name__ = name
    call.__doc__ = f"open3d.visualization.{name} (its module, with dash and plotly, is loaded on first call)."
    return call


def _forward(name: str) -> Any:
    """Any other public name of the stand-in: the real module's. A dunder name the stand-in lacks
    (``__file__``, ``__wrapped__``, ...) is missing, not forwarded: tools probe every module in
    ``sys.modules`` for them (``inspect.getmodule``, run by rclpy's logger at a process's first log
    line), and forwarding would load open3d, dash and plotly in every process that logs."""
    if name.startswith("__") and name.endswith("__"):
        raise AttributeError(f"module '{PLOTLY_MODULE}' (stand-in) has no attribute '{name}'")
    return getattr(_real_module(), name)


def defer_plotly_viewer() -> None:
    """Put the stand-in in place unless open3d (or its plotly module) is imported already. Idempotent."""
    if "open3d" in sys.modules or PLOTLY_MODULE in sys.modules:
        return
    stand_in = types.ModuleType(PLOTLY_MODULE, "stand-in for open3d's plotly viewer (lsu_common.o3d)")
    vars(stand_in)["_lsu_stand_in"] = True
    for name in PLOTLY_NAMES:
        setattr(stand_in, name, _deferred(name))
    vars(stand_in)["__getattr__"] = _forward  # module __getattr__ (PEP 562)
    sys.modules[PLOTLY_MODULE] = stand_in
