"""Messages to and from plain data / YAML (our rosidl_runtime_py stand-in)."""

import pytest
import yaml

from lsu_bags.rosmsg import InterfaceError, fill, get_interface, parse_yaml_mapping, to_data, to_yaml


def test_type_lookup_forms():
    assert get_interface("lsu_interfaces/msg/LaserLine").__name__ == "LaserLine"
    assert get_interface("lsu_interfaces/Step", "srv").__name__ == "Step"
    with pytest.raises(InterfaceError, match="std_msgs/msg/String"):
        get_interface("String")
    with pytest.raises(InterfaceError, match="not installed"):
        get_interface("nope_msgs/msg/X")
    with pytest.raises(InterfaceError, match="has no type 'Nope'"):
        get_interface("lsu_interfaces/msg/Nope")


def test_fill_and_back_round_trip():
    cls = get_interface("lsu_interfaces/msg/LaserLine")
    data = {"header": {"frame_id": "lsu_left_optical", "stamp": {"sec": 3, "nanosec": 5}},
            "image_width": 640, "u": [1.5, 2.25], "v": [10.0, 11.0], "method": "gaussian3"}
    msg = fill(cls(), data)
    back = to_data(msg)
    assert back["header"] == data["header"] and back["u"] == [1.5, 2.25] and back["image_width"] == 640
    assert yaml.safe_load(to_yaml(msg))["method"] == "gaussian3"


def test_sequence_of_messages_is_filled():
    cls = get_interface("diagnostic_msgs/msg/DiagnosticArray")
    msg = fill(cls(), {"status": [{"name": "a", "values": [{"key": "k", "value": "v"}]}]})
    assert msg.status[0].values[0].key == "k"


def test_long_arrays_are_abbreviated_for_printing():
    msg = fill(get_interface("lsu_interfaces/msg/LaserLine")(), {"u": list(range(100))})
    shown = yaml.safe_load(to_yaml(msg, array_limit=4))["u"]
    assert shown == [0.0, 1.0, 2.0, 3.0, "... 96 more"]
    assert len(to_data(msg)["u"]) == 100


def test_bad_fields_name_the_field():
    cls = get_interface("lsu_interfaces/srv/MoveTo").Request
    with pytest.raises(InterfaceError, match="no field 'positon'"):
        fill(cls(), {"positon": 3})
    with pytest.raises(InterfaceError, match="position_steps"):
        fill(cls(), {"position_steps": "far"})


def test_yaml_argument_parsing():
    assert parse_yaml_mapping("") == {}
    assert parse_yaml_mapping("{steps: 5}") == {"steps": 5}
    with pytest.raises(InterfaceError, match="mapping"):
        parse_yaml_mapping("[1, 2]")
