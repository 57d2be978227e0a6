"""``pcc calibrate-filter --trees-out FILE``: boosted trees for a kept weight set, and its thresholds.

The command half of :mod:`pcc_ros.workflows.filter_trees`: the weights of ``--weights-from`` (else
the base / shipped YAML) kept; the ``--sensor-thresholds`` layouts' simulated rows (and ``--real``'s
labelled frames) measured; the trees boosted from the weights' logit, written to ``FILE`` with their
provenance; what they add held out; each layout's threshold for weights plus trees; ``--out`` the
node YAML naming the trees (``shipped`` when ``FILE`` is the packaged one).
"""

from __future__ import annotations

import argparse
import logging
from dataclasses import replace
from typing import Any

from pcc_ros.cli.calibrate_sensors import (
    kept_weights,
    labelled_real_rows,
    layout_rows,
    per_sensor_header,
    per_sensor_step,
    threshold_layouts,
    write_kept_weights,
    write_report,
)
from pcc_ros.errors import ConfigError
from pcc_ros.models.checkpoint import git_revision
from pcc_ros.pipeline.trees import SHIPPED, SHIPPED_PATH
from pcc_ros.workflows.filter_sensors import Rows, measuring_pipeline
from pcc_ros.workflows.filter_trees import TREE_TERMS, boost_rows, held_out_by_sequence, held_out_real

log = logging.getLogger(__name__)


def _kinds(fig: dict[str, Any]) -> str:
    return ", ".join(f"{k} AUC {v['auc_vs_true']:.3f}" for k, v in fig["per_kind"].items())


def command_line(args: argparse.Namespace) -> str:
    real = f" --real {args.real} --real-detections {args.real_detections} --score-mapping {args.score_mapping}" \
        if args.real else ""
    return (f"pcc calibrate-filter --trees-out {args.trees_out} --sensor-thresholds {args.sensor_thresholds}"
            f"{' --weights-from ' + str(args.weights_from) if args.weights_from else ''}"
            f" --sim-root {args.sim_root} --sim-seed {args.sim_seed} --sim-sequences {args.sim_sequences}"
            f" --sim-frames {args.sim_frames}{real} --tree-depth {args.tree_depth} --tree-rounds {args.tree_rounds}"
            f" --tree-rate {args.tree_rate:g}{' --tree-monotone' if args.tree_monotone else ''}"
            f" --threshold-folds {args.threshold_folds}"
            f" --target-lost {args.target_lost:g}")


def run_trees(args: argparse.Namespace) -> int:
    """Boost, report held out, set the thresholds on out-of-fold scores, write the trees and ``--out``."""
    if not args.sensor_thresholds:
        raise ConfigError("--trees-out boosts on the simulated layouts of --sensor-thresholds (e.g. all) and sets "
                          "their thresholds for the weights plus the trees: give it")
    if args.real is not None and args.real_layout not in threshold_layouts(args.sensor_thresholds):
        raise ConfigError(f"--real-layout {args.real_layout}: not among --sensor-thresholds {args.sensor_thresholds}")
    source, config = kept_weights(args)
    config = replace(config, trees="")  # boosted from the weighted sum alone
    shape = config.w_mismatch != 0
    pipeline = measuring_pipeline(args.filter_backend, shape=shape)
    rows = layout_rows(args, pipeline, shape)
    every = Rows.concatenate([*rows.values(), *([labelled_real_rows(args, pipeline)] if args.real else [])])
    settings = {"depth": args.tree_depth, "rounds": args.tree_rounds, "rate": args.tree_rate,
                **({"monotone": True} if args.tree_monotone else {})}
    by_seq, p_out = held_out_by_sequence(every, config, **settings)
    report: dict[str, Any] = {"by_sequence": by_seq}
    print(f"held out by sequence ({by_seq['folds']} folds), the weighted sum alone: AUC "
          f"{by_seq['sum_alone']['auc_false_above_true']:.3f}, best removal at <= 2 % lost "
          f"{by_seq['sum_alone']['false_removed_at_0.02_lost_best']:.1%}; {_kinds(by_seq['sum_alone'])}")
    print(f"  with the trees: AUC {by_seq['with_trees']['auc_false_above_true']:.3f}, best removal at <= 2 % lost "
          f"{by_seq['with_trees']['false_removed_at_0.02_lost_best']:.1%}; {_kinds(by_seq['with_trees'])}")
    print("thresholds on the out-of-fold p_false:")
    per_sensor = per_sensor_step(args, rows, {k: p_out[every.sensor == k] for k in rows}, None)
    if args.real:
        real = held_out_real(every, config, per_sensor["layouts"][args.real_layout]["threshold"], **settings)
        report["real_frames"] = {"layout": args.real_layout, **real}
        print(f"held-out real frames (blocks, trees boosted without the block, the {args.real_layout} threshold): "
              f"{real['false_removed']:.1%} of {real['false']} false removed, {real['true_lost']:.1%} of "
              f"{real['true']} true lost")
    trees = boost_rows(every, config, **settings)
    counts = {str(s): {"true": int((~every.false[every.sensor == s]).sum()),
                       "false": int(every.false[every.sensor == s].sum())} for s in sorted(set(every.sensor))}
    trees = replace(trees, provenance={
        "command": command_line(args), "commit": git_revision(), "weights_from": str(source), "terms": list(TREE_TERMS),
        "sim_seed": args.sim_seed,
        **settings, "rows": counts,
        "held_out": {"by_sequence_auc": by_seq["with_trees"]["auc_false_above_true"],
                     "by_sequence_auc_sum_alone": by_seq["sum_alone"]["auc_false_above_true"],
                     **({"real_frames": {k: report["real_frames"][k] for k in ("true_lost", "false_removed")}}
                        if args.real else {})}})
    args.trees_out.parent.mkdir(parents=True, exist_ok=True)
    trees.save(args.trees_out)
    print(f"wrote {args.trees_out}: {len(trees.leaf)} trees of depth {trees.depth} over {', '.join(trees.terms)}")
    if args.out:
        # the packaged file by name, any other by its absolute path (a node's working directory is not ours)
        value = SHIPPED if args.trees_out.resolve() == SHIPPED_PATH else str(args.trees_out.resolve())
        header = f"# calibrated: trees: {command_line(args)}\n" + per_sensor_header(
            args, per_sensor, "the trees command above, on the out-of-fold p_false")
        write_kept_weights(args, source, replace(config, trees=value), per_sensor["fallback"], per_sensor["value"],
                            header, keep_trees=False)
    if args.json:
        write_report(args.json, {"weights_from": str(source), "trees": str(args.trees_out), "settings": settings,
                                  "rows": counts, **report, "sensor_thresholds": per_sensor})
    return 0
