"""Render the figure tables of the README and docs from committed result files.

A figure is a block of markdown between two marker comments::

    <!-- figure: bench-crop -->
    | boxes | ... |            <- written by this script, never by hand
    Source: docs/results/bench-crop.json (command, commit, date, machine load)
    <!-- /figure -->

Its content comes from one JSON result file, ``docs/results/<source>.json`` (the output of
``pcc bench NAME --json`` or ``pcc eval ... --json``, stored with :func:`store`, which adds the
command, the commit and the date), turned into markdown by the figure's renderer in
:data:`FIGURES` (``scripts/figure_tables/``, one module per family of results).
``test/test_figures.py`` runs :func:`check`: a table that differs from its JSON, a marker with
no renderer, an unclosed block, a result file without its provenance or that no figure renders,
and a table of measured values typed outside a block without saying it is a dated record fail
the test.

Usage (from the repository root)::

    python scripts/render_figures.py                # rewrite every figure block from its JSON
    python scripts/render_figures.py --check        # list the blocks that differ; exit 1 if any
    python scripts/render_figures.py store bench-crop RESULT.json --command "pcc bench crop --repeat 30"
    python scripts/render_figures.py store-bench    # every benchmarks/results/NAME.json as bench-NAME
    python scripts/render_figures.py rerun 'filter-*'  # rerun the recorded commands, store, render
    make figures                                    # make bench, store-bench, render

Adding a figure: run the command with ``--json``, ``store`` the file under a new name, write a
renderer (a function of the JSON returning the table's lines) into :data:`FIGURES`, put the
two markers where the table goes, and run the script.
"""

from __future__ import annotations

import argparse
import fnmatch
import json
import os
import re
import shlex
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from figure_tables import FIGURES  # the renderers, beside this script

ROOT = Path(__file__).resolve().parents[1]
RESULTS = Path("docs/results")
#: Other processes' CPU use (cores) above which a run is said not to be idle (benchmarks' own rule).
IDLE_CORES = 0.1
BEGIN = re.compile(r"^<!-- figure: ([a-z0-9-]+) -->$")
END = "<!-- /figure -->"
#: A table cell that is a measured value: a decimal number, maybe bold, maybe with a unit.
MEASURED = re.compile(r"^\**[-+]?\d+\.\d+\**( ?(ms|s|m|%|MB|x))?\**$")
#: How a typed table of measured values says it is a dated record (in the lines just before it).
RECORD = re.compile(r"dated record", re.IGNORECASE)


def provenance(data: dict[str, Any], source: str) -> str:
    """The line under a figure for each of its sources: which file, command, commit and date, and how
    busy the machine was."""
    p = data["provenance"]
    line = f"Source: `{RESULTS / source}.json` (`{p['command']}`, commit {p['commit']}, {p['date']} UTC"
    machine = p.get("machine") or {}
    cores, others = machine.get("cpu_count"), machine.get("other_processes_cores")
    if others is not None:
        state = "idle" if others <= IDLE_CORES else "not idle, absolute times inflated"
        line += f"; other processes used {others:.2f}{'' if cores is None else f' of {cores}'} cores: {state}"
    return line + ")."


#: The benchmarks ``store-bench`` keeps (as ``bench-NAME``): the README table's and those with a figure of their own.
STORED_BENCHMARKS = {source.removeprefix("bench-") for figure in FIGURES.values() for source in figure.sources
                     if source.startswith("bench-")}


# --------------------------------------------------------------------------- the engine


def documents(root: Path) -> list[Path]:
    """The markdown files that may hold figures: the README and docs/."""
    return [root / "README.md", *sorted((root / "docs").rglob("*.md"))]


def load_result(root: Path, source: str) -> dict[str, Any]:
    path = root / RESULTS / f"{source}.json"
    data = json.loads(path.read_text(encoding="utf-8"))
    missing = [k for k in ("command", "commit", "date") if not (data.get("provenance") or {}).get(k)]
    if missing:
        raise ValueError(f"{path}: provenance lacks {missing} (store results with `render_figures.py store`)")
    return data


def rendered(root: Path, figure_id: str) -> list[str]:
    """The lines of a figure block, from its JSON."""
    figure = FIGURES[figure_id]
    results = {source: load_result(root, source) for source in figure.sources}
    lines = [*figure.render(results), ""]
    if len(figure.sources) == 1:
        return [*lines, provenance(results[figure.sources[0]], figure.sources[0])]
    return [*lines, *(f"- {provenance(results[source], source)}" for source in figure.sources)]


def blocks(text: str, where: str) -> list[tuple[str, int, int]]:
    """``(figure id, first content line, end marker line)`` of every block; ValueError naming
    ``where`` and the line for an unclosed block or an unknown id."""
    lines = text.split("\n")
    out, open_at = [], None
    for number, line in enumerate(lines):
        match = BEGIN.match(line.strip())
        if match:
            if open_at is not None:
                raise ValueError(f"{where}:{number + 1}: figure block opened inside another")
            if match.group(1) not in FIGURES:
                raise ValueError(f"{where}:{number + 1}: unknown figure {match.group(1)!r} "
                                 f"(known: {', '.join(sorted(FIGURES))})")
            open_at = (match.group(1), number)
        elif line.strip() == END:
            if open_at is None:
                raise ValueError(f"{where}:{number + 1}: {END} without an opening marker")
            out.append((open_at[0], open_at[1] + 1, number))
            open_at = None
    if open_at is not None:
        raise ValueError(f"{where}:{open_at[1] + 1}: figure {open_at[0]!r} is never closed ({END})")
    return out


def typed_tables(text: str, where: str) -> list[str]:
    """Markdown tables outside figure blocks that hold two or more measured values without saying, in
    the eight lines before them, that they are a dated record: figures typed by hand."""
    lines, problems, inside, i = text.split("\n"), [], False, 0
    while i < len(lines):
        line = lines[i].strip()
        inside = bool(BEGIN.match(line)) or (inside and line != END)
        if not lines[i].startswith("|"):
            i += 1
            continue
        end = i
        while end < len(lines) and lines[end].startswith("|"):
            end += 1
        cells = [c.strip() for row in lines[i + 2:end] for c in row.strip().strip("|").split("|")]
        if not inside and sum(bool(MEASURED.match(c)) for c in cells) >= 2 \
                and not RECORD.search("\n".join(lines[max(0, i - 8):i])):
            problems.append(f"{where}:{i + 1}: a table of measured values typed by hand (render it from its "
                            "JSON as a figure, or label it a dated record with its commit)")
        i = end
    return problems


def render_text(root: Path, text: str, where: str) -> tuple[str, list[str]]:
    """``text`` with every figure block rendered afresh, and the ids of the blocks that changed."""
    lines = text.split("\n")
    changed = []
    for figure_id, start, end in reversed(blocks(text, where)):
        new = rendered(root, figure_id)
        if lines[start:end] != new:
            changed.append(figure_id)
            lines[start:end] = new
    return "\n".join(lines), changed[::-1]


def check(root: Path = ROOT) -> list[str]:
    """Every problem with the figures of ``root``'s README and docs (empty: all match their JSON)."""
    problems, used = [], set()
    for path in documents(root):
        where = str(path.relative_to(root))
        try:
            text = path.read_text(encoding="utf-8")
            used.update(figure_id for figure_id, _, _ in blocks(text, where))
            problems += typed_tables(text, where)
            _, changed = render_text(root, text, where)
        except (OSError, ValueError, KeyError) as exc:
            problems.append(f"{where}: {exc}")
            continue
        problems += [f"{where}: figure {figure_id!r} differs from its JSON" for figure_id in changed]
    problems += [f"figure {figure_id!r} appears in no document" for figure_id in sorted(set(FIGURES) - used)]
    sources = {source for figure in FIGURES.values() for source in figure.sources}
    problems += [f"{RESULTS / path.name} is rendered by no figure" for path in sorted((root / RESULTS).glob("*.json"))
                 if path.stem not in sources]
    return problems


def render_all(root: Path = ROOT) -> list[str]:
    """Rewrite every figure block; ``where: id`` of each block that changed."""
    out = []
    for path in documents(root):
        where = str(path.relative_to(root))
        text = path.read_text(encoding="utf-8")
        new, changed = render_text(root, text, where)
        if changed:
            path.write_text(new, encoding="utf-8")
            out += [f"{where}: {figure_id}" for figure_id in changed]
    return out


def git_commit(root: Path) -> str:
    """The checkout's short commit, ``-dirty`` when the package or benchmarks have uncommitted changes."""
    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=root, capture_output=True, text=True, check=True).stdout.strip()

    commit = git("rev-parse", "--short", "HEAD")
    return commit + ("-dirty" if git("status", "--porcelain", "--", "pcc_ros", "benchmarks") else "")


def store(root: Path, name: str, result: Path, command: str | None = None) -> Path:
    """Copy a result JSON to ``docs/results/NAME.json`` with its provenance: the command (``command``,
    else the one a benchmark recorded), and the commit and date the benchmark recorded (``run``), else
    the checkout's commit and now."""
    data = json.loads(result.read_text(encoding="utf-8"))
    if "skipped" in data:  # e.g. `pcc bench gpu` where there is no CUDA: the stored measurement stands
        raise SystemExit(f"{result}: the run measured nothing ({data['skipped']}); {name} is not replaced")
    run = data.get("run") or {}
    command = command or run.get("command")
    if not command:
        raise SystemExit(f"{result}: no command recorded; pass --command as a reader would rerun it")
    data["provenance"] = {
        "command": command,
        "commit": run.get("commit") or git_commit(root),
        "date": (run.get("utc") or time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime()))[:16],
        "machine": {"cpu_count": data.get("cpu_count"), "other_processes_cores": run.get("other_processes_cores")},
    }
    out = root / RESULTS / f"{name}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(data, indent=1, sort_keys=True) + "\n", encoding="utf-8")
    return out


def json_output(command: str) -> Path | None:
    """The file the last ``--json FILE`` of a recorded command writes (None: the command names none, as a
    benchmark's recorded command does)."""
    words = shlex.split(command.replace("&&", " && "))
    outs = [words[i + 1] for i, word in enumerate(words[:-1]) if word == "--json"]
    return Path(outs[-1]) if outs else None


def rerun(root: Path, patterns: list[str]) -> list[Path]:
    """Run again the recorded command of every stored result whose name matches one of ``patterns``
    (fnmatch; none: every result that is not a benchmark's, which ``make figures`` refreshes) and store
    what it writes under the same name, with a fresh provenance. The commands run in ``root`` with
    this interpreter's ``pcc`` first on the PATH and ``root`` first on the PYTHONPATH."""
    names = sorted(p.stem for p in (root / RESULTS).glob("*.json"))
    chosen = [n for n in names if any(fnmatch.fnmatch(n, pat) for pat in patterns)] if patterns else [
        n for n in names if not n.startswith("bench-") and n != "demo"]
    if not chosen:
        raise SystemExit(f"no stored result matches {patterns} (stored: {', '.join(names)})")
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}",
           "PYTHONPATH": os.pathsep.join(filter(None, [str(root), os.environ.get("PYTHONPATH")]))}
    stored = []
    for name in tqdm(chosen, desc="rerun", unit="result"):
        command = load_result(root, name)["provenance"]["command"]
        out = json_output(command)
        run = command
        if out is None:  # a benchmark: its recorded command leaves the output out
            out = Path("out/figures") / f"{name}.json"
            run = f"{command} --json {shlex.quote(str(out))}"
        print(f"{name}: {run}", flush=True)
        subprocess.run(["bash", "-c", f"set -e; {run}"], cwd=root, env=env, check=True)
        stored.append(store(root, name, root / out, command))
    return stored


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true", help="list the blocks that differ from their JSON; exit 1")
    sub = parser.add_subparsers(dest="action")
    keep = sub.add_parser("store", help="store a result JSON under docs/results/ with its provenance")
    keep.add_argument("name", help="the result's name (docs/results/NAME.json)")
    keep.add_argument("result", type=Path, help="the JSON a `pcc bench NAME --json` or `pcc eval --json` wrote")
    keep.add_argument("--command", help="the command that produced it, as a reader would rerun it "
                      "(default: the one a benchmark's JSON records)")
    benches = sub.add_parser("store-bench", help="store every benchmark result of a folder as bench-NAME")
    benches.add_argument("folder", type=Path, nargs="?", default=Path("benchmarks/results"),
                         help="where `make bench` wrote them (default benchmarks/results)")
    again = sub.add_parser("rerun", help="run stored results' recorded commands again and store their output")
    again.add_argument("patterns", nargs="*", help="result names or fnmatch patterns (default: every result that "
                       "is not a benchmark's; `make figures` refreshes those)")
    args = parser.parse_args(argv)
    if args.action == "rerun":
        rerun(ROOT, args.patterns)
        print("\n".join(render_all(ROOT)) or "every figure was already up to date")
        return 0
    if args.action == "store":
        print(store(ROOT, args.name, args.result, args.command))
        return 0
    if args.action == "store-bench":
        for result in sorted(args.folder.glob("*.json")):
            if result.stem in STORED_BENCHMARKS:
                skipped = json.loads(result.read_text(encoding="utf-8")).get("skipped")
                print(f"{result}: measured nothing here ({skipped}); the stored bench-{result.stem} stays"
                      if skipped else store(ROOT, f"bench-{result.stem}", result))
        return 0
    if args.check:
        problems = check(ROOT)
        print("\n".join(problems) or "every figure matches its JSON")
        return 1 if problems else 0
    print("\n".join(render_all(ROOT)) or "every figure was already up to date")
    return 0


if __name__ == "__main__":
    sys.exit(main())
