"""Dataset roots given as archives: unpacked once into a cache folder, atomically."""

from __future__ import annotations

import hashlib
import lzma
import os
import shutil
import tarfile
import tempfile
import time
import zipfile
import zlib
from pathlib import Path

from meshseg.data.mesh import MeshDataError

ARCHIVE_SUFFIXES = (".tar.xz", ".tar.gz", ".tgz", ".tar.bz2", ".tar", ".zip")


def is_archive(path: Path) -> bool:
    return path.is_file() and path.name.lower().endswith(ARCHIVE_SUFFIXES)


def file_sha256(path: Path, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
    return h.hexdigest()


def remove_stale_partials(cache: Path, max_age_s: float = 6 * 3600) -> list[Path]:
    """Delete the half-unpacked folders that killed unpacks left in `cache`: those whose process (its
    pid is in the name) is gone, and unnamed ones older than `max_age_s`. Returns what was removed."""
    removed = []
    for d in cache.glob(".*.partial-*"):
        owner = d.name.rpartition(".partial-")[2].split("-")[0]
        if owner.isdigit():
            try:
                os.kill(int(owner), 0)
                continue  # an unpack still running
            except ProcessLookupError:
                pass
            except PermissionError:
                continue
        elif time.time() - d.stat().st_mtime < max_age_s:
            continue
        shutil.rmtree(d, ignore_errors=True)
        removed.append(d)
    return removed


def resolve_root(root: str | os.PathLike, cache_dir: str | os.PathLike, setting: str = "dataset.root") -> Path:
    """A folder for `root`: itself if a folder, else the archive unpacked under `cache_dir`; an error names
    the `setting` the path came from (a dataset's root, a report column's predictions.path).

    The archive is extracted into a temporary sibling and renamed into place only when complete,
    so a killed unpack leaves nothing that a later call would trust. The folder name carries the
    archive's content hash: a changed archive is unpacked afresh.
    """
    root = Path(root).expanduser()
    if root.is_dir():
        return root
    if not root.exists():
        raise MeshDataError(root, f"{setting} does not exist (give a folder or an archive with {setting}=PATH)")
    if not is_archive(root):
        raise MeshDataError(root, f"{setting} is neither a folder nor an archive ({', '.join(ARCHIVE_SUFFIXES)})")
    cache = Path(cache_dir).expanduser()
    cache.mkdir(parents=True, exist_ok=True)
    stem = root.name[: -len(next(s for s in ARCHIVE_SUFFIXES if root.name.lower().endswith(s)))]
    final = cache / f"{stem}-{file_sha256(root)[:16]}"
    if final.is_dir():
        return final
    remove_stale_partials(cache)
    tmp = Path(tempfile.mkdtemp(dir=cache, prefix=f".{final.name}.partial-{os.getpid()}-"))
    try:
        try:
            if root.name.lower().endswith(".zip"):
                with zipfile.ZipFile(root) as z:
                    z.extractall(tmp)
            else:
                with tarfile.open(root) as t:
                    t.extractall(tmp, filter="data")  # refuses absolute paths and '..'
        except (tarfile.TarError, zipfile.BadZipFile, EOFError, OSError, ValueError, lzma.LZMAError, zlib.error) as e:
            raise MeshDataError(root, f"cannot unpack archive (corrupt or truncated?): {e}") from None
        try:
            os.rename(tmp, final)
        except OSError:
            if not final.is_dir():  # not a concurrent unpack that finished first
                raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return final
