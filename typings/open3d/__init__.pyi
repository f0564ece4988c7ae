# Stub read by mypy only (pyproject.toml: mypy_path): open3d ships stubs generated from its C++
# bindings that contradict the library (file names must be os.PathLike, Tensor() demands dtype and
# device, which have defaults), so every name of open3d is Any here instead.
from typing import Any

def __getattr__(name: str) -> Any: ...
