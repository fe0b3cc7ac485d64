"""The launch file and the Foxglove layout: the launch file run against stand-ins of launch and
launch_ros (no wheel exists for them) declares its arguments, passes parameters the table
knows and remaps exactly the node's inputs; the layout shows only topics the node
publishes; both are installed with the package."""

from __future__ import annotations

import importlib.util
import json
import re
import sys
import types

import pytest

from conftest import REPO
from pothole_detector.ros.outputs import OUTPUT_TYPES
from pothole_detector.params import PARAMETER_BY_NAME


class _Recorded:
    """A stand-in for a launch class or substitution: keeps its arguments."""

    def __init__(self, *args, **kwargs):
        self.args, self.kwargs = args, kwargs


def _text(value) -> str:
    """A substitution (or list of them) written out, LaunchConfiguration as $name."""
    if isinstance(value, (list, tuple)):
        return "".join(_text(part) for part in value)
    if isinstance(value, _Recorded):
        if value.kind == "LaunchConfiguration":
            return f"${value.args[0]}"
        return _text(list(value.args[0]) if value.args else [])
    return str(value)


@pytest.fixture
def launch_description(monkeypatch):
    modules = {}
    for name, classes in {"launch": ["LaunchDescription"], "launch.actions":
                          ["DeclareLaunchArgument"], "launch.substitutions":
                          ["LaunchConfiguration", "PathJoinSubstitution", "PythonExpression"],
                          "launch_ros": [], "launch_ros.actions": ["Node"],
                          "launch_ros.substitutions": ["FindPackageShare"]}.items():
        module = types.ModuleType(name)
        for cls in classes:
            setattr(module, cls, type(cls, (_Recorded,), {"kind": cls}))
        modules[name] = module
    for name, module in modules.items():
        monkeypatch.setitem(sys.modules, name, module)
    spec = importlib.util.spec_from_file_location(
        "pothole_launch", REPO / "launch" / "pothole_detector.launch.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.generate_launch_description()


def test_the_launch_file_wires_the_node_to_a_camera(launch_description):
    (entities,) = launch_description.args
    declared = {e.kwargs["name"] if "name" in e.kwargs else e.args[0]: e
                for e in entities if e.kind == "DeclareLaunchArgument"}
    (node,) = [e for e in entities if e.kind == "Node"]
    assert node.kwargs["executable"] == "pothole_detector_node"
    assert "pothole_detector_node = pothole_detector.ros.node_main:main" in \
        (REPO / "setup.py").read_text()
    _, overrides = node.kwargs["parameters"]
    for name in overrides:
        assert name in PARAMETER_BY_NAME and name in declared, name
    for name in ("image_transport", "rectify", "backend"):
        assert declared[name].kwargs["default_value"] == PARAMETER_BY_NAME[name].default
    remapped = {_text(source): _text(target) for source, target in
                node.kwargs["remappings"]}
    suffix = "'/compressed' if '$image_transport' == 'compressed' else ''"
    assert remapped == {
        f"left/image_rect{suffix}": f"$left_image{suffix}",
        f"right/image_rect{suffix}": f"$right_image{suffix}",
        "left/camera_info": "$left_camera_info", "right/camera_info": "$right_camera_info"}


def test_the_foxglove_layout_shows_what_the_node_publishes():
    layout = json.loads((REPO / "config" / "foxglove_layout.json").read_text())
    text = json.dumps(layout)
    topics = set(re.findall(r'"(/[a-z_/0-9]+)', text))
    published = {f"/stereo/{name}" for name in OUTPUT_TYPES} | {"/diagnostics"}
    assert topics and {t.split(".")[0] for t in topics} <= published, topics - published
    assert {"/stereo/overlay", "/stereo/points2", "/stereo/pothole_markers",
            "/stereo/potholes", "/diagnostics"} <= topics

    def panels(node):
        return [node] if isinstance(node, str) else panels(node["first"]) + \
            panels(node["second"])
    assert sorted(panels(layout["layout"])) == sorted(layout["configById"])


def test_launch_file_and_layout_are_installed():
    setup = (REPO / "setup.py").read_text()
    assert '"launch/pothole_detector.launch.py"' in setup
    assert '"config/foxglove_layout.json"' in setup
