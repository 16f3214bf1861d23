"""A manifest's learning curves (`curves:`): per set, each complete cell's accuracy against the training its
fold runs saw, one line per series of columns (one model at growing budgets), beside the published number.

The x of a cell is the mean over its fold runs of what each logged (`n_*` params), never the manifest's
budget: `samples` = n_train_samples x n_epochs (training samples seen), `distinct` = n_train_distinct (faces
any epoch trained on; runs made before that count existed trained every epoch on their n_train_samples).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from meshseg.report.cells import Cell, Table
from meshseg.report.config import METRIC_TEXT

#: the x axis of each `curves.x`
X_TEXT = {
    "samples": "training samples seen per fold run (samples per epoch × epochs)",
    "distinct": "distinct training faces per fold run",
}


def run_x(counts: dict[str, int], x: str) -> float | None:
    """One fold run's x from its counts (Cell.counts); None when the run did not log them."""
    if x == "distinct":
        n = counts.get("n_train_distinct", counts.get("n_train_samples"))
        return None if n is None else float(n)
    if "n_train_samples" not in counts or "n_epochs" not in counts:
        return None
    return float(counts["n_train_samples"] * counts["n_epochs"])


@dataclass(frozen=True)
class Point:
    column: str  # its column's key
    x: float  # mean over the cell's fold runs
    value: float  # the cell's accuracy (%)
    ci: tuple[float, float]


@dataclass(frozen=True)
class Panel:
    group: str
    set: str  # the row label
    lines: dict[str, list[Point]]  # series name -> the points of its complete cells, in the series' order
    published: dict[str, float | None]  # series name -> the set's published number of the series' first column


def _point(cell: Cell, x: str) -> Point | None:
    if cell.status != "ok" or not cell.counts:
        return None
    xs = [run_x(c, x) for c in cell.counts]
    if None in xs:  # a run without counts cannot be placed
        return None
    return Point(cell.column.key, float(np.mean(xs)), float(cell.value), cell.ci)


def curve_panels(table: Table) -> list[Panel]:
    """What the figure plots: one Panel per set row where some series has a complete cell."""
    curves = table.manifest.curves
    if curves is None:
        return []
    index = {c.key: j for j, c in enumerate(table.columns)}
    sets = {(g.name, s.name): s for g in table.manifest.groups for s in g.sets}
    panels = []
    for row in table.rows:
        if row.kind != "set":
            continue
        lines = {name: [_point(row.cells[index[k]], curves.x) for k in keys] for name, keys in curves.series}
        lines = {name: [p for p in points if p is not None] for name, points in lines.items()}
        if not any(lines.values()):
            continue
        published = sets[(row.group, row.label)].published  # the manifest's, also where the cell is n/a
        first = {name: published[index[keys[0]]] for name, keys in curves.series}
        panels.append(Panel(row.group, row.label, {n: p for n, p in lines.items() if p}, first))
    return panels


def learning_curve_figure(table: Table):
    """One panel per set: x (log) against accuracy, the cell's interval as error bars, one line per series and
    its published number dashed in the same colour."""
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D

    curves = table.manifest.curves
    panels = curve_panels(table)
    ncols = min(3, max(1, len(panels)))
    nrows = -(-max(1, len(panels)) // ncols)
    fig = Figure(figsize=(4 * ncols, 3.2 * nrows + 0.8), layout="constrained")
    axes = fig.subplots(nrows, ncols, squeeze=False).ravel()
    colors = {name: f"C{i % 10}" for i, (name, _) in enumerate(curves.series)}
    ref = table.manifest.compared_with.lower()
    for ax, panel in zip(axes, panels):
        for name, points in panel.lines.items():
            v = np.array([p.value for p in points])
            ci = np.array([p.ci for p in points])
            err = np.clip([v - ci[:, 0], ci[:, 1] - v], 0, None)
            ax.errorbar([p.x for p in points], v, yerr=err, fmt="-o", ms=4, capsize=3, color=colors[name])
            if panel.published[name] is not None:
                ax.axhline(panel.published[name], color=colors[name], ls="--", lw=1)
        ax.set_xscale("log")
        ax.set(title=panel.set, xlabel=X_TEXT[curves.x], ylabel="accuracy (%)")
        ax.title.set_fontsize(9)
        ax.xaxis.label.set_fontsize(7)
    for ax in axes[len(panels) :]:
        ax.axis("off")
    if not panels:
        axes[0].text(0.5, 0.5, "no complete cell of any series yet", ha="center", va="center", fontsize=9)
    handles = []
    for name, keys in curves.series:
        handles.append(Line2D([], [], color=colors[name], marker="o", label=f"{name}: {', '.join(keys)}"))
        handles.append(Line2D([], [], color=colors[name], ls="--", label=f"{name} {ref}"))
    fig.legend(handles=handles, loc="outside lower center", ncols=min(4, len(handles)), fontsize=7)
    what = f"accuracy {METRIC_TEXT[table.metric]}, [{100 * table.level:.0f} % bootstrap interval]"
    fig.suptitle(f"{table.manifest.name}: learning curves ({what})", fontsize=9)
    return fig
