"""What the study files share (manifests, claims files, figures files): one problem of a file's content
(`Invalid`; the file's loader adds the file's name), a key outside a file's schema refused by name (`known`),
and which kind of file a YAML file is (`holds_key`)."""

from __future__ import annotations

from pathlib import Path

import yaml


class Invalid(Exception):
    """One problem of a study file's content; its loader adds the file's name."""


def known(value: dict, keys: tuple[str, ...], where: str, what: str) -> None:
    """Refuse a key outside the schema, naming the known ones: a typo would otherwise be dropped without a word
    (a column's `overide:` makes it a published-only column, its runs neither counted nor launched)."""
    unknown = [str(k) for k in value if k not in keys]
    if unknown:
        raise Invalid(f"{where}unknown key {unknown[0]!r}: {what} takes {', '.join(keys)}")


def holds_key(path, key: str) -> bool:
    """Whether a YAML file is a mapping with `key` (a claims or figures file rather than a study manifest); an
    unreadable one is not (its own loader says what is wrong with it)."""
    try:
        doc = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return False
    return isinstance(doc, dict) and key in doc
