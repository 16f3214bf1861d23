"""A table in every format the report writes: Markdown, LaTeX, HTML, CSV, and a PNG of reproduced
vs published per set (and the learning curves of a manifest that declares them). Numbers are accuracies
in %; a cell without a complete set of runs is printed as what it lacks, never as a number; a cell no part
of the study (n/a: outside its column's `sets`) as a dash."""

from __future__ import annotations

import csv
import fcntl
import html
import io
import os
import re
import tempfile
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from meshseg.report.boundaries import BAND_NAMES
from meshseg.report.boundaries import summary as boundaries_summary
from meshseg.report.cells import Cell, Table, progress
from meshseg.report.config import METRIC_TEXT
from meshseg.report.curves import learning_curve_figure

#: the paper's LaTeX label in a manifest's `source`, shown in headers as its bare name (no LaTeX there)
_LABEL = re.compile(r"\\label\{([^}]*)\}")

FILES = ("table.md", "table.tex", "table.html", "table.csv", "comparison.png")


def _num(v: float | None, signed: bool = False) -> str:
    return "—" if v is None else f"{v:+.2f}" if signed else f"{v:.2f}"


def _ours(
    cell: Cell,
    ok: str = "{v:.2f} [{lo:.2f}, {hi:.2f}]",
    missing: str = "{status}: {why}",
    published: str = "—",
    escape=str,
) -> str:
    """The reproduced part of a cell in one format's markup: `ok` formats a value and its interval,
    `missing` what an incomplete or unavailable cell lacks, `published` stands for a published-only column; an
    n/a cell (no part of the study) is a dash in every format."""
    if cell.status == "n/a":
        return "—"
    if cell.status == "ok":
        return ok.format(v=cell.value, lo=cell.ci[0], hi=cell.ci[1])
    if cell.status == "published":
        return published
    if cell.status == "incomplete":
        return cell.short()
    return missing.format(status=cell.status, why=escape(cell.why()))


def header_lines(table: Table) -> list[str]:
    m = table.manifest
    budgets = "; ".join(f"{b} ({table.budget_text.get(b, '?')})" for b in table.budgets)
    lines = [
        m.title,
        f"{m.compared_with}: " + _LABEL.sub(r"\1", m.source) if m.source else "",
        f"Budget: {budgets or '—'}; cell = mean accuracy (%) over all test meshes of all folds "
        f"({METRIC_TEXT[table.metric]}), [{100 * table.level:.0f} % bootstrap interval over test meshes]; "
        f"Δ = reproduced − {m.compared_with.lower()}",
        f"Overrides: {' '.join(table.overrides)}" if table.overrides else "",
        m.note,
    ]
    return [line for line in lines if line]


def _md_cell(cell: Cell) -> str:
    ours = _ours(cell)
    if cell.status == "ok" and cell.seed_sd is not None:  # a mean over seeds: the spread between them
        ours += f" sd {cell.seed_sd:.2f} over {len(cell.seed_values)} seeds"
    if cell.published is None:
        return ours
    return f"{ours} / {cell.published:.2f}" + ("" if cell.delta is None else f" ({cell.delta:+.2f})")


def markdown(table: Table) -> str:
    """One column per method; each cell `reproduced [CI] / published (Δ)` (the parts that exist)."""
    cols = table.columns
    out = [
        f"**{header_lines(table)[0]}**",
        "",
        *[f"{line}  " for line in header_lines(table)[1:]],
        "",
        "| Set | " + " | ".join(c.label for c in cols) + " |",
        "|---|" + "---|" * len(cols),
    ]
    for row in table.rows:
        label = row.label if row.kind == "set" else f"**{row.label}**"
        out.append(f"| {label} | " + " | ".join(_md_cell(c) for c in row.cells) + " |")
    out += ["", progress(table).text()]
    for p in table.pairs:
        out += [
            "",
            f"**Paired comparison: {p.a.label} − {p.b.label}** (mean per-mesh difference in points over the test "
            f"meshes both scored, [{100 * table.level:.0f} % paired bootstrap interval resampling seeds, folds, then "
            "meshes]; averages: mean over sets)",
            "",
            "| Set | Δ | meshes |",
            "|---|---|---|",
        ]
        for r in p.rows:
            label = r.label if r.kind == "set" else f"**{r.label}**"
            value = r.why if r.value is None else f"{r.value:+.2f} [{r.ci[0]:+.2f}, {r.ci[1]:+.2f}]"
            meshes = f"{r.n_meshes} (partial: {r.partial})" if r.partial else r.n_meshes
            out.append(f"| {label} | {value} | {meshes} |")
    if _has_refinement(table):
        out += [
            "",
            "**Refinement: raw → refined** (per set, the network's argmax accuracy → after refinement, and refined "
            f"− raw in points per test mesh [{100 * table.level:.0f} % paired bootstrap interval]; averages: mean "
            "over sets)",
            "",
            "| Set | " + " | ".join(c.label for c, _ in table.refinement) + " |",
            "|---|" + "---|" * len(table.refinement),
        ]
        index = {c.key: j for j, c in enumerate(cols)}
        for i, row in enumerate(table.rows):
            label = row.label if row.kind == "set" else f"**{row.label}**"
            cells = [_refinement_md(row.cells[index[c.key]], gains[i], table.metric) for c, gains in table.refinement]
            out.append(f"| {label} | " + " | ".join(cells) + " |")
        helped = [
            f"{c.label} {sum(r.value > 0 for r in done)} of {len(done)}"
            for c, gains in table.refinement
            if (done := [r for r in gains if r.kind == "set" and r.value is not None])
        ]
        out += ["", f"Sets the refinement raised: {', '.join(helped)}."]
    if table.boundaries is not None:
        out += ["", *_boundaries_md(table)]
    return "\n".join(out) + "\n"


def _boundaries_md(table: Table) -> list[str]:
    """report.boundaries' block: each column's wrong area by face rings from the true part boundary, then
    each pair's difference by ring, over the meshes both have (boundaries.csv has every mesh)."""
    frame, unlabelled, raw_files = table.boundaries
    labels = {c.key: c.label for c in table.columns}
    pairs = [(p.a.key, p.b.key) for p in table.pairs]
    lines = boundaries_summary(frame, pairs)
    why = []
    if unlabelled:
        why.append(
            f"{unlabelled} without per-face labels here (results/ records exported before 2026-12-02 carry none)"
        )
    if raw_files:
        why.append(f"{raw_files} from labellings on disk, which have no argmax before refinement")
    aside = f"; {unlabelled + raw_files} test meshes left out: {', '.join(why)}" if why else ""
    out = [
        "**Where the errors lie** (wrong area in % of each test mesh's area, by face rings from the nearest "
        "true part boundary, ring 0 on it; mean over meshes; a pair's row: its accuracy difference a − b in "
        f"points, split the same way{aside})",
        "",
        "| | meshes | all | " + " | ".join(f"ring {b}" for b in BAND_NAMES) + " |",
        "|---|---|---|" + "---|" * len(BAND_NAMES),
    ]
    for r in lines.itertuples(index=False):
        name = labels[r.column] + (f" − {labels[r.minus]}" if r.minus else "")
        values = [_num(v, bool(r.minus)) for v in r[3:]]
        out.append(f"| {name} | {r.meshes} | " + " | ".join(values) + " |")
    return out if len(lines) else out[:1] + ["", "No test mesh has per-face labels here."]


def boundaries_csv(table: Table) -> str:
    """report.boundaries' frame: one line per (column, test mesh), its wrong area in % by ring band."""
    frame = table.boundaries[0]
    return frame.to_csv(index=False, float_format="%.4f")


def _has_refinement(table: Table) -> bool:
    return any(r.value is not None for _, gains in table.refinement for r in gains)


def _raw_refined(cell: Cell, gain: float, metric: str) -> tuple[float, float]:
    """A cell's (raw, refined) accuracy from its value under `metric` and the refinement's mean gain."""
    refined = cell.value if metric == "acc" else cell.value + gain
    return refined - gain, refined


def _refinement_md(cell: Cell, r, metric: str) -> str:
    if r.value is None:
        return "—" if r.kind != "set" or r.why in ("incomplete", "n/a") else r.why
    raw, refined = _raw_refined(cell, r.value, metric)
    return f"{raw:.2f} → {refined:.2f} ({r.value:+.2f} [{r.ci[0]:+.2f}, {r.ci[1]:+.2f}])"


def refinement_csv(table: Table) -> str:
    """The refinement's effect, one line per (row, run column): raw and refined accuracy, their difference."""
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["row", "kind", "column", "raw", "refined", "gain", "ci_low", "ci_high", "n_meshes", "why"])
    f = lambda v: "" if v is None else f"{v:.4f}"  # noqa: E731
    index = {c.key: j for j, c in enumerate(table.columns)}
    for column, gains in table.refinement:
        for row, r in zip(table.rows, gains):
            raw, refined = (
                (None, None) if r.value is None else _raw_refined(row.cells[index[column.key]], r.value, table.metric)
            )
            w.writerow(
                [
                    row.label,
                    r.kind,
                    column.key,
                    f(raw),
                    f(refined),
                    f(r.value),
                    f(r.ci and r.ci[0]),
                    f(r.ci and r.ci[1]),
                    r.n_meshes,
                    r.why,
                ]
            )
    return buf.getvalue()


def paired_csv(table: Table) -> str:
    """The paired comparisons, one line per (pair, row); columns a and b name the pair."""
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["row", "kind", "a", "b", "delta", "ci_low", "ci_high", "n_meshes", "why", "partial"])
    f = lambda v: "" if v is None else f"{v:.4f}"  # noqa: E731
    for p in table.pairs:
        for r in p.rows:
            ci = (f(r.ci and r.ci[0]), f(r.ci and r.ci[1]))
            w.writerow([r.label, r.kind, p.a.key, p.b.key, f(r.value), *ci, r.n_meshes, r.why, r.partial])
    return buf.getvalue()


def csv_text(table: Table) -> str:
    """Long form, one line per cell (averages included): everything the other formats show."""
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(
        [
            "group",
            "row",
            "kind",
            "column",
            "label",
            "status",
            "reproduced",
            "ci_low",
            "ci_high",
            "published",
            "delta",
            "n_meshes",
            "folds",
            "folds_missing",
            "budget",
            "why",
            "category",
            "config_hashes",
            "seeds",
            "seed_values",
        ]
    )
    f = lambda v: "" if v is None else f"{v:.4f}"
    for row in table.rows:
        for c in row.cells:
            w.writerow(
                [
                    row.group,
                    row.label,
                    row.kind,
                    c.column.key,
                    c.column.label,
                    c.status,
                    f(c.value),
                    f(c.ci and c.ci[0]),
                    f(c.ci and c.ci[1]),
                    f(c.published),
                    f(c.delta),
                    c.n_meshes,
                    c.folds,
                    " ".join(map(str, c.missing)),
                    c.budget or "",
                    c.why() if c.status in ("incomplete", "unavailable", "n/a") else "",
                    c.category or "",
                    " ".join(c.config_hashes),
                    " ".join(map(str, c.seeds)),
                    " ".join(f"{v:.4f}" for v in c.seed_values),
                ]
            )
    return buf.getvalue()


def _tex(s: str) -> str:
    for a, b in (("\\", r"\textbackslash{}"), ("&", r"\&"), ("%", r"\%"), ("_", r"\_"), ("#", r"\#"), ("$", r"\$")):
        s = s.replace(a, b)
    return s


def latex(table: Table) -> str:
    """booktabs tabular: per method three columns, ours (with its interval), published, Δ."""
    cols = table.columns
    lines = ["% " + line for line in header_lines(table)]
    lines += [
        r"\begin{tabular}{l" + "rrr" * len(cols) + "}",
        r"\toprule",
        " & " + " & ".join(rf"\multicolumn{{3}}{{c}}{{{_tex(c.label)}}}" for c in cols) + r" \\",
        "".join(rf"\cmidrule(lr){{{2 + 3 * i}-{4 + 3 * i}}}" for i in range(len(cols))),
        "Set & " + " & ".join(["ours", "paper", r"$\Delta$"] * len(cols)) + r" \\",
        r"\midrule",
    ]
    for row in table.rows:
        if row.kind != "set":
            lines.append(r"\midrule")
        parts = []
        for c in row.cells:
            ours = _ours(c, r"{v:.2f}\,{{\scriptsize[{lo:.2f}, {hi:.2f}]}}", r"\textit{{{status}: {why}}}", "--", _tex)
            parts += [
                ours,
                "--" if c.published is None else f"{c.published:.2f}",
                "--" if c.delta is None else f"{c.delta:+.2f}",
            ]
        label = _tex(row.label) if row.kind == "set" else rf"\textbf{{{_tex(row.label)}}}"
        lines.append(f"{label} & " + " & ".join(parts) + r" \\")
    lines += [r"\bottomrule", r"\end{tabular}", "% " + progress(table).text()]
    return "\n".join(lines) + "\n"


def html_text(table: Table) -> str:
    """A standalone page: the same sub-columns as the LaTeX, incomplete cells in italics."""
    e = html.escape
    cols = table.columns
    head = "".join(f'<th colspan="3">{e(c.label)}</th>' for c in cols)
    sub = "".join("<th>ours</th><th>paper</th><th>Δ</th>" for _ in cols)
    body = []
    for row in table.rows:
        tds = []
        for c in row.cells:
            ours = _ours(
                c, "{v:.2f} <small>[{lo:.2f}, {hi:.2f}]</small>", '<i class="{status}">{status}: {why}</i>', escape=e
            )
            tds.append(f"<td>{ours}</td><td>{_num(c.published)}</td><td>{_num(c.delta, True)}</td>")
        cls = "" if row.kind == "set" else ' class="average"'
        body.append(f"<tr{cls}><th>{e(row.label)}</th>{''.join(tds)}</tr>")
    notes = "".join(f"<p>{e(line)}</p>" for line in header_lines(table)[1:])
    return (
        f'<!doctype html>\n<html><head><meta charset="utf-8"><title>{e(table.manifest.name)}</title>\n'
        "<style>table{border-collapse:collapse}td,th{border:1px solid #ccc;padding:2px 6px;text-align:right}"
        "tr.average{font-weight:bold}i{color:#a00}</style></head><body>\n"
        f"<h2>{e(table.manifest.title)}</h2>{notes}\n"
        f'<table><tr><th rowspan="2">Set</th>{head}</tr><tr>{sub}</tr>\n'
        + "\n".join(body)
        + f"\n</table><p>{e(progress(table).text())}</p></body></html>\n"
    )


def comparison_figure(table: Table):
    """Left: reproduced vs published for every complete cell with a published number, y = x dashed,
    intervals as error bars. Right: per set, reproduced bars per column with published ticks. A table with
    no published number at all (a figure the paper printed only as an image, e.g. the CF figure) is drawn
    as that figure: `bar_figure`."""
    from matplotlib.figure import Figure

    if all(c.published is None for r in table.rows for c in r.cells):
        return bar_figure(table)
    cols = [c for c in table.columns if c.overrides is not None]
    sets = [r for r in table.rows if r.kind == "set"]
    ref = table.manifest.compared_with.lower()  # "published", or "reference" for a pinned run's numbers
    colors = {c.key: f"C{i % 10}" for i, c in enumerate(cols)}
    fig = Figure(figsize=(6 + 0.45 * len(sets) * max(1, len(cols)) ** 0.5, 5), layout="constrained")
    ax, bx = fig.subplots(1, 2, width_ratios=[1, 2])
    lo, hi = 100.0, 0.0
    for c in cols:
        pts = [
            (x.published, x.value, x.ci)
            for r in sets
            for x in r.cells
            if x.column.key == c.key and x.status == "ok" and x.published is not None
        ]
        if pts:
            p, v, ci = map(np.array, zip(*pts))
            ax.errorbar(p, v, yerr=np.abs(ci.T - v), fmt="o", ms=4, color=colors[c.key], capsize=2)
            lo, hi = min(lo, p.min(), ci.min()), max(hi, p.max(), ci.max())
    if hi > lo:
        pad = 0.05 * (hi - lo) + 0.2
        ax.plot([lo - pad, hi + pad], [lo - pad, hi + pad], "k--", lw=0.8, label="y = x")
        ax.legend(fontsize=7, loc="upper left")  # the columns' colours: the figure's legend
    else:
        ax.text(
            0.5,
            0.5,
            f"no cell has both a reproduced\nand a {ref} number",
            ha="center",
            va="center",
            transform=ax.transAxes,
            fontsize=8,
        )
    ax.set(xlabel=f"{ref} accuracy (%)", ylabel="reproduced accuracy (%)", title=f"reproduced vs {ref}")
    ax.title.set_fontsize(9)
    width = 0.8 / max(1, len(cols))
    x = np.arange(len(sets))
    for i, c in enumerate(cols):
        cells = [next(x_ for x_ in r.cells if x_.column.key == c.key) for r in sets]
        studied = sum(x_.status != "n/a" for x_ in cells)  # a column's `sets` are all it has
        vals = np.array([np.nan if x_.value is None else x_.value for x_ in cells])
        pub = np.array([np.nan if x_.published is None else x_.published for x_ in cells])
        pos = x - 0.4 + width * (i + 0.5)
        done = int(np.isfinite(vals).sum())
        label = c.label if done == studied else f"{c.label} ({done}/{studied} sets)"  # a partly empty table says so
        bx.bar(pos, vals, width, color=colors[c.key], label=label)
        bx.plot(pos, pub, "_", color="k", ms=max(4, 40 * width), mew=1.5)
    finite = [v for r in sets for c in r.cells for v in (c.value, c.published) if v is not None]
    if finite:
        bx.set_ylim(max(0, min(finite) - 3), min(100, max(finite) + 1))
    bx.set_xticks(x, [r.label for r in sets], rotation=60, ha="right", fontsize=7)
    bx.set(ylabel="accuracy (%)", title=f"per set: bars reproduced, black ticks {ref}")
    bx.title.set_fontsize(9)
    if cols:  # below both panels, so that it hides no bar
        handles, labels = bx.get_legend_handles_labels()
        fig.legend(handles, labels, loc="outside lower center", ncols=min(4, len(cols)), fontsize=7)
    p = progress(table)
    fig.suptitle(
        f"{table.manifest.name} (budget {', '.join(table.budgets) or '—'}; {p.cells_done} of {p.cells} cells complete)",
        fontsize=9,
    )
    return fig


def bar_figure(table: Table):
    """Per set, then per average row, one bar per column with its interval as an error bar, the sets in
    table order: the paper's bar charts (e.g. the CF figure). A cell without a value has no bar; the legend
    says how many sets each column has."""
    from matplotlib.figure import Figure

    cols = [c for c in table.columns if c.overrides is not None or c.predictions is not None]  # not published-only
    rows = [r for r in table.rows if r.kind in ("set", "average", "total")]
    fig = Figure(figsize=(max(6.5, 3 + 0.26 * len(rows) * max(1, len(cols)) ** 0.5), 4.6), layout="constrained")
    ax = fig.subplots()
    width, x = 0.8 / max(1, len(cols)), np.arange(len(rows), dtype=float)
    x[[r.kind != "set" for r in rows]] += 0.5  # a gap before the averages
    low = []
    for i, c in enumerate(cols):
        cells = [next(x_ for x_ in r.cells if x_.column.key == c.key) for r in rows]
        vals = np.array([np.nan if x_.value is None else x_.value for x_ in cells])
        err = np.array([[v - x_.ci[0], x_.ci[1] - v] if x_.ci else [0, 0] for x_, v in zip(cells, vals)]).T
        done = sum(x_.value is not None for x_, r in zip(cells, rows) if r.kind == "set")
        studied = sum(x_.status != "n/a" for x_, r in zip(cells, rows) if r.kind == "set")
        label = c.label if done == studied else f"{c.label} ({done}/{studied} sets)"
        ax.bar(
            x - 0.4 + width * (i + 0.5),
            vals,
            width,
            yerr=err,
            color=f"C{i % 10}",
            label=label,
            error_kw={"elinewidth": 0.7, "capsize": 1.5},
        )
        low += [x_.ci[0] for x_ in cells if x_.ci]
    if low:
        ax.set_ylim(max(0, min(low) - 5), 100)
    ax.set_xticks(x, [r.label for r in rows], rotation=60, ha="right", fontsize=7)
    level = round(100 * table.level)
    ax.set(ylabel=f"accuracy (%), bars with {level} % intervals over test meshes")
    ax.yaxis.label.set_fontsize(8)
    ax.grid(axis="y", lw=0.3)
    ax.set_axisbelow(True)
    if cols:
        fig.legend(loc="outside lower center", ncols=min(6, len(cols)), fontsize=7)
    p = progress(table)
    fig.suptitle(
        f"{table.manifest.title}\n{table.manifest.name} (budget {', '.join(table.budgets) or '—'}; "
        f"{p.cells_done} of {p.cells} cells complete)",
        fontsize=9,
    )
    return fig


def png_bytes(fig, dpi: int = 110) -> bytes:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    buf = io.BytesIO()
    FigureCanvasAgg(fig)  # headless, without touching pyplot's global backend
    fig.savefig(buf, format="png", dpi=dpi)
    return buf.getvalue()


#: files a report writes only when it has their content (paired blocks, a learning curve, refined runs)
OPTIONAL_FILES = frozenset({"paired.csv", "learning_curve.png", "refinement.csv", "boundaries.csv"})


def write_report(table: Table, out_dir: str | Path) -> list[Path]:
    """Write every format into out_dir (created); each file is written whole or not at all."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    contents = {
        "table.md": markdown(table),
        "table.tex": latex(table),
        "table.html": html_text(table),
        "table.csv": csv_text(table),
        "comparison.png": png_bytes(comparison_figure(table)),
    }
    if table.pairs:
        contents["paired.csv"] = paired_csv(table)
    if table.manifest.curves is not None:
        contents["learning_curve.png"] = png_bytes(learning_curve_figure(table))
    if _has_refinement(table):
        contents["refinement.csv"] = refinement_csv(table)
    if table.boundaries is not None:
        contents["boundaries.csv"] = boundaries_csv(table)
    # one an earlier report wrote would describe other runs
    return write_files(out, contents, stale=OPTIONAL_FILES.difference(contents))


def write_files(out: Path, contents: dict[str, str | bytes], stale: Iterable[str] = ()) -> list[Path]:
    """Each file of `contents` into the folder `out`, written whole or not at all, and the files named in
    `stale` removed. Two writers of one folder (two reports of one manifest, `reproduce` beside `report`)
    take turns under a lock, so the folder ends wholly one writer's, and each file goes through a
    temporary name of its own, never another writer's."""
    paths = []
    with open(out / ".write.lock", "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes, also if this process dies
        for name in stale:
            (out / name).unlink(missing_ok=True)
        for name, data in contents.items():
            path = out / name
            fd, tmp = tempfile.mkstemp(dir=out, prefix=f".{name}.", suffix=".tmp")
            try:
                with os.fdopen(fd, "wb") as f:
                    f.write(data if isinstance(data, bytes) else data.encode())
                os.chmod(tmp, 0o644)  # mkstemp's 0600 would hide a report from other users
                os.replace(tmp, path)
            except BaseException:
                Path(tmp).unlink(missing_ok=True)
                raise
            paths.append(path)
    return paths
