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


def test_a_partial_rule_gives_the_weights_it_does_not_name_weight_0(tmp_path, caplog):
    """A file written before the profile terms (its own calibrated weights, none of theirs)
    does not inherit the shipped weights of those terms: they are 0, said in one INFO line."""
    old_rule = ("w_bias: -3.0\nw_density: -1.2\nw_free_space: 0.4\nw_ground_gap: 2.0\nw_score: 0.0\n"
                "w_mismatch: 0.0\nreject_threshold: 0.6\n")
    path = tmp_path / "old.yaml"
    path.write_text("/**/detection_filter_node:\n  ros__parameters:\n    backend: input\n"
                    + "".join(f"    {line}\n" for line in old_rule.splitlines()))
    with caplog.at_level("INFO", logger="pcc_ros.pipeline.filter"):
        config = PipelineConfig.from_yaml(path).filter
    assert (config.w_bias, config.w_density, config.w_ground_gap, config.reject_threshold) == (-3.0, -1.2, 2.0, 0.6)
    assert all(getattr(config, f"w_{t}") == 0.0 for t in ("above", "fill", "spill", "overlap", "depth", "top"))
    lines = [r.getMessage() for r in caplog.records if "calibrated rule is a whole" in r.getMessage()]
    missing = lines[0].split(" but not ")[1] if len(lines) == 1 else ""
    assert "w_above" in missing and "w_overlap" in missing and "w_density" not in missing
    # an override naming a weight on top of the file names the same rule (the file's, plus it)
    tweaked = pipeline_config(load_parameters(path, True, w_depth=2.0)).filter
    assert (tweaked.w_depth, tweaked.w_density, tweaked.w_overlap) == (2.0, -1.2, 0.0)


def test_the_shipped_rule_is_whole_and_kept_whole(caplog):
    """The shipped file names every weight: nothing is zeroed, nothing logged; a parameter set
    that names no weight keeps the shipped rule; an override of one weight on the shipped file is
    refused while the file's trees (boosted from its weights) stay, and with ``trees: ""`` changes
    that weight only."""
    from pcc_ros.errors import ConfigError
    from pcc_ros.pipeline.filter import RULE_WEIGHTS, FilterConfig

    shipped = (CONFIG / CONFIG_FILES["filter"]).read_text()
    assert all(f"    {w}:" in shipped for w in RULE_WEIGHTS)  # calibrate-filter wrote every one
    with caplog.at_level("INFO", logger="pcc_ros.pipeline.filter"):
        config, _ = load_config(None, with_filter=True)
        tweaked, _ = load_config(None, with_filter=True, w_score=0.5, trees="")
        plain = pipeline_config(node_parameters({"backend": "input"}))
    assert not [r for r in caplog.records if "calibrated rule is a whole" in r.getMessage()]
    assert config.filter.weighted_terms == FilterConfig().weighted_terms and config.filter.w_overlap != 0.0
    assert tweaked.filter.w_score == 0.5 and tweaked.filter.w_overlap == config.filter.w_overlap
    assert plain.filter.weights.tolist() == FilterConfig().weights.tolist()
    assert config.filter.trees == "shipped" == plain.filter.trees and tweaked.filter.trees == ""
    with pytest.raises(ConfigError, match="boosted from other filter weights"):
        load_config(None, with_filter=True, w_score=0.5)


def test_the_nuscenes_preset_keeps_the_shipped_rule():
    """config/detection_filter_nuscenes.yaml is the shipped rule with nuScenes' options: the same
    weights, trees and per-layout thresholds (a recalibration of the shipped file must reach it)."""
    shipped, _ = load_config(None, with_filter=True)
    nuscenes, _ = load_config(CONFIG / "detection_filter_nuscenes.yaml", with_filter=True)
    a, b = shipped.filter, nuscenes.filter
    assert a.weights.tolist() == b.weights.tolist() and a.w_bias == b.w_bias and a.trees == b.trees == "shipped"
    assert (a.sensor_thresholds, a.reject_threshold) == (b.sensor_thresholds, b.reject_threshold)
    assert b.score_mapping == "identity" and b.sensor == "auto"


def test_per_layout_thresholds_belong_to_the_weights_they_were_set_for():
    """The shipped file's sensor_thresholds stay with its weights (an override of reject_threshold
    on it changes the fallback only); a file or parameter set with its own rule or threshold and no
    table judges every sensor by its own reject_threshold (the KITTI preset must not inherit the
    shipped table)."""
    from pcc_ros.pipeline.filter import parse_sensor_thresholds

    shipped, _ = load_config(None, with_filter=True)
    assert parse_sensor_thresholds(shipped.filter.sensor_thresholds)["hdl64"] != shipped.filter.reject_threshold
    fallback, _ = load_config(None, with_filter=True, reject_threshold=0.6)
    assert fallback.filter.sensor_thresholds == shipped.filter.sensor_thresholds
    assert fallback.filter.reject_threshold == 0.6
    kitti, _ = load_config(CONFIG / "detection_filter_kitti.yaml", with_filter=True)
    assert kitti.filter.sensor_thresholds == ""
    own = pipeline_config(node_parameters({"backend": "input", "reject_threshold": 0.6}))
    assert own.filter.sensor_thresholds == "" and own.filter.reject_threshold == 0.6
    table = pipeline_config(node_parameters({"reject_threshold": 0.6, "sensor_thresholds": "vlp16:0.4"}))
    assert table.filter.sensor_thresholds == "vlp16:0.4"


def test_calibrate_filter_writes_every_weight(tmp_path):
    """pcc calibrate-filter's YAML names every term weight, those it fitted at 0 too."""
    import numpy as np

    from pcc_ros.pipeline.filter import RULE_WEIGHTS, TERMS
    from pcc_ros.workflows.filter_calibration import preset_yaml

    base = tmp_path / "base.yaml"
    base.write_text("/**/detection_filter_node:\n  ros__parameters:\n    backend: input\n")
    weights = np.zeros(len(TERMS))
    weights[TERMS.index("density")] = -1.0
    text = preset_yaml(base, -2.0, weights, 0.7, {}, "# calibrated: test\n")
    path = tmp_path / "out.yaml"
    path.write_text(text)
    assert all(f"{w}:" in text for w in RULE_WEIGHTS)
    config = PipelineConfig.from_yaml(path).filter
    assert config.weighted_terms == ("density",) and config.w_bias == -2.0
    # the shipped file as the base: its per-layout table belongs to its weights, not these
    shipped_base = preset_yaml(CONFIG / CONFIG_FILES["filter"], -2.0, weights, 0.7, {}, "# calibrated: test\n")
    path.write_text(shipped_base)
    assert 'sensor_thresholds: ""' in shipped_base and PipelineConfig.from_yaml(path).filter.sensor_thresholds == ""
