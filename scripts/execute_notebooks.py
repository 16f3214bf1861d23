"""Execute the notebooks in place on the shipped results, so their committed outputs show today's results/.

    python scripts/execute_notebooks.py                      # all of notebooks/*.ipynb
    python scripts/execute_notebooks.py compare_published    # one

Each runs from notebooks/ with its own default parameters (results/, no store), this checkout first on the
kernel's path. tests/test_notebooks.py holds the committed outputs to the committed reports.
"""

import os
import sys
import time
from pathlib import Path

import nbformat
from nbclient import NotebookClient

REPO = Path(__file__).resolve().parents[1]
NOTEBOOKS = REPO / "notebooks"


def main(names: list[str]) -> None:
    paths = [NOTEBOOKS / f"{n.removesuffix('.ipynb')}.ipynb" for n in names] or sorted(NOTEBOOKS.glob("*.ipynb"))
    missing = [str(p) for p in paths if not p.is_file()]
    if missing:
        sys.exit(f"error: no such notebook: {', '.join(missing)}")
    # the kernel imports this checkout's meshseg, whatever the environment's editable install points at
    os.environ["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))
    for path in paths:
        nb = nbformat.read(path, as_version=4)
        start = time.monotonic()
        NotebookClient(
            nb,
            timeout=600,
            kernel_name="python3",
            record_timing=False,
            resources={"metadata": {"path": str(NOTEBOOKS)}},
        ).execute()
        for cell in nb.cells:  # no timestamps: a re-run on the same results changes nothing but what it shows
            cell.metadata.pop("execution", None)
        nbformat.write(nb, path)
        print(f"{path.relative_to(REPO)}: executed in {time.monotonic() - start:.0f} s")


if __name__ == "__main__":
    main(sys.argv[1:])
