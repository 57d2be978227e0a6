"""``pcc``: the offline command-line tool.

Each sub-command lives in its own module exposing ``add_arguments(parser)`` and
``run(args) -> int``. The table below is the registry: adding a command is one line.
Modules are imported only when their command is parsed or run, so ``pcc --help`` stays
fast and works without torch, open3d or ROS being importable.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import importlib
import importlib.util
import logging
import os
import sys
import traceback
from pathlib import Path

from pcc_ros import __version__
from pcc_ros.cli.text import plain_text
from pcc_ros.errors import PccError

# name -> (module, one-line help). Keep sorted by workflow order.
COMMANDS: dict[str, tuple[str, str]] = {
    "synth": ("pcc_ros.cli.synth", "generate a SynthCars LiDAR dataset (KITTI tracking layout)"),
    "check-data": ("pcc_ros.cli.check_data", "which dataset layout a folder holds and what it lacks"),
    "convert": ("pcc_ros.cli.convert", "convert KITTI / nuScenes / Argoverse 2 / SynthCars to a ROS 2 bag"),
    "info": ("pcc_ros.cli.info", "summarise a ROS 2 bag"),
    "extract": ("pcc_ros.cli.extract", "extract canonical car instances from bags or datasets"),
    "train": ("pcc_ros.cli.train", "train a completion backend self-supervised"),
    "eval": ("pcc_ros.cli.eval", "evaluate completion backends (`pcc eval detections`: the detection filter)"),
    "eval-detections": ("pcc_ros.cli.eval_detections", "detection AP and the filter's operating curve vs baselines"),
    "calibrate-filter": (
        "pcc_ros.cli.calibrate_filter", "fit the detection filter's weights (SynthCars + real frames)",
    ),
    "replay": ("pcc_ros.cli.replay", "run the per-frame pipeline over a bag"),
    "demo": ("pcc_ros.cli.demo", "end-to-end demo on SynthCars and real KITTI frames"),
    "play": ("pcc_ros.nodes.play", "publish a bag onto the ROS 2 graph with its recorded timing (rclpy)"),
    "echo": ("pcc_ros.nodes.echo", "print the messages of a ROS 2 topic (rclpy)"),
    "bench": ("pcc_ros.cli.bench", "run a benchmark and print a table"),
}


def available_commands() -> dict[str, tuple[str, str]]:
    """Commands whose module exists in this installation (features land one by one)."""
    found = {}
    for name, (module, text) in COMMANDS.items():
        try:
            if importlib.util.find_spec(module) is not None:
                found[name] = (module, text)
        except ModuleNotFoundError:  # a parent package that has not landed
            continue
    return found


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The ``pcc`` parser. ``only``: just that command's sub-parser (what :func:`main` builds when a
    command is named), so running ``pcc train`` imports the training modules and not every other
    command's dependencies (bag I/O's rosbags / mcap, a machine without them trains all the same)."""
    parser = argparse.ArgumentParser(
        prog="pcc",
        description="pcc_ros offline tools: datasets, bags, training, evaluation, benchmarks.",
        epilog="`pcc COMMAND --help` lists a command's options; `pcc eval detections` is `pcc eval-detections`. "
        "Errors are one line (ERROR pcc: <file>: <what> — <what to do>); --debug adds the traceback. "
        "The ROS 2 nodes: completion_node / detection_filter_node --help. Docs: README.md and docs/.",
    )
    parser.add_argument("--version", action="version", version=f"pcc_ros {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    parser.add_argument("--debug", action="store_true", help="on an error, also print the Python traceback")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module_name, text) in available_commands().items():
        if only is not None and name != only:
            continue
        module = importlib.import_module(module_name)
        summary = (module.__doc__ or text).strip().splitlines()[0]
        command = sub.add_parser(name, help=text, description=plain_text(summary))
        module.add_arguments(command)
        command.set_defaults(_module=module)
    return parser


#: Two-word commands: ``pcc eval detections ...`` runs ``pcc eval-detections ...``.
NESTED = {("eval", "detections"): "eval-detections"}


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if tuple(argv[:2]) in NESTED:
        argv = [NESTED[tuple(argv[:2])], *argv[2:]]
    named = next((a for a in argv if not a.startswith("-")), None)  # the command, when one is given
    parser = build_parser(only=named if named in COMMANDS else None)
    args, extra = parser.parse_known_args(argv)
    if extra:  # only commands that forward options to a sub-tool accept unknown ones
        if not hasattr(args, "passthrough"):
            parser.error(f"unrecognized arguments: {' '.join(extra)}")
        args.passthrough = extra + args.passthrough
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO)
    for handler in logging.getLogger().handlers:  # basicConfig's (tqdm's redirect copies the formatter)
        if handler.formatter is None or type(handler.formatter) is logging.Formatter:
            handler.setFormatter(NodeNameFormatter())
    if args.command is None:
        parser.print_help()
        return 2
    try:
        with _log_above_progress_bars():
            return int(args._module.run(args) or 0)
    except KeyboardInterrupt:
        _report("interrupted — no partial output was left behind; re-run the command (pcc extract resumes "
                "where it stopped, pcc train with --resume)")
        return 130
    except BrokenPipeError:  # `pcc info BAG | head`: the reader left; not an error worth a message
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    except Exception as exc:  # the command boundary: a named error, never a traceback
        if args.debug:
            traceback.print_exc()
        _report(describe_error(exc))
        return 1


class NodeNameFormatter(logging.Formatter):
    """``LEVEL name: message``, the name being the node's (``pcc_node``, set while a node core
    works: :func:`pcc_ros.runtime.node.working_for`) for a line a node's pipeline logged."""

    def __init__(self) -> None:
        super().__init__("%(levelname)s %(name)s: %(message)s")

    def formatMessage(self, record: logging.LogRecord) -> str:
        node = getattr(record, "pcc_node", None)
        if node is None:
            return super().formatMessage(record)
        shown = copy.copy(record)  # other handlers see the record as logged
        shown.name = node
        return super().formatMessage(shown)


def _log_above_progress_bars():
    """Log lines printed while a progress bar runs go above it (tqdm's redirect), not glued to the
    bar's line (``replay:  0%| | 0/9 [00:00<?, ?msg/s]WARNING pcc_ros...``). Only where the log goes
    to the console (not under a test's log capture)."""
    console = any(isinstance(h, logging.StreamHandler) and getattr(h, "stream", None) in (sys.stdout, sys.stderr)
                  for h in logging.getLogger().handlers)
    if not console:
        return contextlib.nullcontext()
    from tqdm.contrib.logging import logging_redirect_tqdm

    return logging_redirect_tqdm()


def describe_error(exc: BaseException) -> str:
    """One line for any exception: ``<file>[:line|@offset]: <what> — <what to do>``."""
    if isinstance(exc, PccError):
        return str(exc)
    if isinstance(exc, OSError) and exc.filename is not None:
        path = Path(exc.filename)
        if path.is_symlink() and not path.exists():  # "File exists" from mkdir on a dangling link
            return f"{exc.filename}: a broken symbolic link (to {os.readlink(path)}) — remove it or choose another path"
        return f"{exc.filename}: {exc.strerror or exc} — check the path, its permissions and the free disk space"
    if isinstance(exc, MemoryError):
        return "out of memory — process less at once (fewer frames, smaller --batch-size) or free memory"
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
    return (
        f"internal error {type(exc).__name__}{': ' + text if text else ''} — "
        "this is a bug in pcc_ros; re-run with --debug for the traceback and report it"
    )


def _report(text: str) -> None:
    """``ERROR pcc: <text>`` on stderr, through logging when it is set up."""
    logging.getLogger("pcc").error("%s", text)


if __name__ == "__main__":
    sys.exit(main())
