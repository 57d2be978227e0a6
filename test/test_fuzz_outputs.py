"""Fuzz corpus, outputs: atomic files, interrupted / failed extraction, re-runs with --force."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
from fuzz_support import car_points, small_frames

from pcc_ros import files
from pcc_ros.data.instances import ExtractConfig, InstanceCache, extract_instances
from pcc_ros.errors import DataError


def test_atomic_write_keeps_the_old_file_on_any_failure(tmp_path):
    target = tmp_path / "out.json"
    files.write_json(target, {"v": 1})
    for error in (ValueError, KeyboardInterrupt):
        with pytest.raises(error):
            with files.atomic_write(target, "w") as stream:
                stream.write('{"v": 2, "partial": ')
                raise error
        assert json.loads(target.read_text()) == {"v": 1}
        assert [p.name for p in tmp_path.iterdir()] == ["out.json"]  # no temporary left
    files.save_npy(tmp_path / "a.npy", np.arange(3))  # exact name, no ".npy.npy"
    files.save_npz(tmp_path / "b.npz", x=np.ones(2))
    assert np.load(tmp_path / "a.npy").tolist() == [0, 1, 2]
    assert np.load(tmp_path / "b.npz")["x"].tolist() == [1.0, 1.0]


def test_write_json_turns_nonfinite_floats_into_null_and_leaves_strings(tmp_path):
    """NaN / inf become ``null`` by value (numpy scalars and arrays too), never by a text replace
    that would rewrite a string saying "NaN" or "Infinity"."""
    target = tmp_path / "out.json"
    payload = {
        "label": "NaN means undefined; Infinity too", "NaN": 1.5, "ap": float("nan"),
        "f32": np.float32("nan"), "curve": np.array([0.5, np.inf, -np.inf]), "pair": (np.int64(2), float("-inf")),
        "nested": [{"x": np.nan, "ok": np.float64(0.25), "flag": np.bool_(True)}],
    }
    files.write_json(target, payload, indent=1, nonfinite_null=True)
    assert json.loads(target.read_text()) == {
        "label": "NaN means undefined; Infinity too", "NaN": 1.5, "ap": None, "f32": None,
        "curve": [0.5, None, None], "pair": [2, None], "nested": [{"x": None, "ok": 0.25, "flag": True}],
    }
    with pytest.raises(ValueError):  # without the option, NaN may still be refused as before
        files.write_json(target, {"ap": float("nan")}, allow_nan=False)
    assert json.loads(target.read_text())["ap"] is None  # and the old file stays


def test_stale_temporaries_of_dead_processes_are_removed(tmp_path):
    dead = tmp_path / ".x.json.tmp999999999"  # no such pid
    alive = tmp_path / f".y.json.tmp{os.getppid()}"
    dead.write_text("partial")
    alive.write_text("being written")
    assert files.remove_stale_temporaries(tmp_path) == 1
    assert not dead.exists() and alive.exists()


@pytest.fixture
def synth_root(tmp_path):
    """A SynthCars-like root (meta.json + the car's shape) so extraction copies eval shapes."""
    root = tmp_path / "synth"
    (root / "shapes" / "0000").mkdir(parents=True)
    (root / "meta.json").write_text(json.dumps({"seed": 0, "splits": {"train": [], "test": ["0000"]}}))
    np.save(root / "shapes" / "0000" / "7.npy", (car_points(np.random.default_rng(1)) / 4.2).astype(np.float32))
    return root


def _interrupted(frames, at):
    for k, frame in enumerate(frames):
        if k == at:
            raise KeyboardInterrupt
        yield frame


def test_interrupt_before_any_progress_leaves_nothing_and_reruns(synth_root, tmp_path):
    frames = small_frames(4)
    cfg = ExtractConfig(ground_margin=0.0)
    out = tmp_path / "cache"
    with pytest.raises(KeyboardInterrupt):  # eval shapes were copied for frame 0, no shard yet
        extract_instances(_interrupted(frames, 1), out, cfg, synthcars=synth_root, progress=False)
    assert not out.exists()
    out.mkdir()  # a directory the user made: kept, but recognisably a cache to resume
    with pytest.raises(KeyboardInterrupt):
        extract_instances(_interrupted(frames, 1), out, cfg, synthcars=synth_root, progress=False)
    assert (out / "index.json").exists() and (out / "eval_shapes").exists()
    cache = extract_instances(frames, out, cfg, synthcars=synth_root, progress=False)
    assert len(cache) == 4


@pytest.mark.parametrize("force", [False, True])
def test_leftover_eval_shapes_without_index_are_rebuilt(synth_root, tmp_path, force):
    """What an interrupted run of an older version left: eval_shapes/ and no index.json."""
    out = tmp_path / "cache"
    (out / "eval_shapes" / "0000").mkdir(parents=True)
    np.save(out / "eval_shapes" / "0000" / "7.npy", np.zeros((3, 3), np.float32))
    (out / ".index.json.tmp999999999").write_text("{")
    cache = extract_instances(small_frames(2), out, ExtractConfig(ground_margin=0.0), synthcars=synth_root,
                              force=force, progress=False)
    assert len(cache) == 2
    assert np.load(out / "eval_shapes" / "0000" / "7.npy").shape != (3, 3)  # re-copied, not the stale one
    assert not list(out.glob(".*tmp*"))


def test_foreign_directory_is_still_refused(tmp_path):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("keep me")
    with pytest.raises(DataError, match="not an instance cache"):
        extract_instances(small_frames(1), out, ExtractConfig(), force=True, progress=False)
    assert (out / "notes.txt").read_text() == "keep me"


def test_failed_extraction_leaves_no_cache(tmp_path):
    def broken():
        yield from small_frames(1)
        raise DataError("scan 000001.bin: truncated")

    with pytest.raises(DataError, match="truncated"):
        extract_instances(broken(), tmp_path / "cache", ExtractConfig(ground_margin=0.0), progress=False)
    assert not (tmp_path / "cache").exists()
    with pytest.raises(DataError, match=r"index\.json"):
        InstanceCache.load(tmp_path / "cache")


# ----------------------------------------------------------------------------- the CLI boundary


@pytest.mark.parametrize("error, expected", [
    (RuntimeError("boom"), "internal error RuntimeError: boom — this is a bug in pcc_ros; re-run with --debug"),
    (FileNotFoundError(2, "No such file or directory", "/x/y.bin"), "/x/y.bin: No such file or directory"),
    (DataError("a.txt:3: bad", hint="fix it"), "a.txt:3: bad — fix it"),
])
def test_every_exception_is_one_named_line_and_debug_shows_the_traceback(monkeypatch, caplog, capsys, error, expected):
    from conftest import run_cli

    import pcc_ros.cli.info as info

    def fail(args):
        raise error

    monkeypatch.setattr(info, "run", fail)
    rc, text = run_cli(["info", "whatever"], caplog)
    assert rc == 1 and f"ERROR pcc: {expected}" in text
    assert "Traceback" not in capsys.readouterr().err
    rc, text = run_cli(["--debug", "info", "whatever"], caplog)
    assert rc == 1 and "Traceback" in capsys.readouterr().err


def test_ctrl_c_is_reported_with_status_130(monkeypatch, caplog):
    from conftest import run_cli

    import pcc_ros.cli.info as info

    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(info, "run", interrupted)
    rc, text = run_cli(["info", "whatever"], caplog)
    assert rc == 130 and "ERROR pcc: interrupted" in text
