"""The ROS 2 / pip packaging itself: package.xml, setup.cfg, entry points, installed layout."""

from __future__ import annotations

import configparser
import os
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
from conftest import colcon_style_install

from pcc_ros.cli.main import COMMANDS, available_commands, build_parser

REPO = Path(__file__).resolve().parents[1]


def test_package_xml_format_and_dependencies():
    root = ET.parse(REPO / "package.xml").getroot()
    assert root.tag == "package" and root.get("format") == "3"
    assert root.findtext("name") == "pcc_ros"
    assert root.find("export/build_type").text == "ament_python"
    exec_deps = {e.text for e in root.findall("exec_depend")}
    for dep in ("rclpy", "std_msgs", "sensor_msgs", "geometry_msgs", "visualization_msgs",
                "vision_msgs", "tf2_ros", "python3-numpy"):
        assert dep in exec_deps, dep
    assert "python3-pytest" in {e.text for e in root.findall("test_depend")}


def test_setup_cfg_puts_scripts_under_lib_pcc_ros():
    cfg = configparser.ConfigParser()
    cfg.read(REPO / "setup.cfg")
    assert cfg["develop"]["script_dir"] == "$base/lib/pcc_ros"
    assert cfg["install"]["install_scripts"] == "$base/lib/pcc_ros"


def test_resource_marker_and_config_exist():
    assert (REPO / "resource" / "pcc_ros").is_file()
    assert list((REPO / "config").glob("*.yaml"))
    assert (REPO / "bags" / "README.md").is_file()


def test_console_entry_points_resolve():
    import importlib
    import re

    text = (REPO / "setup.py").read_text()
    for module, func in re.findall(r"= ([\w.]+):(\w+)", text):
        assert callable(getattr(importlib.import_module(module), func))


def test_cli_registry_modules_expose_the_command_protocol():
    import importlib

    parser = build_parser()  # imports every available command module
    assert parser.prog == "pcc"
    for name, (module_name, _) in available_commands().items():
        module = importlib.import_module(module_name)
        assert hasattr(module, "add_arguments") and hasattr(module, "run"), name
    assert set(available_commands()) == set(COMMANDS)  # every registered command is in this install


def test_command_descriptions_are_docstrings_as_plain_text():
    """``--help`` shows a command's docstring without reStructuredText markup (cli.text, the
    one place ``pcc`` and ``pcc bench`` make help text)."""
    from pcc_ros.cli.text import plain_text

    doc = "Run :func:`~pcc_ros.x.run` of :mod:`pcc_ros.y` (``pcc z``)."
    assert plain_text(doc) == "Run pcc_ros.x.run of pcc_ros.y (pcc z)."
    parser = build_parser()
    commands = next(a for a in parser._actions if a.dest == "command").choices
    described = {name: command.description for name, command in commands.items()}
    assert "(pcc eval detections)" in described["eval-detections"]  # its docstring says ``pcc eval detections``
    assert not [name for name, text in described.items() if "``" in text or ":mod:`" in text or ":func:`" in text]


def test_pcc_help_runs_as_a_program():
    out = subprocess.run([sys.executable, "-m", "pcc_ros.cli", "--help"], capture_output=True, text=True)
    assert out.returncode == 0 and "usage: pcc" in out.stdout


def test_import_pcc_ros_needs_no_ros():
    code = "import sys, pcc_ros, pcc_ros.cli.main; assert 'rclpy' not in sys.modules; print('ok')"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.stdout.strip() == "ok", out.stderr


@pytest.mark.parametrize("given, policy, expected", [(None, None, "10000"), ("7", None, "7"),
                                                     (None, "passive", "unset")])
def test_import_pcc_ros_shortens_openmp_spin_before_torch_loads(given, policy, expected):
    """libgomp reads GOMP_SPINCOUNT once, when torch loads it: ``import pcc_ros`` (which every
    entry point does first) sets the short default then, and keeps a value the user gave; with
    OMP_WAIT_POLICY set it sets none (libgomp would take it over the policy's spin)."""
    import os

    env = {k: v for k, v in os.environ.items() if k not in ("GOMP_SPINCOUNT", "OMP_WAIT_POLICY")}
    if given is not None:
        env["GOMP_SPINCOUNT"] = given
    if policy is not None:
        env["OMP_WAIT_POLICY"] = policy
    code = ("import os, sys, pcc_ros; assert 'torch' not in sys.modules; "
            "print(os.environ.get('GOMP_SPINCOUNT', 'unset'))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    assert out.stdout.strip() == expected, out.stderr


@pytest.mark.slow
def test_colcon_style_install_layout(tmp_path):
    """What colcon runs for an ament_python package places scripts and data correctly."""
    prefix = tmp_path / "install"
    out = colcon_style_install(prefix, tmp_path)
    assert out.returncode == 0, out.stderr[-2000:]
    assert (prefix / "lib" / "pcc_ros" / "pcc").is_file()
    share = prefix / "share" / "pcc_ros"
    assert (share / "package.xml").is_file()
    assert (prefix / "share" / "ament_index" / "resource_index" / "packages" / "pcc_ros").is_file()
    for cfg in [*(REPO / "config").glob("*.yaml"), REPO / "config" / "fastdds_large_data.xml"]:
        assert (share / "config" / cfg.name).is_file()
    for launch in (REPO / "launch").glob("*.launch.py"):
        assert (share / "launch" / launch.name).is_file()
    for weights in (REPO / "pcc_ros" / "weights").glob("*.safetensors"):
        assert (share / "weights" / weights.name).is_file()


def test_readme_rosdep_line_skips_every_pip_key_of_package_xml():
    """rosdistro lacks some of the -pip keys (python3-rosbags-pip; python3-pytorch-pip is end-of-life),
    so the README's rosdep line skips them all and the next line pip-installs requirements.txt."""
    import re

    root = ET.parse(REPO / "package.xml").getroot()
    pip_keys = {e.text for e in root.iter() if e.tag.endswith("depend") and (e.text or "").endswith("-pip")}
    line = re.search(r"rosdep install [^\n]*\\\n\s*--skip-keys \"([^\"]+)\"", (REPO / "README.md").read_text())
    assert line, "README: the rosdep install line with --skip-keys is gone"
    assert pip_keys and pip_keys <= set(line.group(1).split()), pip_keys - set(line.group(1).split())


def test_a_named_command_imports_only_its_own_module(tmp_path):
    """``pcc train ...`` runs where the bag libraries (rosbags, mcap), open3d, matplotlib or
    scikit-image are missing, as on a lent training machine: only the named command's module is
    imported."""
    blocker = tmp_path / "sitecustomize.py"
    blocker.write_text(  # those packages look not installed (find_spec -> None)
        "from importlib.machinery import PathFinder\n"
        "_find = PathFinder.find_spec\n"
        "def _hide(name, path=None, target=None):\n"
        "    if name.split('.')[0] in ('rosbags', 'mcap', 'open3d', 'rclpy', 'matplotlib', 'skimage'):\n"
        "        return None\n"
        "    return _find(name, path, target)\n"
        "PathFinder.find_spec = staticmethod(_hide)\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), str(Path(__file__).resolve().parents[1])])}
    out = subprocess.run([sys.executable, "-m", "pcc_ros.cli", "train", "--help"], capture_output=True, text=True,
                         env=env)
    assert out.returncode == 0 and "--max-minutes" in out.stdout, out.stderr
    parser = build_parser(only="train")
    commands = next(a for a in parser._actions if a.dest == "command").choices
    assert list(commands) == ["train"]
