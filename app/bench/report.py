"""The results of ``fdmo bench``: results.csv (a row per cell), summary.csv and table.md (per sequence, method,
setting and task: the mean and the spread over seeds), ate.png and trajectories.png.

The spread is the sample standard deviation over the seeds whose cell finished (``n - 1`` in the denominator,
as evo's and numpy's ``ddof=1``); with one seed it is left out. A failed cell is counted, never averaged: the
table says how many of each group's cells finished, and lists every failure with its error.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from app.bench.cell import COLUMNS, LABELS, METRICS, OK
from app.experiments.common import figure, markdown_table, write_csv

RESULTS_FILE = "results.csv"
SUMMARY_FILE = "summary.csv"
TABLE_FILE = "table.md"
ATE_PLOT_FILE = "ate.png"
TRAJECTORIES_PLOT_FILE = "trajectories.png"
GROUP = ("task", "setting", "sequence", "method")  # a row of the table: the seeds of one group
DPI = 110


def _fixed(digits: int) -> Callable[[float], str]:
    return lambda value: f"{value:.{digits}f}"


def _percent(value: float) -> str:
    return f"{100 * value:.1f}"


# The table's columns for each task: (metric, header, format of a number).
TABLE_COLUMNS = {
    "run": (("ate_m", "ATE m", _fixed(4)), ("rpe_m", "RPE m", _fixed(4)), ("tracked_fraction", "tracked %", _percent),
            ("initialization_frame", "init frame", _fixed(0)), ("fps", "fps", _fixed(1)),
            ("failures", "failures", _fixed(1)), ("recoveries", "recoveries", _fixed(1)),
            ("reinitializations", "reinit.", _fixed(1))),
    "frame-drop": (("forward_limit_frames", "forward limit (frames)", _fixed(1)),
                   ("backward_limit_frames", "backward limit (frames)", _fixed(1))),
    "two-loop": (("ate_m", "ATE m", _fixed(4)), ("alignment_error_m", "alignment error m", _fixed(4)),
                 ("scale_drift", "scale drift", _fixed(3)), ("rotation_drift_deg", "rotation drift deg", _fixed(2)),
                 ("tracked_fraction", "posed % (loop 2)", _percent), ("failures", "failures", _fixed(1)),
                 ("recoveries", "recoveries", _fixed(1))),
}


def write_report(rows: list[dict[str, Any]], tasks: dict[str, str], out_dir: Path) -> str:
    """Every file of the report; returns table.md's text. ``tasks``: each task name's kind (run, frame-drop, ...)."""
    write_csv(out_dir / RESULTS_FILE, [{column: row.get(column) for column in COLUMNS} for row in rows])
    groups = summarize(rows)
    write_csv(out_dir / SUMMARY_FILE, groups)
    table = markdown_report(groups, rows, tasks)
    (out_dir / TABLE_FILE).write_text(table + "\n")
    runs = [row for row in rows if tasks.get(row["task"]) == "run"]
    if any(row["status"] == OK and row["ate_m"] is not None for row in runs):
        ate_plot(groups, tasks).savefig(out_dir / ATE_PLOT_FILE, dpi=DPI)
        trajectories_plot(runs).savefig(out_dir / TRAJECTORIES_PLOT_FILE, dpi=DPI)
    return table


def summarize(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """A row per group (task, setting, sequence, method) in the order of ``rows``: cells, cells finished, and
    each metric's mean and spread over the finished ones."""
    grouped: dict[tuple, list[dict[str, Any]]] = {}
    for row in rows:
        grouped.setdefault(tuple(row[key] for key in GROUP), []).append(row)
    summary = []
    for key, members in grouped.items():
        finished = [row for row in members if row["status"] == OK]
        entry: dict[str, Any] = {**dict(zip(GROUP, key)), "cells": len(members), "ok": len(finished)}
        for metric in METRICS:
            values = np.array([row[metric] for row in finished if row[metric] is not None], dtype=float)
            entry[f"{metric}_mean"] = float(values.mean()) if len(values) else None
            entry[f"{metric}_std"] = float(values.std(ddof=1)) if len(values) > 1 else None
        summary.append(entry)
    return summary


def markdown_report(groups: list[dict[str, Any]], rows: list[dict[str, Any]], tasks: dict[str, str]) -> str:
    sections = []
    for task, setting in dict.fromkeys((group["task"], group["setting"]) for group in groups):
        columns = TABLE_COLUMNS[tasks[task]]
        lines = [(group["sequence"], group["method"], f"{group['ok']}/{group['cells']}",
                  *(_mean_and_spread(group, metric, number) for metric, _, number in columns))
                 for group in groups if (group["task"], group["setting"]) == (task, setting)]
        header = ("sequence", "method", "cells ok", *(title for _, title, _ in columns))
        sections.append(f"### {task} ({setting})\n\n" + markdown_table(header, lines))
    failed = [row for row in rows if row["status"] != OK]
    if failed:
        sections.append("### cells that did not finish\n\n" + "\n".join(
            f"- {' / '.join(str(row[label]) for label in LABELS)}: {row['status']}: {row['error']}" for row in failed))
    return "\n\n".join(sections)


def _mean_and_spread(group: dict[str, Any], metric: str, number: Callable[[float], str]) -> str:
    mean, spread = group[f"{metric}_mean"], group[f"{metric}_std"]
    if mean is None:
        return "-"
    return number(mean) if spread is None else f"{number(mean)} ± {number(spread)}"


def ate_plot(groups: list[dict[str, Any]], tasks: dict[str, str]):
    """The ATE of each sequence and method (bars: mean over seeds; whiskers: spread), a panel per setting of each
    run task."""
    panels_of = [key for key in dict.fromkeys((g["task"], g["setting"]) for g in groups) if tasks[key[0]] == "run"]
    canvas = figure(max(6.0, 1.6 * len({g["sequence"] for g in groups}) + 3), 3.6 * len(panels_of))
    for panel, (task, setting) in zip(np.atleast_1d(canvas.subplots(len(panels_of), 1)), panels_of):
        members = [g for g in groups if (g["task"], g["setting"]) == (task, setting)]
        sequences = list(dict.fromkeys(g["sequence"] for g in members))
        methods = list(dict.fromkeys(g["method"] for g in members))
        width = 0.8 / len(methods)
        for m, method in enumerate(methods):
            by_sequence = {g["sequence"]: g for g in members if g["method"] == method}
            means = [by_sequence.get(s, {}).get("ate_m_mean") for s in sequences]
            spreads = [by_sequence.get(s, {}).get("ate_m_std") or 0.0 for s in sequences]
            x = np.arange(len(sequences)) + (m - (len(methods) - 1) / 2) * width
            heights = [np.nan if mean is None else mean for mean in means]
            panel.bar(x, heights, width, yerr=spreads, capsize=3, color=f"C{m}", label=method)
        panel.set_xticks(np.arange(len(sequences)), sequences, rotation=15, ha="right", fontsize="small")
        panel.set(ylabel="ATE rmse [m]", yscale="log", title=f"{task} ({setting}): ATE, mean and spread over seeds")
        panel.legend(fontsize="small")
    return canvas


def trajectories_plot(rows: list[dict[str, Any]]):
    """Each sequence's top view: the ground truth and, per method, the first finished seed's trajectory aligned
    to it (Sim(3)), for the first setting and run task."""
    from app.plot import AXES, position_errors, read_run, view_axes

    first = (rows[0]["task"], rows[0]["setting"])
    shown = [row for row in rows if (row["task"], row["setting"]) == first and row["status"] == OK
             and row.get("tracked_fraction")]  # a run that never posed a frame (a static camera) has nothing to draw
    sequences = list(dict.fromkeys(row["sequence"] for row in shown))
    columns = max(1, min(3, len(sequences)))
    rows_of_panels = max(1, -(-len(sequences) // columns))
    canvas = figure(5 * columns, 4.5 * rows_of_panels)
    panels = np.atleast_1d(canvas.subplots(rows_of_panels, columns)).ravel()
    for panel, sequence in zip(panels, sequences):
        drawn = set()
        for row in (row for row in shown if row["sequence"] == sequence):
            run = read_run(Path(row["folder"]))
            if run.ground_truth is None or row["method"] in drawn or len(run.estimate) < 3:
                continue
            aligned = position_errors(run.estimate, run.ground_truth, "sim3").aligned
            u, v = view_axes(run.ground_truth.positions, None)[0]
            if not drawn:
                panel.plot(run.ground_truth.positions[:, u], run.ground_truth.positions[:, v], "k-", lw=1.2,
                           label="ground truth")
                panel.set(xlabel=f"{AXES[u]} [m]", ylabel=f"{AXES[v]} [m]")
            panel.plot(aligned.positions[:, u], aligned.positions[:, v], lw=0.9,
                       label=f"{row['method']} (seed {row['seed']})")
            drawn.add(row["method"])
        panel.set(title=sequence, aspect="equal", adjustable="datalim")
        panel.legend(fontsize="x-small")
    for panel in panels[len(sequences):]:
        panel.set_axis_off()
    return canvas
