"""Configuration in one place: every shipped YAML checked against the one parameter table, and
every way in (file, overrides, ``PipelineConfig.from_dict``/``from_yaml``, the node core) the same check."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from pcc_ros.errors import ConfigError
from pcc_ros.pipeline.config import (
    CONFIG_FILES,
    NODE_NAMES,
    PipelineConfig,
    load_config,
    load_file,
    load_parameters,
    node_parameters,
    parameter_specs,
    pipeline_config,
    read_parameters,
    shipped_config_dir,
)

CONFIG = Path(__file__).resolve().parents[1] / "config"
SHIPPED = sorted(CONFIG.glob("*.yaml"))


def _nodes(path: Path) -> list[str]:
    """The node names of a parameter file's blocks (``/**/detection_filter_node`` -> ``detection_filter_node``)."""
    return [key.rsplit("/", 1)[-1] for key in yaml.safe_load(path.read_text())]


def test_every_shipped_yaml_is_a_node_file():
    assert {p.name for p in SHIPPED} >= set(CONFIG_FILES.values())
    assert shipped_config_dir().resolve() == CONFIG.resolve()
    for path in SHIPPED:
        assert set(_nodes(path)) <= set(NODE_NAMES.values()), path


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.name)
def test_shipped_yaml_values_follow_the_parameter_table(path):
    specs = parameter_specs()
    for node in _nodes(path):
        raw = read_parameters(path, node)
        checked = load_file(path, node)  # every key known, typed, within its range or choices
        for name, value in raw.items():
            spec = specs[name]
            assert spec.description and checked[name] == (list(value) if isinstance(value, list) else value), name
            if spec.range is not None:
                assert spec.range[0] <= value <= spec.range[1], name
            if spec.choices is not None:
                assert value in spec.choices, name
        # the pipeline config of the file is the same whichever way it is read
        assert PipelineConfig.from_yaml(path, node) == pipeline_config(checked) == PipelineConfig.from_dict(raw)


@pytest.mark.parametrize("with_filter", [False, True])
def test_default_config_is_the_shipped_file_of_the_node(with_filter):
    mode = "filter" if with_filter else "completion"
    assert load_parameters(None, with_filter) == load_file(CONFIG / CONFIG_FILES[mode], NODE_NAMES[mode])
    config, slop = load_config(None, with_filter, backend="mirror")
    assert config.backend == "mirror" and slop == load_parameters(None, with_filter)["sync_slop"]


@pytest.mark.parametrize(("line", "message"), [
    ("min_points: 0", r"'min_points' = 0 is outside \[1, 100000\]"),
    ("queue_size: '2'", r"'queue_size' must be an integer"),
    ("rule: strict", r"'rule' = 'strict' is not one of"),
    ("mni_points: 3", r"unknown node parameter\(s\): \['mni_points'\]"),
])
def test_a_bad_file_is_refused_naming_the_file_and_the_parameter(tmp_path, line, message):
    path = tmp_path / "bad.yaml"
    path.write_text(f"/**/completion_node:\n  ros__parameters:\n    {line}\n")
    with pytest.raises(ConfigError, match=rf"bad\.yaml: .*{message}"):
        load_parameters(path)
    with pytest.raises(ConfigError, match=message):
        PipelineConfig.from_yaml(path)
    with pytest.raises(ConfigError, match=message):
        node_parameters(read_parameters(path))  # what the node core does with the same values


@pytest.mark.parametrize(("text", "message"), [
    ("/**/completion_node:\n  ros__parameters:\n    min_points: [1\n", r"bad\.yaml:4:1: not valid YAML \(expected ','"),
    ("/**/completion_node:\n\tros__parameters: {}\n", r"bad\.yaml:2:1: not valid YAML \(found character '\\t'"),
    (None, r"bad\.yaml: cannot read parameter file \(No such file or directory\) — check the path"),
    (b"\x89PNG\r\n\x1a\n\xff\xfe", r"bad\.yaml: cannot read parameter file \(not UTF-8 text: .*\) — check the path"),
    # UTF-8 but a control character (the head of a .safetensors file): PyYAML's report spans two lines
    (b"\x08\x00\x00{}", r"bad\.yaml: not valid YAML \(unacceptable character #x0008: .* position 0\) — fix the file"),
])
def test_an_unreadable_file_is_one_line_naming_file_and_line(tmp_path, text, message):
    path = tmp_path / "bad.yaml"
    if isinstance(text, bytes):  # an image or a bag given where the YAML belongs
        path.write_bytes(text)
    elif text is not None:
        path.write_text(text)
    with pytest.raises(ConfigError, match=message) as caught:
        load_parameters(path)
    assert "\n" not in str(caught.value)


def test_overrides_are_checked_like_the_file(tmp_path):
    with pytest.raises(ConfigError, match=r"completion\.yaml: parameter 'device' must be a string"):
        load_parameters(None, False, device=3)
    assert load_parameters(None, False, device=None)["device"] == load_parameters()["device"]  # None: the file's


def test_a_file_is_parsed_once_and_an_override_does_not_hide_its_bad_value(tmp_path, monkeypatch):
    path = tmp_path / "bad.yaml"
    path.write_text("/**/completion_node:\n  ros__parameters:\n    backend: 3\n")
    with pytest.raises(ConfigError, match=r"bad\.yaml: parameter 'backend' must be a string"):
        load_parameters(path, backend="mirror")  # the file is what a node would refuse
    path.write_text("/**/other_node:\n  ros__parameters:\n    min_points: 7\n")
    parses = []
    monkeypatch.setattr(yaml, "safe_load", lambda text: parses.append(text) or yaml.load(text, yaml.SafeLoader))
    values = load_parameters(path, backend="mirror")  # no completion_node block: the file's first block
    assert values["min_points"] == 7 and values["backend"] == "mirror" and len(parses) == 1
