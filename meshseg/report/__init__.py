"""The report: a manifest's table rebuilt from the logged runs and set beside the published numbers
(Markdown, LaTeX, HTML, CSV, PNG under reports/<manifest>/), itself logged as an MLflow run.

    python -m meshseg.report experiments/table2_psb_5fold.yaml

Modules: manifest (experiments/*.yaml), runs (the fold runs of a store, or of results/ records, as one per-mesh
frame), cells (the table's values), aggregate (cells, averages, bootstrap and paired blocks from the frame), table
(a manifest's table assembled: collect, collect_records), write (every format), claims_file and claims (the
paper's claims judged), config (conf/report.yaml and the command line), publish (build, write, log), app (the
command).
"""

from meshseg.errors import ManifestError
from meshseg.report.app import report
from meshseg.report.cells import Table
from meshseg.report.manifest import Manifest, load_manifest
from meshseg.report.publish import build, publish, summary
from meshseg.report.table import collect, collect_records
from meshseg.report.write import write_report

__all__ = [
    "ManifestError",
    "Manifest",
    "Table",
    "load_manifest",
    "collect",
    "collect_records",
    "write_report",
    "build",
    "publish",
    "summary",
    "report",
]
