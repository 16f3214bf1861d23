"""The README and docs/ name only what exists: links resolve, and every command module, make target, file and
config option they name is there. The commands a test can afford to run are run elsewhere
(tests/test_adding_a_method.py, tests/test_cli.py, tests/test_report.py); this keeps the rest from going stale."""

import re
from pathlib import Path

import pytest
from conftest import REPO

PAGES = [REPO / "README.md", REPO / "experiments/README.md", *sorted((REPO / "docs").glob("*.md"))]
TOP = "conf|meshseg|experiments|benchmarks|scripts|tests|notebooks|reports|results|docs|hydra_plugins"
GROUPS = ("dataset", "features", "model", "split", "refine", "budget", "trainer")


def text(page: Path) -> str:
    return page.read_text()


def names(pattern: str) -> list[tuple[str, str]]:
    """(page, match) for every match of `pattern` (its groups) in every page; ^ matches at each line."""
    return [(p.relative_to(REPO).as_posix(), m) for p in PAGES for m in re.findall(pattern, text(p), re.M)]


def test_every_relative_link_resolves():
    broken = []
    for page in PAGES:
        for target in re.findall(r"\]\(([^)\s]+)\)", text(page)):
            if re.match(r"[a-z]+:|#", target):
                continue
            if not (page.parent / target.split("#")[0]).exists():
                broken.append(f"{page.relative_to(REPO)}: {target}")
    assert not broken


def test_every_command_module_exists():
    found = names(r"python -m (meshseg(?:\.\w+)+)")
    assert {"meshseg.run", "meshseg.report", "meshseg.reproduce", "meshseg.predict"} <= {m for _, m in found}
    missing = [
        (page, module)
        for page, module in found
        if not (REPO / (module.replace(".", "/") + ".py")).is_file()
        and not (REPO / module.replace(".", "/") / "__main__.py").is_file()
    ]
    assert not missing


def test_every_make_target_exists():
    makefile = (REPO / "Makefile").read_text()
    targets = set(re.findall(r"^([\w-]+):", makefile, re.M))
    found = names(r"(?:`|^)make ([a-z][\w-]*)")
    assert {"demo", "test", "ui"} <= {t for _, t in found}
    assert not [(page, t) for page, t in found if t not in targets]


def test_every_repository_path_named_exists():
    """Paths such as `conf/model/cnn2d.yaml` or `python benchmarks/fold_time.py` (of a template such as
    reports/<manifest>/table.md, its fixed start)."""
    found = names(rf"(?<![\w./-])((?:{TOP})/[\w./-]*[\w/])")
    assert len(found) > 100
    missing = [(page, path) for page, path in found if not (REPO / path).exists()]
    assert not missing


def test_every_config_option_named_exists():
    """`model=pca_nn`, `budget=smoke`, ... name a file of conf/<group>/; the worked example's own models and
    the budget study's hypothetical `cpu2` are the exceptions."""
    own = set(re.findall(r"my_conf/model/(\w+)\.yaml", text(REPO / "docs/adding-a-method.md")))
    assert own == {"mlp", "nearest_mean"}
    found = names(rf"(?<![\w.]){'(' + '|'.join(GROUPS) + ')'}=([\w,]+)")
    missing = [
        (page, f"{group}={option}")
        for page, (group, options) in found
        for option in options.split(",")
        if option and option not in own | {"cpu2"} and not (REPO / "conf" / group / f"{option}.yaml").is_file()
    ]
    assert not missing


@pytest.mark.parametrize("manifest", sorted(p.stem for p in (REPO / "experiments").glob("*.yaml")))
def test_the_readme_has_one_command_per_manifest(manifest):
    command = "report" if manifest in ("claims", "figures") else "reproduce"
    assert f"python -m meshseg.{command} experiments/{manifest}.yaml" in text(REPO / "README.md")
