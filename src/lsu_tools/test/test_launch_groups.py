"""`lsu launch FILE --group NAME`: the nodes of a part of a launch file, for a graph spread over two PCs."""

from pathlib import Path

import pytest

from lsu_tools.cli import config_dir
from lsu_tools.launch_file import LaunchError, load_groups, load_launch, select_nodes
from lsu_tools.nodes_index import resolve_executable

LAUNCH = config_dir() / "launch"
RIG = {"gp32_emulator", "gp32_driver", "stereo_camera"}
PROCESSING = {"laser_extractor", "stereo_matcher", "face_processor", "scan_coordinator"}


def labels(desc) -> set:
    return {n.label for n in desc.nodes}


def sim(**args: str):
    return load_launch(LAUNCH / "sim.launch.yaml", args, resolve_executable)


def test_rig_and_processing_groups_split_the_sim_graph_without_overlap_or_loss():
    groups = load_groups(LAUNCH / "groups.yaml")
    whole = sim()
    rig = select_nodes(whole, ["rig"], [], groups)
    processing = select_nodes(whole, ["processing"], [], groups)
    assert labels(rig) == RIG
    assert labels(processing) == PROCESSING
    assert labels(rig) | labels(processing) == labels(whole)
    # a node keeps everything the file gave it (parameters, environment, respawn)
    driver = next(n for n in rig.nodes if n.label == "gp32_driver")
    assert driver.env == {"FASTDDS_BUILTIN_TRANSPORTS": "UDPv4"} and driver.respawn


def test_extractor_on_the_rig_groups_move_exactly_the_extractor():
    groups = load_groups(LAUNCH / "groups.yaml")
    whole = sim()
    assert labels(select_nodes(whole, ["rig_extract"], [], groups)) == RIG | {"laser_extractor"}
    assert labels(select_nodes(whole, ["processing_lines"], [], groups)) == PROCESSING - {"laser_extractor"}
    # the same selection written with node names
    assert labels(select_nodes(whole, ["processing"], ["laser_extractor"], groups)) == PROCESSING - {"laser_extractor"}


def test_view_argument_adds_the_bridge_and_its_group_selects_it():
    groups = load_groups(LAUNCH / "groups.yaml")
    assert "foxglove_bridge" not in labels(sim())
    viewed = sim(view="true", view_port="9001")
    bridge = next(n for n in viewed.nodes if n.label == "foxglove_bridge")
    assert bridge.params == {"host": "127.0.0.1", "port": 9001}
    assert labels(select_nodes(viewed, ["processing", "view"], [], groups)) == PROCESSING | {"foxglove_bridge"}
    for name in ("lab", "replay"):
        desc = load_launch(LAUNCH / f"{name}.launch.yaml", {"view": "true"}, resolve_executable)
        assert "foxglove_bridge" in labels(desc)


def test_unknown_group_names_the_groups_and_nodes_there_are():
    groups = load_groups(LAUNCH / "groups.yaml")
    with pytest.raises(LaunchError) as err:
        select_nodes(sim(), ["rigg"], [], groups)
    text = str(err.value)
    assert "'rigg' is neither a group" in text and "processing" in text and "gp32_driver" in text


def test_a_selection_that_leaves_nothing_is_refused():
    groups = load_groups(LAUNCH / "groups.yaml")
    with pytest.raises(LaunchError, match="no node of this file"):
        select_nodes(sim(), ["rig"], ["rig"], groups)


def test_malformed_groups_file_is_one_line_error(tmp_path: Path):
    bad = tmp_path / "groups.yaml"
    bad.write_text("rig: gp32_driver\n")
    with pytest.raises(LaunchError, match="mapping of group name -> list of node names"):
        load_groups(bad)
