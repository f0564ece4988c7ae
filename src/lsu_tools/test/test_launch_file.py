"""The YAML launch reader: what it accepts and the one-line errors it gives."""

from pathlib import Path

import pytest
import yaml

from lsu_tools.launch_file import LaunchError, load_launch, parse_cli_arguments
from lsu_tools.nodes_index import resolve_executable


def write(tmp_path: Path, text: str, name: str = "t.launch.yaml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


GOOD = """\
launch:
- arg: {name: ns, default: lsu}
- arg: {name: rate, default: "12.5"}
- node:
    pkg: lsu_tools
    exec: selftest_talker
    name: talker
    namespace: $(var ns)
    param:
    - from: $(dirname)/p.yaml
    - {name: rate_hz, value: $(var rate)}
    - {name: label, value: "plain text"}
    - {name: sizes, value: [1, 2, 3]}
    remap:
    - {from: selftest/state, to: /elsewhere/state}
    respawn: true
    respawn_delay: 0.5
- node:
    pkg: lsu_tools
    exec: selftest_listener
    required: true
    if: $(var with_listener)
"""


def test_good_file_gives_nodes_with_names_params_remaps(tmp_path):
    (tmp_path / "p.yaml").write_text("/**:\n  ros__parameters: {track_steps: 100}\n")
    src = "launch:\n- arg: {name: with_listener, default: 'true'}\n" + GOOD.split("launch:\n", 1)[1]
    desc = load_launch(write(tmp_path, src), {"rate": "20"}, resolve_executable)
    talker, listener = desc.nodes
    assert (talker.package, talker.executable, talker.name, talker.namespace) == \
        ("lsu_tools", "selftest_talker", "talker", "/lsu")
    # a substituted value is read again as YAML (like launch_ros): "20" -> 20
    assert talker.params == {"rate_hz": 20, "label": "plain text", "sizes": [1, 2, 3]}
    assert talker.param_files == [(tmp_path / "p.yaml").resolve()]
    assert talker.remaps == [("selftest/state", "/elsewhere/state")]
    assert talker.respawn and talker.respawn_delay_s == 0.5 and not talker.required
    assert listener.required and listener.name is None
    args = talker.ros_args(tmp_path / "inline.yaml")
    assert args[:5] == ["--ros-args", "-r", "__node:=talker", "-r", "__ns:=/lsu"]
    assert "--params-file" in args and "selftest/state:=/elsewhere/state" in args
    inline = yaml.safe_load(talker.inline_params_yaml())
    assert inline == {"/**": {"ros__parameters": talker.params}}


def test_if_false_drops_the_node(tmp_path):
    (tmp_path / "p.yaml").write_text("{}\n")
    src = "launch:\n- arg: {name: with_listener, default: 'false'}\n" + GOOD.split("launch:\n", 1)[1]
    desc = load_launch(write(tmp_path, src), {}, resolve_executable)
    assert [n.executable for n in desc.nodes] == ["selftest_talker"]


def test_include_passes_arguments(tmp_path):
    write(tmp_path, "launch:\n- arg: {name: who}\n- node: {pkg: lsu_tools, exec: selftest_talker, name: $(var who)}\n",
          "inner.launch.yaml")
    outer = write(tmp_path, "launch:\n- include:\n    file: $(dirname)/inner.launch.yaml\n    arg: [{name: who, value: bob}]\n")
    assert [n.name for n in load_launch(outer, {}, resolve_executable).nodes] == ["bob"]


def one_line_error(path: Path, args=None) -> LaunchError:
    with pytest.raises(LaunchError) as info:
        load_launch(path, args or {}, resolve_executable)
    assert "\n" not in str(info.value)
    assert str(path) in str(info.value)
    return info.value


def test_syntax_error_names_the_line(tmp_path):
    err = one_line_error(write(tmp_path, "launch:\n- node:\n    pkg: lsu_tools\n    exec: [unclosed\n"))
    assert err.line in (4, 5) and "YAML syntax error" in str(err)


def test_unknown_package_names_line_and_key(tmp_path):
    err = one_line_error(write(tmp_path, "launch:\n- node:\n    pkg: lsu_nothing\n    exec: x\n"))
    assert err.line == 3 and err.key == "node.pkg" and "unknown package 'lsu_nothing'" in str(err)


def test_unknown_executable_lists_what_exists(tmp_path):
    err = one_line_error(write(tmp_path, "launch:\n- node:\n    pkg: lsu_tools\n    exec: no_such_node\n"))
    assert err.line == 4 and err.key == "node.exec"
    assert "no executable 'no_such_node'" in str(err) and "selftest_talker" in str(err)


def test_missing_param_file(tmp_path):
    err = one_line_error(write(tmp_path, "launch:\n- node:\n    pkg: lsu_tools\n    exec: selftest_talker\n"
                                          "    param:\n    - from: missing.yaml\n"))
    assert err.line == 6 and "param.from" in err.key and "parameter file not found" in str(err)


def test_unknown_var(tmp_path):
    err = one_line_error(write(tmp_path, "launch:\n- node:\n    pkg: lsu_tools\n    exec: selftest_talker\n"
                                          "    name: $(var nobody)\n"))
    assert err.line == 5 and "$(var nobody)" in str(err)


def test_unknown_key_is_a_typo_not_silence(tmp_path):
    err = one_line_error(write(tmp_path, "launch:\n- node:\n    pkg: lsu_tools\n    exec: selftest_talker\n"
                                          "    respwan: true\n"))
    assert err.line == 5 and err.key == "node.respwan"


def test_required_argument_and_unknown_cli_argument(tmp_path):
    path = write(tmp_path, "launch:\n- arg: {name: port}\n")
    assert "pass port:=VALUE" in str(one_line_error(path))
    path = write(tmp_path, "launch:\n- arg: {name: port, default: x}\n")
    assert "unknown launch argument(s) prot" in str(one_line_error(path, {"prot": "y"}))


def test_not_a_launch_file(tmp_path):
    assert "must start with 'launch:'" in str(one_line_error(write(tmp_path, "nodes: []\n")))
    assert "empty" in str(one_line_error(write(tmp_path, "")))


def test_cli_arguments():
    assert parse_cli_arguments(["a:=1", "b:=x:=y"]) == {"a": "1", "b": "x:=y"}
    with pytest.raises(ValueError, match="name:=value"):
        parse_cli_arguments(["a=1"])


def test_dirname_is_absolute_when_the_file_is_given_relative(tmp_path, monkeypatch):
    (tmp_path / "sub").mkdir()
    (tmp_path / "p.yaml").write_text("{}\n")
    write(tmp_path / "sub", "launch:\n- node:\n    pkg: lsu_tools\n    exec: selftest_talker\n"
                            "    param:\n    - from: $(dirname)/../p.yaml\n")
    monkeypatch.chdir(tmp_path)
    desc = load_launch("sub/t.launch.yaml", {}, resolve_executable)
    assert desc.nodes[0].param_files == [(tmp_path / "p.yaml").resolve()]


def test_find_pkg_share_names_the_folder_with_the_package_xml(tmp_path):
    import xml.etree.ElementTree as ET

    desc = load_launch(write(tmp_path, "launch:\n- arg: {name: where, default: $(find-pkg-share lsu_tools)}\n"
                                       "- node: {pkg: lsu_tools, exec: selftest_talker, name: $(var where)}\n"),
                       {}, None)
    share = Path(desc.arguments["where"])
    assert ET.parse(share / "package.xml").getroot().findtext("name") == "lsu_tools"
    err = one_line_error(write(tmp_path, "launch:\n- arg: {name: w, default: $(find-pkg-share lsu_nowhere)}\n"))
    assert "unknown package 'lsu_nowhere'" in str(err)
