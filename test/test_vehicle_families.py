"""SynthCars vehicle families: the selectable mix, the small truck, aliases, and the per-family
evaluation's lookup of each track's family."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pcc_ros.data.synthetic.vehicles import (
    FAMILIES,
    FAMILY_WEIGHTS,
    LABELS,
    build_vehicle,
    family_weights,
    random_vehicle,
    sample_family,
)
from pcc_ros.errors import ConfigError, DataError


def test_mix_defaults_to_the_street_mix_and_resolves_aliases():
    assert family_weights(None) == FAMILY_WEIGHTS and family_weights(()) == FAMILY_WEIGHTS
    assert "truck" not in FAMILY_WEIGHTS  # not on the default streets
    assert family_weights([("estate", 1), ("van", 2)]) == {"wagon": 1.0, "van": 2.0}
    assert family_weights({"box_truck": 1}) == {"truck": 1.0}
    for bad in ([("lorry", 1)], [("van", -1)], [("van", 0)]):
        with pytest.raises(ValueError):
            family_weights(bad)
    # the default draws are those of the street mix (same seed, same vehicles as before the mix existed)
    a = [sample_family(np.random.default_rng(s)) for s in range(50)]
    names = list(FAMILY_WEIGHTS)
    p = np.array([FAMILY_WEIGHTS[n] for n in names])
    b = [names[int(np.random.default_rng(s).choice(len(names), p=p / p.sum()))] for s in range(50)]
    assert a == b
    rng = np.random.default_rng(0)
    assert {sample_family(rng, [("van", 1), ("truck", 1)]) for _ in range(40)} == {"van", "truck"}


def test_every_family_has_its_proportions():
    sizes = {f: np.mean([build_vehicle(f, np.random.default_rng(s)).size for s in range(6)], axis=0)
             for f in FAMILIES}
    aspect = {f: s[2] / s[0] for f, s in sizes.items()}  # height / length
    assert aspect["truck"] > aspect["van"] > aspect["sedan"]
    assert aspect["suv"] > aspect["wagon"] > aspect["sedan"]
    assert sizes["truck"][0] > sizes["pickup"][0] > sizes["sedan"][0] > sizes["hatchback"][0]
    assert 5.5 < sizes["truck"][0] < 7.0 and 2.5 < sizes["truck"][2] < 3.2
    truck = random_vehicle(np.random.default_rng(1), "box_truck")
    assert truck.family == "truck" and truck.label == LABELS["truck"] == "Truck"
    assert random_vehicle(np.random.default_rng(1), "estate").family == "wagon"


def test_vehicle_mix_flag_parses_and_refuses_unknown_families():
    from pcc_ros.cli.synth import parse_vehicle_mix

    assert parse_vehicle_mix("van=1, estate=2") == (("van", 1.0), ("wagon", 2.0))
    for bad in ("van", "lorry=1", "van=x", "van=0"):
        with pytest.raises(ConfigError, match="--vehicle-mix"):
            parse_vehicle_mix(bad)


def test_a_street_holds_only_the_families_asked_for():
    from pcc_ros.data.synthetic.scene import KIND_VEHICLE, SceneParams, build_street

    street = build_street(2, SceneParams(vehicle_mix=(("van", 1.0), ("truck", 1.0))), np.random.default_rng(3))
    names = {o.name for o in street.objects if o.kind == KIND_VEHICLE}
    assert names and names <= {"van", "truck"}


def test_families_of_a_synthcars_root(tmp_path):
    from pcc_ros.data.synthetic import load_families

    assert load_families(tmp_path) == {}
    (tmp_path / "meta.json").write_text(json.dumps({"splits": {"train": ["0000"]}}))
    assert load_families(tmp_path) == {}  # no tracks recorded: no families
    meta = {"sequences": {"0000": {"tracks": {"3": {"name": "van"}, "4": {"name": "sedan"}}}}}
    (tmp_path / "meta.json").write_text(json.dumps(meta))
    assert load_families(tmp_path) == {("0000", "3"): "van", ("0000", "4"): "sedan"}
    (tmp_path / "meta.json").write_text("{")
    with pytest.raises(DataError, match=r"meta\.json"):
        load_families(tmp_path)
