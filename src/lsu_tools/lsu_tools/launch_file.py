"""Reader for launch files in the ROS 2 YAML launch format (no rclpy import).

Supported (the subset our graphs use, with ROS 2 semantics)::

    launch:
    - arg: {name: port, default: "/tmp/gp32", description: "..."}
    - include: {file: "$(dirname)/other.launch.yaml", arg: [{name: x, value: y}], if: "$(var a)"}
    - node:
        pkg: lsu_driver
        exec: gp32_driver
        name: gp32_driver
        namespace: lsu
        param:
        - from: "$(dirname)/../params/driver.yaml"
        - {name: port, value: "$(var port)"}
        remap:
        - {from: state, to: /lsu/driver/state}
        respawn: true
        respawn_delay: 1.0
        required: true            # or on_exit: shutdown - the launch ends when this node dies
        if: "$(var use_driver)"   # / unless:

Substitutions: ``$(var NAME)``, ``$(env NAME [DEFAULT])``, ``$(optenv NAME [DEFAULT])``,
``$(dirname)``, ``$(find-pkg-share PKG)``.

Every problem is a `LaunchError` that names the file, the line and the key, in one line.

Running part of a file on one machine (`lsu launch sim --group rig` on the PC wired to the unit,
`--group processing` on another): :func:`select_nodes` keeps the nodes of named groups, which
``config/launch/groups.yaml`` defines as lists of node names (a node name itself is a group too).
"""

from __future__ import annotations

import importlib
import importlib.metadata as metadata
import json
import os
import re
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import urlparse
from urllib.request import url2pathname

import yaml
from yaml.nodes import MappingNode, Node, ScalarNode, SequenceNode

_SUBST = re.compile(r"\$\(([^()]*)\)")
_TRUE = {"true", "1", "yes", "on"}
_FALSE = {"false", "0", "no", "off", ""}


class LaunchError(Exception):
    """A launch file cannot be used; ``str()`` is one line: ``FILE:LINE: KEY: what is wrong``."""

    def __init__(self, file: Path | str, line: int | None, key: str, message: str) -> None:
        self.file = str(file)
        self.line = line
        self.key = key
        self.message = message
        where = f"{self.file}:{line}" if line else self.file
        super().__init__(f"{where}: {key}: {message}" if key else f"{where}: {message}")


@dataclass
class NodeSpec:
    """One node of a launch file, ready to be started as a process or built in-process."""

    package: str
    executable: str
    name: str | None = None
    namespace: str | None = None
    params: dict[str, Any] = field(default_factory=dict)
    param_files: list[Path] = field(default_factory=list)
    remaps: list[tuple[str, str]] = field(default_factory=list)
    respawn: bool = False
    respawn_delay_s: float = 0.0
    required: bool = False
    args: list[str] = field(default_factory=list)
    env: dict[str, str] = field(default_factory=dict)
    source: str = ""

    @property
    def label(self) -> str:
        """Name used to prefix log lines: the node name, else the executable."""
        return self.name or self.executable

    def ros_args(self, inline_params_file: Path | None = None) -> list[str]:
        """The ``--ros-args ...`` list that gives this node its name, namespace, params and remaps."""
        out = ["--ros-args"]
        if self.name:
            out += ["-r", f"__node:={self.name}"]
        if self.namespace:
            out += ["-r", f"__ns:={self.namespace}"]
        for path in self.param_files:
            out += ["--params-file", str(path)]
        if inline_params_file is not None:
            out += ["--params-file", str(inline_params_file)]
        for src, dst in self.remaps:
            out += ["-r", f"{src}:={dst}"]
        return out

    def inline_params_yaml(self) -> str:
        """Inline params as a parameter file (wildcard node name: the file is this node's only)."""
        return yaml.safe_dump({"/**": {"ros__parameters": self.params}}, sort_keys=False)


@dataclass
class LaunchDescription:
    """What a launch file asks for: the resolved arguments and the nodes to start."""

    file: Path
    arguments: dict[str, str]
    nodes: list[NodeSpec]


ExecResolver = Callable[[str, str], object]


def _as_path(text: str, base: Path) -> Path:
    path = Path(text).expanduser()
    return path if path.is_absolute() else (base / path)


def _find_pkg_share(package: str) -> Path:
    """Folder with the package's package.xml: ``share/PKG`` of this install or of an ament prefix,
    else (an editable install, which installs no data files) the source folder it was installed from."""
    try:
        importlib.import_module(package)
    except ImportError as exc:
        raise LookupError(f"unknown package '{package}'") from exc
    prefixes = [sys.prefix, *(p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p)]
    for prefix in prefixes:
        share = Path(prefix) / "share" / package
        if (share / "package.xml").is_file():
            return share
    try:  # PEP 610: an editable install records the folder it came from
        direct = json.loads(metadata.distribution(package).read_text("direct_url.json") or "{}")
    except (metadata.PackageNotFoundError, ValueError):
        direct = {}
    if direct.get("dir_info", {}).get("editable") and str(direct.get("url", "")).startswith("file://"):
        source = Path(url2pathname(urlparse(direct["url"]).path))
        if (source / "package.xml").is_file():
            return source
    raise LookupError(f"package '{package}' has no share folder (no share/{package}/package.xml in "
                      f"{', '.join(prefixes)})")


class _Reader:
    """Walks the composed YAML node tree so every error keeps its line number."""

    def __init__(self, path: Path, arguments: dict[str, str], resolve_exec: ExecResolver | None,
                 depth: int = 0) -> None:
        self.path = path
        self.dir = path.parent.resolve()  # $(dirname) must not be re-joined to a relative base
        self.given = dict(arguments)
        self.arguments: dict[str, str] = {}
        self.resolve_exec = resolve_exec
        self.depth = depth
        self._loader = yaml.SafeLoader("")

    # -- helpers -----------------------------------------------------------------------------
    def error(self, node: Node | None, key: str, message: str) -> LaunchError:
        line = node.start_mark.line + 1 if node is not None else None
        return LaunchError(self.path, line, key, message)

    def value(self, node: Node) -> Any:
        return self._loader.construct_object(node, deep=True)

    def mapping(self, node: Node, key: str, allowed: tuple[str, ...]) -> dict[str, tuple[Node, Node]]:
        if not isinstance(node, MappingNode):
            raise self.error(node, key, f"expected a mapping with keys {', '.join(allowed)}")
        out: dict[str, tuple[Node, Node]] = {}
        for k_node, v_node in node.value:
            k = str(self.value(k_node))
            if k not in allowed:
                raise self.error(k_node, f"{key}.{k}", f"unknown key (allowed: {', '.join(allowed)})")
            out[k] = (k_node, v_node)
        return out

    def sequence(self, node: Node, key: str) -> list[Node]:
        if not isinstance(node, SequenceNode):
            raise self.error(node, key, "expected a list (items starting with '- ')")
        return list(node.value)

    def subst(self, node: Node, key: str, text: str) -> str:
        def one(match: re.Match[str]) -> str:
            parts = match.group(1).split()
            if not parts:
                raise self.error(node, key, "empty substitution '$()'")
            kind, rest = parts[0], parts[1:]
            if kind == "var":
                if len(rest) != 1:
                    raise self.error(node, key, "use $(var NAME)")
                if rest[0] not in self.arguments:
                    known = ", ".join(sorted(self.arguments)) or "none declared"
                    raise self.error(node, key, f"unknown launch argument $(var {rest[0]}) (declared so far: {known})")
                return self.arguments[rest[0]]
            if kind in ("env", "optenv"):
                if not rest:
                    raise self.error(node, key, f"use $({kind} NAME [DEFAULT])")
                if rest[0] in os.environ:
                    return os.environ[rest[0]]
                if len(rest) > 1:
                    return " ".join(rest[1:])
                if kind == "optenv":
                    return ""
                raise self.error(node, key, f"environment variable {rest[0]} is not set and $(env) has no default")
            if kind == "dirname":
                return str(self.dir)
            if kind == "find-pkg-share":
                if len(rest) != 1:
                    raise self.error(node, key, "use $(find-pkg-share PACKAGE)")
                try:
                    return str(_find_pkg_share(rest[0]))
                except LookupError as exc:
                    raise self.error(node, key, str(exc)) from None
            raise self.error(node, key, f"unknown substitution $({kind}) "
                                        "(known: var, env, optenv, dirname, find-pkg-share)")

        return _SUBST.sub(one, text)

    def text(self, node: Node, key: str) -> str:
        if not isinstance(node, ScalarNode):
            raise self.error(node, key, "expected a single value")
        return self.subst(node, key, str(self.value(node)))

    def flag(self, node: Node, key: str) -> bool:
        raw = self.value(node)
        if isinstance(raw, bool):
            return raw
        text = self.text(node, key).strip().lower()
        if text in _TRUE:
            return True
        if text in _FALSE:
            return False
        raise self.error(node, key, f"expected true or false, got '{text}'")

    def number(self, node: Node, key: str) -> float:
        try:
            return float(self.text(node, key))
        except ValueError:
            raise self.error(node, key, "expected a number") from None

    def param_value(self, node: Node, key: str) -> Any:
        raw = self.value(node)
        if isinstance(node, ScalarNode) and isinstance(raw, str) and _SUBST.search(raw):
            # like launch_ros: a substituted string is read again as YAML ("5" -> 5, "true" -> True)
            substituted = self.subst(node, key, raw)
            try:
                typed = yaml.safe_load(substituted)
            except yaml.YAMLError:
                return substituted
            return substituted if typed is None or isinstance(typed, (dict, list)) else typed
        if isinstance(node, SequenceNode):
            return [self.param_value(item, key) for item in node.value]
        return raw

    # -- entities ----------------------------------------------------------------------------
    def enabled(self, fields: dict[str, tuple[Node, Node]], key: str) -> bool:
        if "if" in fields and not self.flag(fields["if"][1], f"{key}.if"):
            return False
        if "unless" in fields and self.flag(fields["unless"][1], f"{key}.unless"):
            return False
        return True

    def read(self, root: Node) -> LaunchDescription:
        keys = [str(self.value(k)) for k, _ in root.value] if isinstance(root, MappingNode) else []
        if keys != ["launch"]:
            raise LaunchError(self.path, 1, "launch", "the file must start with 'launch:' followed by a list "
                              f"(and hold nothing else; found: {', '.join(keys) or 'no mapping'})")
        top = self.mapping(root, "launch", ("launch",))
        nodes: list[NodeSpec] = []
        for item in self.sequence(top["launch"][1], "launch"):
            if not isinstance(item, MappingNode) or len(item.value) != 1:
                raise self.error(item, "launch", "each item must be exactly one of: arg, node, include")
            k_node, body = item.value[0]
            kind = str(self.value(k_node))
            if kind == "arg":
                self.read_arg(body)
            elif kind == "node":
                spec = self.read_node(body)
                if spec is not None:
                    nodes.append(spec)
            elif kind == "include":
                nodes.extend(self.read_include(body))
            else:
                raise self.error(k_node, kind, "unknown launch entity (known: arg, node, include)")
        unused = sorted(set(self.given) - set(self.arguments))
        if unused and self.depth == 0:
            raise LaunchError(self.path, None, "arg",
                              f"unknown launch argument(s) {', '.join(unused)} given on the command line "
                              f"(declared: {', '.join(sorted(self.arguments)) or 'none'})")
        return LaunchDescription(self.path, dict(self.arguments), nodes)

    def read_arg(self, body: Node) -> None:
        fields = self.mapping(body, "arg", ("name", "default", "description", "choices"))
        if "name" not in fields:
            raise self.error(body, "arg", "missing 'name'")
        name = self.text(fields["name"][1], "arg.name")
        if name in self.given:
            self.arguments[name] = self.given[name]
        elif "default" in fields:
            self.arguments[name] = self.text(fields["default"][1], f"arg {name}.default")
        else:
            raise self.error(body, f"arg {name}", f"required launch argument has no default: pass {name}:=VALUE")

    def read_node(self, body: Node) -> NodeSpec | None:
        allowed = ("pkg", "exec", "name", "namespace", "ns", "param", "remap", "respawn", "respawn_delay",
                   "required", "on_exit", "output", "args", "env", "if", "unless")
        fields = self.mapping(body, "node", allowed)
        if not self.enabled(fields, "node"):
            return None
        for needed in ("pkg", "exec"):
            if needed not in fields:
                raise self.error(body, "node", f"missing '{needed}'")
        spec = NodeSpec(package=self.text(fields["pkg"][1], "node.pkg"),
                        executable=self.text(fields["exec"][1], "node.exec"),
                        source=f"{self.path}:{body.start_mark.line + 1}")
        if self.resolve_exec is not None:
            try:
                self.resolve_exec(spec.package, spec.executable)
            except LookupError as exc:
                bad_key = "pkg" if str(exc).startswith("unknown package") else "exec"
                raise self.error(fields[bad_key][1], f"node.{bad_key}", str(exc)) from None
        if "name" in fields:
            spec.name = self.text(fields["name"][1], "node.name")
        ns_key = "namespace" if "namespace" in fields else "ns" if "ns" in fields else None
        if ns_key:
            ns = self.text(fields[ns_key][1], f"node.{ns_key}").strip()
            spec.namespace = ns if ns.startswith("/") else "/" + ns
        key = f"node {spec.label}"
        if "param" in fields:
            for entry in self.sequence(fields["param"][1], f"{key}.param"):
                self.read_param(entry, spec, key)
        if "remap" in fields:
            for entry in self.sequence(fields["remap"][1], f"{key}.remap"):
                remap = self.mapping(entry, f"{key}.remap", ("from", "to"))
                if set(remap) != {"from", "to"}:
                    raise self.error(entry, f"{key}.remap", "needs both 'from' and 'to'")
                spec.remaps.append((self.text(remap["from"][1], f"{key}.remap.from"),
                                    self.text(remap["to"][1], f"{key}.remap.to")))
        if "respawn" in fields:
            spec.respawn = self.flag(fields["respawn"][1], f"{key}.respawn")
        if "respawn_delay" in fields:
            spec.respawn_delay_s = self.number(fields["respawn_delay"][1], f"{key}.respawn_delay")
        if "required" in fields:
            spec.required = self.flag(fields["required"][1], f"{key}.required")
        if "on_exit" in fields:
            action = self.text(fields["on_exit"][1], f"{key}.on_exit")
            if action != "shutdown":
                raise self.error(fields["on_exit"][1], f"{key}.on_exit", "only 'shutdown' is supported")
            spec.required = True
        if "args" in fields:
            spec.args = self.text(fields["args"][1], f"{key}.args").split()
        if "env" in fields:
            for entry in self.sequence(fields["env"][1], f"{key}.env"):
                env = self.mapping(entry, f"{key}.env", ("name", "value"))
                if set(env) != {"name", "value"}:
                    raise self.error(entry, f"{key}.env", "needs both 'name' and 'value'")
                spec.env[self.text(env["name"][1], f"{key}.env.name")] = self.text(env["value"][1], f"{key}.env.value")
        return spec

    def read_param(self, entry: Node, spec: NodeSpec, key: str) -> None:
        fields = self.mapping(entry, f"{key}.param", ("name", "value", "from"))
        if "from" in fields:
            if len(fields) != 1:
                raise self.error(entry, f"{key}.param", "'from' stands alone (a parameter file)")
            node = fields["from"][1]
            path = _as_path(self.text(node, f"{key}.param.from"), self.dir)
            if not path.is_file():
                raise self.error(node, f"{key}.param.from", f"parameter file not found: {path}")
            try:
                yaml.safe_load(path.read_text())
            except yaml.YAMLError as exc:
                mark = getattr(exc, "problem_mark", None)
                where = f"{path}:{mark.line + 1}" if mark else str(path)
                raise self.error(node, f"{key}.param.from", f"parameter file {where} is not valid YAML") from None
            spec.param_files.append(path.resolve())
            return
        if set(fields) != {"name", "value"}:
            raise self.error(entry, f"{key}.param", "needs 'name' and 'value' (or 'from' for a file)")
        name = self.text(fields["name"][1], f"{key}.param.name")
        value = self.param_value(fields["value"][1], f"{key}.param {name}")
        if isinstance(value, dict):
            raise self.error(fields["value"][1], f"{key}.param {name}", "nested values: use a parameter file")
        spec.params[name] = value

    def read_include(self, body: Node) -> list[NodeSpec]:
        fields = self.mapping(body, "include", ("file", "arg", "if", "unless"))
        if not self.enabled(fields, "include"):
            return []
        if "file" not in fields:
            raise self.error(body, "include", "missing 'file'")
        if self.depth > 8:
            raise self.error(body, "include", "includes nested deeper than 8 (a cycle?)")
        path = _as_path(self.text(fields["file"][1], "include.file"), self.dir)
        passed = dict(self.arguments)
        if "arg" in fields:
            for entry in self.sequence(fields["arg"][1], "include.arg"):
                arg = self.mapping(entry, "include.arg", ("name", "value"))
                if set(arg) != {"name", "value"}:
                    raise self.error(entry, "include.arg", "needs both 'name' and 'value'")
                passed[self.text(arg["name"][1], "include.arg.name")] = self.text(arg["value"][1], "include.arg.value")
        if not path.is_file():
            raise self.error(fields["file"][1], "include.file", f"launch file not found: {path}")
        return load_launch(path, passed, self.resolve_exec, depth=self.depth + 1).nodes


def load_launch(path: Path | str, arguments: Mapping[str, str] | None = None,
                resolve_exec: ExecResolver | None = None, depth: int = 0) -> LaunchDescription:
    """Read a YAML launch file.

    Args:
        path: the launch file.
        arguments: ``name -> value`` from the command line (``name:=value``).
        resolve_exec: called with (package, executable) for every node; raises LookupError
            for an unknown one so the error can name the line.
        depth: include depth (internal).

    Raises:
        LaunchError: anything wrong with the file, in one line naming the file, line and key.
    """
    path = Path(path)
    if not path.is_file():
        raise LaunchError(path, None, "", "launch file not found")
    text = path.read_text()
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line = mark.line + 1 if mark else None
        raise LaunchError(path, line, "", f"YAML syntax error: {exc.problem or exc.context}") from None
    except yaml.YAMLError as exc:
        raise LaunchError(path, None, "", f"YAML error: {exc}") from None
    if root is None:
        raise LaunchError(path, 1, "launch", "the file is empty")
    return _Reader(path, dict(arguments or {}), resolve_exec, depth).read(root)


def parse_cli_arguments(items: list[str]) -> dict[str, str]:
    """``["a:=1", "b:=x"]`` -> ``{"a": "1", "b": "x"}``; raises ValueError for another form."""
    out: dict[str, str] = {}
    for item in items:
        if ":=" not in item:
            raise ValueError(f"launch arguments are written name:=value, got '{item}'")
        name, value = item.split(":=", 1)
        out[name.strip()] = value
    return out


def load_groups(path: Path | str) -> dict[str, list[str]]:
    """``group -> node names`` from a groups file (a YAML mapping of lists); LaunchError when malformed."""
    path = Path(path)
    if not path.is_file():
        return {}
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        raise LaunchError(path, mark.line + 1 if mark else None, "", "not valid YAML") from None
    if not isinstance(data, dict) or not all(isinstance(v, list) and all(isinstance(n, str) for n in v)
                                             for v in data.values()):
        raise LaunchError(path, None, "", "expected a mapping of group name -> list of node names")
    return {str(k): list(v) for k, v in data.items()}


def select_nodes(description: LaunchDescription, groups: list[str], exclude: list[str],
                 known_groups: Mapping[str, list[str]]) -> LaunchDescription:
    """The nodes of ``groups`` (group or node names; empty: all) less those named in ``exclude``.

    Raises:
        LaunchError: a name is neither a group nor a node of the file, or nothing is left.
    """
    labels = [n.label for n in description.nodes]

    def expand(names: list[str], what: str) -> set:
        out: set = set()
        for name in names:
            if name in labels:
                out.add(name)
            elif name in known_groups:
                out.update(n for n in known_groups[name] if n in labels)
            else:
                raise LaunchError(description.file, None, what,
                                  f"'{name}' is neither a group ({', '.join(sorted(known_groups)) or 'none defined'}) "
                                  f"nor a node of this file ({', '.join(labels)})")
        return out

    keep = expand(groups, "--group") if groups else set(labels)
    keep -= expand(exclude, "--exclude")
    nodes = [n for n in description.nodes if n.label in keep]
    if not nodes:
        raise LaunchError(description.file, None, "--group",
                          f"no node of this file is in {', '.join(groups) or 'the selection'}"
                          f"{' less ' + ', '.join(exclude) if exclude else ''} (nodes: {', '.join(labels)})")
    return LaunchDescription(description.file, description.arguments, nodes)
