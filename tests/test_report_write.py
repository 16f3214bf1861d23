"""Writing a report folder: two writers of one folder neither collide nor mix (issue 48, 3)."""

from __future__ import annotations

import multiprocessing as mp

from meshseg.report.write import write_files


def _writer(out, tag: str, rounds: int) -> None:
    for i in range(rounds):
        # each round's files carry the writer and the round: a folder mixed from two writes shows it
        write_files(out, {"table.md": f"{tag} {i}\n" * 200, "table.csv": f"{tag} {i}\n"}, stale=["paired.csv"])


def test_two_writers_of_one_folder_never_collide_and_the_folder_is_one_writes(tmp_path):
    (tmp_path / "paired.csv").write_text("stale\n")
    ctx = mp.get_context("fork")
    procs = [ctx.Process(target=_writer, args=(tmp_path, tag, 300)) for tag in ("A", "B")]
    for p in procs:
        p.start()
    for p in procs:
        p.join(120)
    assert [p.exitcode for p in procs] == [0, 0]  # a collision was a FileNotFoundError in one of them
    md, csv = (tmp_path / "table.md").read_text(), (tmp_path / "table.csv").read_text()
    assert md == csv * 200 and csv in ("A 299\n", "B 299\n")  # both files from the same, last, write
    assert not (tmp_path / "paired.csv").exists()
    assert [f.name for f in tmp_path.iterdir() if f.suffix == ".tmp"] == []


def test_a_failed_write_leaves_no_temporary_file_and_the_old_file_whole(tmp_path):
    write_files(tmp_path, {"table.md": "old\n"})

    class Boom:  # not bytes and no .encode(): fails after the temporary file exists
        pass

    try:
        write_files(tmp_path, {"table.md": Boom()})
    except AttributeError:
        pass
    assert (tmp_path / "table.md").read_text() == "old\n"
    assert [f.name for f in tmp_path.iterdir() if f.suffix == ".tmp"] == []


def test_two_average_rows_of_one_label_are_logged_under_their_groups_and_a_lone_one_plainly():
    """Table 3 prints `Average` under each of its groups: as metrics, neither may overwrite the other."""
    from meshseg.report.cells import Cell, Row
    from meshseg.report.manifest import Column
    from meshseg.report.publish import summary_metrics

    col, published = Column("3B", "1D CNN 3B", ("branches=3",)), Column("PFCN", "ShapePFCN", None)
    rows = [
        Row("Cup", "set", "small", (Cell(col, None, 90.0), Cell(published, 91.0))),
        Row("Average", "average", "small", (Cell(col, None, 90.0), Cell(published, 91.0))),
        Row("Lamp", "set", "large", (Cell(col, None, 80.0, missing=(1,)), Cell(published, 81.0))),
        Row("Average", "average", "large", (Cell(col, None, 70.0), Cell(published, 71.0))),
        Row("All", "total", "", (Cell(col, None, 75.0), Cell(published, None))),
    ]
    assert summary_metrics(rows) == {  # the published column: not a cell of the runs, no value
        "cells_ok": 4,
        "cells_incomplete": 1,
        "cells_unavailable": 0,
        "small.Average.3B": 90.0,
        "large.Average.3B": 70.0,
        "All.3B": 75.0,
    }
