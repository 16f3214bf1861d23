"""The paper's figures of segmentations and features, rebuilt from the runs (experiments/figures.yaml).

    python -m meshseg.report experiments/figures.yaml      -> reports/figures/{<key>.png, figures.md}

A figures file lists figures, each a grid of mesh pictures (meshseg.render), one grid column per mesh shown:

- kind `labels`: one row per `rows` entry, a column of a study manifest (`table`) or `truth` (the ground
  truth), each test mesh coloured by its per-face labels from the run that tested it. The runs are those the
  manifest's report counts (shipped `results/` imported first, as every report does; a record's labels
  reach the store with it). Which meshes of a set are shown is a fixed rule on the per-mesh accuracies of
  the last run row (`pick`): `median`, `lowest`, `largest_gap` (last row minus the one before), or `first`
  (lowest mesh ids, no runs needed). A panel whose run has no per-face labels (records exported before
  they carried them) is left blank, and the command that gives them (`meshseg.results verify attach=true`
  on just those records) is printed and written under the figure.
- kind `feature_map`: feature columns (`rows`, of the feature set `features`) as colour maps, from the
  feature cache (computed there if missing).
- kind `feature_image`: one face's `features` vector laid out as ToG15's image (`shape`), each column
  standardised over the mesh's faces, its families parted and named.

Every mesh is shown in its principal pose (render.principal_pose), so a rule, not a hand, places it. Each
figure's PNG carries the paper's caption, the mesh ids and each panel's accuracy; figures.md lists the same
with the rule, the runs' config hashes and what could not be drawn (`no_data`: e.g. COSEG's panels).
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from meshseg.errors import ManifestError
from meshseg.report.schema import Invalid, holds_key, known

log = logging.getLogger("meshseg.report")

KINDS = ("labels", "feature_map", "feature_image")
PICKS = ("median", "lowest", "largest_gap", "first")
TRUTH = "truth"
FILE_KEYS = ("name", "title", "note", "overrides", "figures")
FIGURE_KEYS = (
    *("key", "kind", "source", "caption", "table", "rows", "sets", "pick", "meshes"),
    *("features", "face", "shape", "camera", "no_data"),
)
#: pixels per panel side
PANEL = 260


@dataclass(frozen=True)
class FigureSpec:
    key: str
    kind: str
    caption: str
    source: str = ""
    table: str | None = None  # labels: the study manifest whose runs it shows
    rows: tuple[str, ...] = ()  # labels: column keys or `truth`; feature_map: feature columns
    sets: tuple[str, ...] = ()
    pick: str = "first"
    meshes: int = 1  # meshes shown per set
    features: str | None = None  # feature_map / feature_image: a conf/features set
    face: int = 0  # feature_image: the face shown
    shape: tuple[int, int] = (30, 20)  # feature_image: rows x columns
    camera: tuple[float, float] = (15.0, -75.0)  # elev, azim of render.Camera, in the principal pose
    no_data: str = ""  # what the paper's figure shows that cannot be drawn here, and why


@dataclass(frozen=True)
class FiguresFile:
    path: Path
    name: str
    title: str
    note: str
    overrides: tuple[str, ...]
    figures: tuple[FigureSpec, ...]


@dataclass
class Drawn:
    """A figure as drawn: its spec, the meshes shown, the PNG (and where it was written), what kept panels blank."""

    spec: FigureSpec
    shown: list[dict]  # per mesh: set, mesh, and per run row its accuracy (%) and config hash
    blank: list[str] = field(default_factory=list)  # why panels are blank
    missing_labels: list[str] = field(default_factory=list)  # config hashes of runs without per-face labels
    image: bytes | None = None
    png: Path | None = None


def is_figures_file(path) -> bool:
    """Whether a YAML file is a figures file (a mapping with `figures:`)."""
    return holds_key(path, "figures")


def load_figures(path) -> FiguresFile:
    """Read and check a figures file; every problem is one ManifestError naming the file."""
    path = Path(path)
    try:
        doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as e:
        raise ManifestError(f"{path}: cannot read it as YAML: {e}") from None
    try:
        return _figures_file(path, doc)
    except (Invalid, KeyError, TypeError, ValueError) as e:
        raise ManifestError(f"{path}: {e.args[0] if e.args else e}") from None


def _figures_file(path: Path, doc) -> FiguresFile:
    if not isinstance(doc, dict):
        raise ValueError("not a mapping")
    known(doc, FILE_KEYS, "", "a figures file")
    if doc.get("name") != path.stem:
        raise ValueError(f"name must be the file's stem {path.stem!r}, not {doc.get('name')!r}")
    figures = doc.get("figures")
    if not isinstance(figures, list) or not figures:
        raise ValueError("figures: give a list of figures")
    specs = tuple(_figure(f, path) for f in figures)
    keys = [s.key for s in specs]
    if len(set(keys)) != len(keys):
        raise ValueError(f"figure keys must be distinct: {keys}")
    return FiguresFile(
        path, doc["name"], str(doc.get("title", "")), str(doc.get("note", "")), _strings(doc, "overrides"), specs
    )


def _figure(f, path: Path) -> FigureSpec:
    if not isinstance(f, dict):
        raise ValueError(f"a figure must be a mapping, not {f!r}")
    known(f, FIGURE_KEYS, f"figure {f.get('key')!r}: ", "a figure")
    key, kind = f.get("key"), f.get("kind")
    if not isinstance(key, str) or not re.fullmatch(r"[A-Za-z0-9_\-]+", key):
        raise ValueError(f"figure key {key!r}: give a plain name (letters, digits, _ and -)")
    if kind not in KINDS:
        raise ValueError(f"figure {key}: kind {kind!r} is not one of {', '.join(KINDS)}")
    spec = FigureSpec(
        key=key,
        kind=kind,
        caption=str(f.get("caption", "")),
        source=str(f.get("source", "")),
        table=f.get("table"),
        rows=_strings(f, "rows"),
        sets=_strings(f, "sets"),
        pick=f.get("pick", "first"),
        meshes=f.get("meshes", 1),
        features=f.get("features"),
        face=f.get("face", 0),
        shape=tuple(f.get("shape", (30, 20))),
        camera=tuple(float(x) for x in f.get("camera", (15.0, -75.0))),
        no_data=str(f.get("no_data", "")),
    )
    if spec.pick not in PICKS:
        raise ValueError(f"figure {key}: pick {spec.pick!r} is not one of {', '.join(PICKS)}")
    if not isinstance(spec.meshes, int) or spec.meshes < 1:
        raise ValueError(f"figure {key}: meshes must be a whole number >= 1, not {spec.meshes!r}")
    if not spec.sets:
        raise ValueError(f"figure {key}: sets: give the sets it shows")
    if len(spec.camera) != 2:
        raise ValueError(f"figure {key}: camera: give [elev, azim] in degrees")
    (_check_labels if kind == "labels" else _check_features)(spec, path)
    return spec


def _check_labels(spec: FigureSpec, path: Path) -> None:
    key, runs = spec.key, [r for r in spec.rows if r != TRUTH]
    if not spec.rows:
        raise ValueError(f"figure {key}: rows: give column keys of its table, or {TRUTH}")
    if runs and not spec.table:
        raise ValueError(f"figure {key}: table: name the study manifest whose columns {runs} are")
    if spec.table and not (path.parent / f"{spec.table}.yaml").is_file():
        raise ValueError(f"figure {key}: table {spec.table!r}: no {spec.table}.yaml beside {path.name}")
    if spec.pick != "first" and not runs:
        raise ValueError(f"figure {key}: pick {spec.pick} needs a run row; only {TRUTH} is shown")
    if spec.pick == "largest_gap" and len(runs) < 2:
        raise ValueError(f"figure {key}: pick largest_gap needs two run rows (the last minus the one before)")


def _check_features(spec: FigureSpec, path: Path) -> None:
    key, kind = spec.key, spec.kind
    if not spec.features:
        raise ValueError(f"figure {key}: features: name a conf/features set")
    if spec.pick != "first":
        raise ValueError(f"figure {key}: a {kind} figure has no accuracies to pick by: use pick: first")
    if kind == "feature_map" and not spec.rows:
        raise ValueError(f"figure {key}: rows: give the feature columns it maps")
    if kind == "feature_image" and (len(spec.shape) != 2 or not isinstance(spec.face, int) or spec.face < 0):
        raise ValueError(f"figure {key}: give shape: [rows, columns] and face: a face index >= 0")


def _strings(doc: dict, key: str) -> tuple[str, ...]:
    value = doc.get(key) or []
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise ValueError(f"{key}: give a list of names, not {value!r}")
    return tuple(value)


# --- which meshes ---------------------------------------------------------------------------------------


def _id_order(mesh_id: str):
    return (0, int(mesh_id), "") if mesh_id.isdigit() else (1, 0, mesh_id)


def pick_meshes(rule: str, n: int, accuracy: dict[str, float], ids: list[str]) -> list[str]:
    """The n meshes a rule picks: `first` the lowest ids of `ids`; else by `accuracy` (mesh -> value; for
    largest_gap the gap), ties by id: `lowest` the n lowest, `largest_gap` the n largest, `median` the n in
    the middle (for n = 1 the lower median). Shown in id order."""
    if rule == "first":
        return sorted(ids, key=_id_order)[:n]
    order = sorted(accuracy, key=lambda m: (accuracy[m], _id_order(m)))
    if rule == "lowest":
        chosen = order[:n]
    elif rule == "largest_gap":
        chosen = sorted(accuracy, key=lambda m: (-accuracy[m], _id_order(m)))[:n]
    elif rule == "median":
        start = max(0, (len(order) - n) // 2)
        chosen = order[start : start + n]
    else:
        raise ValueError(f"unknown pick rule {rule!r}")
    return sorted(chosen, key=_id_order)


# --- the figures ----------------------------------------------------------------------------------------


def figures_from_config(cfg) -> tuple[FiguresFile, list[Drawn], list[Path]]:
    """`python -m meshseg.report experiments/figures.yaml`: every figure drawn under
    <report.out_dir>/<name>/, with figures.md."""
    from meshseg.report.config import run_overrides

    figures = load_figures(cfg.manifest)
    out = Path(cfg.report.out_dir) / figures.name
    out.mkdir(parents=True, exist_ok=True)
    overrides = [*figures.overrides, *run_overrides(cfg)]
    drawn = []
    for spec in figures.figures:
        builder = {"labels": _labels, "feature_map": _feature_map, "feature_image": _feature_image}[spec.kind]
        d = builder(spec, figures, overrides, cfg)
        if d.image is not None:
            d.png = out / f"{spec.key}.png"
            d.png.write_bytes(d.image)
        drawn.append(d)
    md = out / "figures.md"
    md.write_text(markdown(figures, drawn))
    return figures, drawn, [*(d.png for d in drawn if d.png), md]


def _dataset(overrides):
    from meshseg.config import run_config
    from meshseg.data.datasets import build_dataset

    cfg = run_config(list(overrides))
    return cfg, build_dataset(cfg.dataset)


def _labels(spec: FigureSpec, figures: FiguresFile, overrides, cfg) -> Drawn:
    """A `labels` figure: its rows' labels on the picked meshes of each set."""
    from meshseg.render import Camera, Panel, grid_png, label_colors, principal_pose, render_labels
    from meshseg.report.runs import run_predictions

    runs = [r for r in spec.rows if r != TRUTH]
    table = _table(spec, figures, runs, overrides, cfg) if runs else None
    run_cfg, dataset = _dataset([*(table.manifest.overrides if table else ()), *overrides])
    client = _client(run_cfg) if table else None
    camera = Camera(*spec.camera)
    columns, legends, shown, blank, missing = [], [], [], [], []
    labels_of = {}
    for set_name in spec.sets:
        category = _category(dataset, set_name, spec)
        frame = _set_meshes(table, set_name, runs) if table else {}
        ids = list(dataset.mesh_ids(category))
        incomplete = [k for k in runs if _cell(table, set_name, k).status != "ok"] if table else []
        if incomplete:
            cell = _cell(table, set_name, incomplete[0])
            blank.append(f"{set_name}: {incomplete[0]} not complete ({cell.why()})")
            continue
        score = _pick_scores(spec, runs, frame)
        for n, mesh_id in enumerate(pick_meshes(spec.pick, spec.meshes, score, ids)):
            mesh = dataset.load(category, mesh_id)
            pose = principal_pose(mesh.vertices)
            row_panels, entry = [], {"set": set_name, "mesh": mesh_id}
            for row in spec.rows:
                if row == TRUTH:
                    n_labels = len(mesh.label_names)
                    image = render_labels(pose, mesh.faces, mesh.labels, n_labels, size=PANEL, camera=camera)
                    row_panels.append(Panel(image, f"{set_name} {mesh_id}: ground truth"))
                    continue
                r = frame[row].loc[mesh_id]
                entry[row], entry[f"{row} run"] = float(r["acc"]), str(r["config_hash"])
                key = (row, str(r["run_id"]))
                if key not in labels_of:
                    labels_of[key] = run_predictions(client, str(r["run_id"]))
                pred = (labels_of[key] or {}).get(f"labels_{mesh_id}")
                if pred is None:
                    missing.append(str(r["config_hash"]))
                    row_panels.append(Panel(None, f"{set_name} {mesh_id}: no labels (figures.md)"))
                    continue
                _check_accuracy(pred, mesh, float(r["acc"]), f"{spec.key}: {row} on {set_name} {mesh_id}")
                image = render_labels(pose, mesh.faces, pred, len(mesh.label_names), size=PANEL, camera=camera)
                row_panels.append(Panel(image, f"{set_name} {mesh_id}: {float(r['acc']):.1f} %"))
            columns.append(row_panels)
            legends.append(
                list(zip(mesh.label_names, map(tuple, label_colors(len(mesh.label_names))))) if n == 0 else []
            )
            shown.append(entry)
    d = Drawn(spec, shown, blank, sorted(set(missing)))
    if columns:
        titles = [_row_title(table, r) for r in spec.rows]
        grid = [[columns[j][i] for j in range(len(columns))] for i in range(len(spec.rows))]
        d.image = grid_png(grid, title=_wrap(spec.caption), row_titles=titles, legends=legends, note=_note(d))
    return d


def _table(spec: FigureSpec, figures: FiguresFile, runs: list[str], overrides, cfg):
    """The figure's study manifest's table, with only its run rows' columns and sets (results imported)."""
    from meshseg.report.manifest import load_manifest
    from meshseg.report.publish import bootstrap, import_results
    from meshseg.report.table import collect

    manifest = load_manifest(figures.path.parent / f"{spec.table}.yaml")
    unknown = [k for k in runs if k not in {c.key for c in manifest.columns}]
    if unknown:
        raise ManifestError(f"{figures.path}: figure {spec.key}: {unknown} are not columns of {spec.table}")
    names = {s.name for g in manifest.groups for s in g.sets}
    if set(spec.sets) - names:
        raise ManifestError(
            f"{figures.path}: figure {spec.key}: {sorted(set(spec.sets) - names)} are not sets of {spec.table} "
            f"({', '.join(sorted(names))})"
        )
    manifest = manifest.only_columns(runs)
    import_results([manifest], cfg, spec.sets)
    return collect(manifest, list(overrides), sets=list(spec.sets), paired=[], boot=bootstrap(cfg.report))


def _cell(table, set_name: str, key: str):
    j = [c.key for c in table.columns].index(key)
    return next(r.cells[j] for r in table.rows if r.kind == "set" and r.label == set_name)


def _set_meshes(table, set_name: str, runs: list[str]) -> dict[str, pd.DataFrame]:
    """Per run row, the set's per-mesh rows indexed by mesh id (acc, run_id, config_hash); a column with several
    training seeds shows its first seed's runs."""
    m = table.meshes
    return {
        k: m[(m["row"] == set_name) & (m["column"] == k)]
        .sort_values("seed", kind="stable")
        .drop_duplicates("mesh")
        .set_index("mesh")
        for k in runs
    }


def _pick_scores(spec: FigureSpec, runs: list[str], frame: dict) -> dict[str, float]:
    if spec.pick == "first" or not runs:
        return {}
    last = frame[runs[-1]]["acc"]
    if spec.pick == "largest_gap":
        return (last - frame[runs[-2]]["acc"]).dropna().to_dict()
    return last.to_dict()


def _category(dataset, set_name: str, spec: FigureSpec) -> str:
    names = {re.sub(r"[-_]", "", c).lower(): c for c in dataset.categories}
    found = names.get(re.sub(r"[-_]", "", set_name).lower())
    if found is None:
        raise ManifestError(f"figure {spec.key}: dataset {dataset.name} has no set {set_name!r}")
    return found


def _client(run_cfg):
    from mlflow import MlflowClient

    from meshseg.tracking import store_uri

    return MlflowClient(tracking_uri=store_uri(run_cfg.tracking.uri))


def _check_accuracy(pred: np.ndarray, mesh, acc: float, what: str) -> None:
    """The labels drawn must score what the run logged: otherwise they are another run's, or another mesh's."""
    from meshseg.metrics import area_weighted_accuracy

    again = 100.0 * area_weighted_accuracy(np.asarray(pred, np.int64), mesh.labels, mesh.face_areas)
    if abs(again - acc) > 1e-6:
        raise ManifestError(f"{what}: the run's labels score {again:.4f} %, its logged accuracy is {acc:.4f} %")


def _row_title(table, row: str) -> str:
    if row == TRUTH:
        return "ground truth"
    return next(c.label for c in table.columns if c.key == row)


def _feature_values(spec: FigureSpec, overrides, mesh):
    """The mesh's (F, dim) features of the set `spec.features`, and the set (cache: paths.cache_dir)."""
    from meshseg.config import run_config
    from meshseg.features.cache import FeatureCache
    from meshseg.features.sets import FeatureSet

    cfg = run_config([*overrides, f"features={spec.features}"])
    fs = FeatureSet.from_config(cfg.features)
    return fs.compute(mesh.vertices, mesh.faces, mesh.content_hash, FeatureCache(cfg.paths.cache_dir)), fs


def _feature_map(spec: FigureSpec, figures: FiguresFile, overrides, cfg) -> Drawn:
    """A `feature_map` figure: feature columns as colour maps on the first meshes of each set."""
    from meshseg.render import Camera, Panel, grid_png, principal_pose, render_faces, value_colors

    _, dataset = _dataset(overrides)
    camera, columns, shown = Camera(*spec.camera), [], []
    for set_name in spec.sets:
        category = _category(dataset, set_name, spec)
        for mesh_id in pick_meshes("first", spec.meshes, {}, list(dataset.mesh_ids(category))):
            mesh = dataset.load(category, mesh_id)
            X, fs = _feature_values(spec, overrides, mesh)
            unknown = [r for r in spec.rows if r not in fs.columns]
            if unknown:
                raise ManifestError(f"{figures.path}: figure {spec.key}: {unknown} are not columns of {fs.name}")
            pose = principal_pose(mesh.vertices)
            panels = []
            for r in spec.rows:
                values = X[:, fs.columns.index(r)]
                image = render_faces(pose, mesh.faces, value_colors(values), size=PANEL, camera=camera)
                panels.append(Panel(image, f"{set_name} {mesh_id}: {r}"))
            columns.append(panels)
            shown.append({"set": set_name, "mesh": mesh_id})
    d = Drawn(spec, shown)
    grid = [[columns[j][i] for j in range(len(columns))] for i in range(len(spec.rows))]
    note = "colour: each map from its own 2nd (dark) to 98th (yellow) percentile (viridis)"
    d.image = grid_png(grid, title=_wrap(spec.caption), row_titles=list(spec.rows), note=_note(d, note))
    return d


def _feature_image(spec: FigureSpec, figures: FiguresFile, overrides, cfg) -> Drawn:
    """A `feature_image` figure: one face's feature vector as ToG15's image, its families named."""
    from meshseg.render import feature_image_png

    _, dataset = _dataset(overrides)
    category = _category(dataset, spec.sets[0], spec)
    mesh_id = pick_meshes("first", 1, {}, list(dataset.mesh_ids(category)))[0]
    mesh = dataset.load(category, mesh_id)
    X, fs = _feature_values(spec, overrides, mesh)
    h, w = spec.shape
    if h * w != X.shape[1] or spec.face >= len(X):
        raise ManifestError(
            f"{figures.path}: figure {spec.key}: {fs.name} has {X.shape[1]} columns and the mesh {len(X)} faces; "
            f"shape {h} x {w} and face {spec.face} do not fit"
        )
    sd = X.std(axis=0)
    z = (X[spec.face] - X.mean(axis=0)) / np.where(sd > 0, sd, 1.0)
    bands = [(label, a, b) for label, (a, b) in fs.layout.items()]
    title = f"{spec.sets[0]} {mesh_id}, face {spec.face}: {fs.name} standardised over the mesh's faces"
    d = Drawn(spec, [{"set": spec.sets[0], "mesh": mesh_id, "face": spec.face}])
    d.image = feature_image_png(z.reshape(h, w), bands, title=_wrap(f"{spec.caption}\n{title}", 70))
    return d


def _wrap(text: str, width: int = 110) -> str:
    import textwrap

    return "\n".join(textwrap.fill(part, width) for part in text.split("\n"))


def _note(d: Drawn, extra: str = "") -> str:
    parts = [extra] if extra else []
    if d.spec.no_data:
        parts.append(f"not drawn: {d.spec.no_data}")
    parts += [f"blank: {b}" for b in d.blank]
    if d.missing_labels:
        parts.append(f"{len(d.missing_labels)} runs have no per-face labels: see figures.md")
    return _wrap("; ".join(parts), 140)


def verify_command(hashes: list[str]) -> str:
    """The command that gives the runs of these config hashes their per-face labels (records in results/)."""
    where = "|".join(hashes)
    return f"python -m meshseg.results verify where=config_hash={where} attach=true out=reports/verify-figures"


_RULES = {
    "median": "the set's median mesh by the last row's accuracy (lower median; ties by id)",
    "lowest": "the set's lowest-scoring meshes by the last row's accuracy",
    "largest_gap": "the meshes where the last row leads the row before it most",
    "first": "the set's lowest mesh ids",
}


def markdown(figures: FiguresFile, drawn: list[Drawn]) -> str:
    lines = [f"# {figures.title or figures.name}", ""]
    if figures.note:
        lines += [figures.note, ""]
    for d in drawn:
        s = d.spec
        lines += [f"## {s.key} ({s.source})" if s.source else f"## {s.key}", "", f"> {s.caption}", ""]
        rule = _RULES[s.pick] + (f", {s.meshes} per set" if s.meshes > 1 else "")
        what = f"rows: {', '.join(s.rows)}" + (f" of `{s.table}`" if s.table else "")
        lines += [f"{what}; meshes: {rule}." + (f" File: `{d.png.name}`." if d.png else " Not drawn."), ""]
        runs = [r for r in s.rows if r != TRUTH] if s.kind == "labels" else []
        if d.shown:
            head = ["set", "mesh", *(f"{r} (%)" for r in runs), *(f"{r} run" for r in runs)]
            if s.kind == "feature_image":
                head.append("face")
            lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
            for e in d.shown:
                cells = [e["set"], e["mesh"], *(f"{e[r]:.2f}" if r in e else "—" for r in runs)]
                cells += [e.get(f"{r} run", "—") for r in runs]
                if s.kind == "feature_image":
                    cells.append(str(e["face"]))
                lines.append("| " + " | ".join(cells) + " |")
            lines.append("")
        if s.no_data:
            lines += [f"No data: {s.no_data}", ""]
        lines += [f"Blank: {b}" for b in d.blank]
        if d.missing_labels:
            lines += [
                f"{len(d.missing_labels)} of its runs carry no per-face labels (records exported before they did); "
                "make them again and attach their labels, then rebuild:",
                "",
                f"    {verify_command(d.missing_labels)}",
                "",
            ]
    return "\n".join(lines).rstrip() + "\n"


def summary(drawn: list[Drawn], files: list[Path]) -> str:
    """What the command prints: each figure, what it shows or lacks, then the files."""
    out = []
    for d in drawn:
        meshes = ", ".join(f"{e['set']} {e['mesh']}" for e in d.shown) or "nothing"
        out.append(f"{d.spec.key}: {meshes}")
        out += [f"  blank: {b}" for b in d.blank]
        if d.missing_labels:
            out.append(f"  {len(d.missing_labels)} runs without labels: {verify_command(d.missing_labels)}")
    return "\n".join(out) + "\nwrote " + ", ".join(map(str, files))
