"""`pcc eval` end to end on the tiny cache of conftest (written with the instance extractor)."""

from __future__ import annotations

import json

import pytest
from conftest import assert_named_failure, run_cli

from pcc_ros.cli.main import main


@pytest.mark.slow
def test_pcc_eval_end_to_end_ground_truth(tiny_cache, tmp_path, capsys):
    out_json, out_png = tmp_path / "eval.json", tmp_path / "eval.png"
    argv = ["eval", "--data", str(tiny_cache), "--split", "test", "--backends", "input,densify,mirror",
            "--json", str(out_json), "--plot", str(out_png), "--emd-points", "128", "--seed", "1"]
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "reference: ground_truth" in text and "cd_l1 [m, sensor frame" in text
    results = json.loads(out_json.read_text())
    assert results["reference"] == "ground_truth" and results["instances"] == 9 and results["split"] == "test"
    b = results["backends"]
    for name in ("input", "densify", "mirror"):
        overall = b[name]["overall"]
        assert set(overall) >= {"cd_l1", "cd_l2", "precision", "coverage", "fscore", "emd", "fidelity", "side_cd"}
        assert overall["count"] == 9
        assert [b[name]["by_distance"][k]["count"] for k in ("0-20m", "20-40m", "40m+")] == [3, 3, 3]
    # Half of each car seen: the mirror covers the other half.
    assert b["mirror"]["overall"]["coverage"] < 0.7 * b["input"]["overall"]["coverage"]
    assert b["input"]["overall"]["precision"] < b["densify"]["overall"]["precision"]
    assert out_png.stat().st_size > 10_000 and len(results["plot"]["instances"]) == 4
    # Re-running reuses the finished results and reproduces the file exactly.
    before = out_json.read_text()
    assert main(argv) == 0
    assert out_json.read_text() == before


def test_pcc_eval_aggregated_reference(tiny_cache, tmp_path):
    out_json = tmp_path / "agg.json"
    assert main(["eval", "--data", str(tiny_cache), "--backends", "input,mirror", "--reference", "aggregated",
                 "--no-emd", "--max-instances", "5", "--json", str(out_json)]) == 0
    results = json.loads(out_json.read_text())
    assert results["reference"] == "aggregated" and results["instances"] == 5
    overall = results["backends"]["input"]["overall"]
    # The aggregate contains the observation itself: input is exactly on it.
    assert overall["precision"] == 0.0 and overall["fidelity"] == 0.0 and "emd" not in overall
    # The mirror reflects across the canonical x-z plane (y -> -y): its side view (the x-z
    # projection) is the input's, point for point, so the side-view Chamfer cannot differ.
    side = {name: results["backends"][name]["overall"]["side_cd"] for name in ("input", "mirror")}
    assert side["input"] > 0.0 and side["mirror"] == pytest.approx(side["input"], rel=1e-5), side


@pytest.mark.parametrize(("args", "named"), [
    (["--data", "{tmp}/none", "--backends", "input"], ["{tmp}/none: instance cache not found", "pcc extract"]),
    (["--data", "{cache}", "--backends", "bogus"], ["unknown completion backend 'bogus'", "available: "]),
    (["--data", "{cache}", "--split", "nope", "--backends", "input"],
     ["unknown split 'nope'", "('train', 'val', 'test')"]),
    (["--data", "{cache}", "--backends", "input", "--checkpoint", "input=x"],
     ["backend 'input' has no weights", "do not pass a checkpoint"]),
])
def test_pcc_eval_errors(tiny_cache, tmp_path, caplog, args, named):
    """Each refusal names the input and what is wrong with it, never an internal error."""
    fill = {"tmp": tmp_path, "cache": tiny_cache}
    rc, text = run_cli(["eval", *(a.format(**fill) for a in args)], caplog)
    assert_named_failure(rc, text, *(n.format(**fill) for n in named))


@pytest.mark.parametrize("real", [False, True])
def test_pcc_eval_names_an_unknown_backend_before_reading_any_data(tmp_path, caplog, real):
    """The backends are checked first (as `pcc bench complete` does): a typo is said at once, not after
    the instance cache or the real frames have been read."""
    source = ["--real", "--real-sources", str(tmp_path / "none")] if real else ["--data", str(tmp_path / "none")]
    assert_named_failure(*run_cli(["eval", *source, "--backends", "input,bogus"], caplog),
                         "unknown completion backend 'bogus'; available: ")


def test_pcc_eval_real_refuses_a_plot_column_it_does_not_evaluate(tmp_path, caplog):
    """`--plot-backends mirorr` was left out of the PNG without a word, after the whole evaluation."""
    argv = ["eval", "--real", "--real-sources", str(tmp_path / "none"), "--backends", "input,mirror",
            "--plot", str(tmp_path / "p.png"), "--plot-backends", "mirror,mirorr"]
    assert_named_failure(*run_cli(argv, caplog), "--plot-backends names backend(s) not evaluated: ['mirorr']")


def test_a_dangling_symlink_as_output_is_named_as_one(tmp_path):
    """mkdir on a dangling link fails with "File exists": the message says what the path is."""
    import errno

    from pcc_ros.cli.main import describe_error

    link = tmp_path / "cache"
    link.symlink_to(tmp_path / "gone")
    text = describe_error(FileExistsError(errno.EEXIST, "File exists", str(link)))
    assert text.startswith(f"{link}: a broken symbolic link (to {tmp_path / 'gone'})"), text
    assert "free disk space" in describe_error(FileExistsError(errno.EEXIST, "File exists", str(tmp_path)))


@pytest.mark.parametrize("real", [False, True])
def test_pcc_eval_refuses_to_write_over_a_checkpoints_config(tmp_path, caplog, real):
    """`--json run/trapcc.json` beside `--checkpoint trapcc=run/trapcc.safetensors` replaced the
    checkpoint's config (its weights' hash and training record) without a word."""
    weights = tmp_path / "trapcc.safetensors"
    config = tmp_path / "trapcc.json"
    config.write_text("{}")
    source = ["--real", "--real-sources", str(tmp_path / "none")] if real else ["--data", str(tmp_path / "none")]
    argv = ["eval", *source, "--backends", "trapcc", "--checkpoint", f"trapcc={weights}", "--json", str(config)]
    assert_named_failure(*run_cli(argv, caplog), f"--json {config} is a file of the trapcc checkpoint")
    assert config.read_text() == "{}"
