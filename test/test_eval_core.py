"""`pcc eval` scoring core on hand-made instances (no cache needed)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from shapes import car_with_cabin

from pcc_ros.errors import ConfigError
from pcc_ros.workflows.evaluate import (
    EvalInstance,
    evaluate,
    example_indices,
    parse_checkpoints,
    plot_examples,
    print_tables,
    select_indices,
    summarise,
)


def symmetric_car(rng, n=4000):
    """Surface samples of a box body + cabin, symmetric about y = 0 (canonical units)."""
    car = car_with_cabin(rng, n)
    return np.concatenate([car, car * np.float32([1, -1, 1])])


def make_instances(count=6, seed=0):
    rng = np.random.default_rng(seed)
    out = []
    for i in range(count):
        gt = symmetric_car(rng)
        visible = gt[gt[:, 1] > 0.05]  # only the left side was seen
        partial = visible[rng.choice(len(visible), 40 + 150 * i, replace=False)]
        out.append(EvalInstance(f"0000/{i}", partial, gt, 4.0 + 0.2 * i, 8.0 * i + 1, True))
    return out


def test_evaluate_ranks_baselines_and_converts_units(tmp_path, capsys):
    instances = make_instances()
    results, completions = evaluate(
        instances, "ground_truth", ["input", "densify", "mirror"], device="cpu", emd_points=128, progress=False,
        keep=range(len(instances)),
    )
    b = results["backends"]
    assert set(b) == {"input", "densify", "mirror"}
    # Only one side seen: the symmetry prior must recover coverage; input is exact on precision.
    assert b["mirror"]["overall"]["coverage"] < 0.5 * b["input"]["overall"]["coverage"]
    assert b["mirror"]["overall"]["cd_l1"] < b["input"]["overall"]["cd_l1"]
    assert b["input"]["overall"]["precision"] < 1e-6
    assert b["input"]["overall"]["fidelity"] == 0.0
    assert b["densify"]["overall"]["fidelity"] > 0.0
    # metres = canonical x box length (x length^2 for squared metrics), instance by instance
    lengths = np.array([inst.length for inst in instances])
    from pcc_ros.metrics import chamfer

    per = [chamfer(completions["mirror"][i], inst.reference) for i, inst in enumerate(instances)]
    assert b["mirror"]["overall"]["cd_l1"] == pytest.approx(np.mean([r["cd_l1"] for r in per] * lengths))
    assert b["mirror"]["overall"]["cd_l2"] == pytest.approx(np.mean([r["cd_l2"] for r in per] * lengths**2))
    assert b["mirror"]["overall_canonical"]["cd_l1"] == pytest.approx(np.mean([r["cd_l1"] for r in per]))
    # breakdowns: distances 1, 9, 17 | 25, 33 | 41 -> 3 / 2 / 1
    assert [b["input"]["by_distance"][k]["count"] for k in ("0-20m", "20-40m", "40m+")] == [3, 2, 1]
    assert sum(v["count"] for v in b["input"]["by_points"].values()) == 6
    assert b["input"]["by_points"]["<50pts"]["count"] == 1
    assert results["units"]["overall"]["cd_l2"] == "m^2"
    json.dumps(results, allow_nan=False)  # strict JSON (empty bands are null, not NaN)

    print_tables(results, "ground_truth")
    text = capsys.readouterr().out
    assert "cd_l1 [m, sensor frame; lower is better; reference: ground_truth]" in text
    assert "overall in canonical units" in text

    picks = example_indices(instances, 3)
    assert picks == [0, 2, 5]  # spread over the distance range
    plot_examples(tmp_path / "grid.png", instances, completions, "ground_truth", picks)
    assert (tmp_path / "grid.png").stat().st_size > 10_000


def test_resume_reuses_finished_backends():
    instances = make_instances(2)
    calls = []
    first, _ = evaluate(instances, "ground_truth", ["input", "densify"], emd_points=64, progress=False,
                        on_backend_done=lambda r: calls.append(list(r["backends"])))
    assert calls == [["input"], ["input", "densify"]]
    # Tamper with a stored figure: a resumed run must reuse it, not recompute it.
    first["backends"]["densify"]["overall"]["cd_l1"] = 123.0
    again, kept = evaluate(instances, "ground_truth", ["input", "densify", "mirror"], emd_points=64,
                           progress=False, previous=first, keep=[1])
    assert again["backends"]["densify"]["overall"]["cd_l1"] == 123.0
    assert set(kept["densify"]) == {1} and len(kept["mirror"][1]) == 2 * instances[1].num_points
    # Different settings -> different fingerprint -> recomputed.
    other, _ = evaluate(instances, "ground_truth", ["densify"], emd_points=32, progress=False, previous=first)
    assert other["backends"]["densify"]["overall"]["cd_l1"] != 123.0
    # The same instances now carrying their SynthCars families (a run that could not read them
    # wrote no per-family tables): recomputed, with the family table.
    for inst in instances:
        inst.meta["family"] = "van"
    with_families, _ = evaluate(instances, "ground_truth", ["input", "densify"], emd_points=64, progress=False,
                                previous=first)
    assert with_families["backends"]["densify"]["overall"]["cd_l1"] != 123.0
    assert "van" in with_families["backends"]["densify"]["by_family"]


def test_evaluate_is_reproducible():
    instances = make_instances(3)
    r1, _ = evaluate(instances, "ground_truth", ["densify"], emd_points=64, seed=3, progress=False)
    r2, _ = evaluate(instances, "ground_truth", ["densify"], emd_points=64, seed=3, progress=False)
    r1["backends"]["densify"].pop("completion_ms_per_instance")
    r2["backends"]["densify"].pop("completion_ms_per_instance")
    assert r1 == r2


def test_summarise_empty_band_is_null():
    inst = make_instances(1)
    rows = [{"cd_l1": 0.1, "cd_l2": 0.01}]
    s = summarise(inst, rows)
    assert s["by_distance"]["40m+"] == {"count": 0, "cd_l1": None, "cd_l2": None}
    assert s["overall"]["cd_l1"] == pytest.approx(0.1 * inst[0].length)


def test_cli_helpers():
    assert parse_checkpoints(["pointpncnet=a/b.safetensors"]) == {"pointpncnet": Path("a/b.safetensors")}
    with pytest.raises(ConfigError):
        parse_checkpoints(["oops"])
    np.testing.assert_array_equal(select_indices(5, None, 0), np.arange(5))
    sub = select_indices(100, 10, 1)
    assert len(sub) == 10 and np.all(np.diff(sub) > 0)
    np.testing.assert_array_equal(sub, select_indices(100, 10, 1))
    with pytest.raises(ConfigError, match="not evaluated"):
        evaluate(make_instances(1), "ground_truth", ["input"], {"pointpncnet": "x"}, progress=False)


def test_checkpoint_stamp_is_the_loaded_checkpoint_s_weights_and_aspect():
    """The stamp a resumed pcc eval compares: what the completer was loaded from, not a second read."""
    from pcc_ros.models.registry import default_checkpoint, load_completer
    from pcc_ros.workflows.evaluate import checkpoint_stamp

    config = json.loads(default_checkpoint("pointpncnet").with_suffix(".json").read_text())
    stamp = checkpoint_stamp(load_completer("pointpncnet", device="cpu"))
    assert stamp == f"{config['sha256']}:{json.dumps(config['box_aspect'], sort_keys=True)}"
    assert checkpoint_stamp(load_completer("mirror")) is None
