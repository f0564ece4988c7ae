"""open3d imported without its plotly viewer, and that viewer still working when called."""

import subprocess
import sys

SCRIPT = r"""
import sys
import numpy as np
from lsu_common.o3d import PLOTLY_MODULE, defer_plotly_viewer

defer_plotly_viewer()
import inspect
inspect.getframeinfo(inspect.currentframe())  # what rclpy's logger does at a process's first log line
print("open3d after inspect:", "open3d" in sys.modules, "dash" in sys.modules)
import open3d as o3d

print("dash before:", "dash" in sys.modules, "plotly" in sys.modules)
cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.random.default_rng(1).normal(size=(50, 3))))
figure = o3d.visualization.get_plotly_fig([cloud])
xs = np.asarray(figure.data[0].x)
print("points drawn:", len(xs), "same:", bool(np.allclose(np.sort(xs), np.sort(np.asarray(cloud.points)[:, 0]))))
print("dash after:", "dash" in sys.modules, "real:", not getattr(sys.modules[PLOTLY_MODULE], "_lsu_stand_in", False))
"""


def test_open3d_imports_without_dash_and_its_plotly_viewer_still_draws():
    out = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert "open3d after inspect: False False" in lines  # probing the stand-in's dunders loads nothing
    assert "dash before: False False" in lines
    assert "points drawn: 50 same: True" in lines  # the real viewer, loaded on its first call
    assert "dash after: True real: True" in lines
