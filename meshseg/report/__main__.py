"""`python -m meshseg.report MANIFEST [overrides]`: see meshseg/report/app.py and conf/report.yaml."""

from meshseg.report.app import main

if __name__ == "__main__":
    main()
