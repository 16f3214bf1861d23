"""`python -m meshseg.report MANIFEST [overrides]`: see meshseg/report/__init__.py and conf/report.yaml."""

import logging
import sys

from meshseg.data.mesh import MeshDataError
from meshseg.report import report, summary


def main(argv: list[str]) -> int:
    if not argv or argv[0] in ("-h", "--help"):
        print(__doc__.strip() + "\n\nexample: python -m meshseg.report experiments/table2_psb_5fold.yaml budget=cpu report.sets=[Teddy]")
        return 0 if argv else 2
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        table, files, run_id = report(argv[0], argv[1:])
    except (MeshDataError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(summary(table, files, run_id))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
