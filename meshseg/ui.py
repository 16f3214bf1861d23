"""`python -m meshseg.ui` (`make ui`): the MLflow UI on the runs' store, opened at the runs table.

    python -m meshseg.ui [port=5000] [tracking.uri=...] [paths.mlflow_dir=...]

A sqlite store gets `mlflow ui` on 127.0.0.1:<port>; a tracking server (`tracking.uri=http://...`) is its own
UI, so its URL is printed and nothing is started. MLflow 3 opens an experiment in its GenAI view; the URL
printed here lands on the runs table (`workflowType=machine_learning`).
"""

from __future__ import annotations

import os
import shutil
import sys

from meshseg.cli import command


@command
def main(argv=None) -> None:
    from hydra import compose, initialize_config_dir

    from meshseg import CONF_DIR
    from meshseg.tracking import Tracker

    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] in ("-h", "--help"):
        print(__doc__.strip())
        return
    port = next((a.split("=", 1)[1] for a in argv if a.startswith("port=")), "5000")
    overrides = [a for a in argv if not a.startswith("port=")]
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose("run", overrides=overrides)
    tracker = Tracker(cfg.tracking.uri, cfg.tracking.experiment, cfg.tracking.artifact_dir)
    base = f"http://127.0.0.1:{port}"
    print(f"runs of experiment {cfg.tracking.experiment!r}: {tracker.runs_url(base)}", flush=True)
    if tracker.uri.startswith(("http://", "https://")):
        return
    mlflow = shutil.which("mlflow", path=os.path.dirname(sys.executable)) or "mlflow"
    args = [mlflow, "ui", "--backend-store-uri", tracker.uri, "--host", "127.0.0.1", "--port", str(port)]
    os.execv(mlflow, args)  # the UI in this process: Ctrl-C stops it


if __name__ == "__main__":
    main()
