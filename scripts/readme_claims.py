"""Copy the claims table of reports/claims/claims.md into README.md between its claims markers.

    python -m meshseg.report experiments/claims.yaml && python scripts/readme_claims.py

tests/test_claims.py holds the README's table equal to reports/claims/claims.csv.
"""

import re
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def main() -> None:
    md = (REPO / "reports/claims/claims.md").read_text()
    table = re.search(r"^\| # \| claim.*?(?=\n\n)", md, re.S | re.M)
    readme = REPO / "README.md"
    text = readme.read_text()
    new, n = re.subn(
        r"(<!-- claims:begin -->\n).*?(<!-- claims:end -->)", lambda m: m[1] + table[0] + "\n" + m[2], text, flags=re.S
    )
    if not table or n != 1:
        sys.exit("error: README.md has no claims markers, or claims.md no claims table")
    readme.write_text(new)


if __name__ == "__main__":
    main()
