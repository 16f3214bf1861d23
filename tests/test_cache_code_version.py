"""A feature group's cache key covers all the code it runs, not just its own module (issue: editing
`geodesic_balls`, then in `curvature`, kept serving old `pca` values)."""

import inspect

import pytest

from meshseg.features import cache
from meshseg.features.registry import get_group


@pytest.fixture
def edited(monkeypatch):
    """Pretend the source of one module was edited; the code-version memo starts empty."""
    original = inspect.getsource

    def edit(module_name):
        def getsource(obj):
            text = original(obj)
            return text + "\n# edited\n" if getattr(obj, "__name__", "") == module_name else text

        monkeypatch.setattr(cache.inspect, "getsource", getsource)
        cache._code_version.cache_clear()

    yield edit
    cache._code_version.cache_clear()


@pytest.mark.parametrize(
    "group, module",
    [
        ("pca", "meshseg.features.neighbourhoods"),  # geodesic balls
        ("curvature", "meshseg.features.neighbourhoods"),
        ("shape_context", "meshseg.features.agd"),  # sampled geodesics
        ("dms", "meshseg.features.shape_diameter"),  # rays
        ("spin_images", "meshseg.features.shape_diameter"),
        ("pca", "meshseg.features.geometry"),
        ("pca", "meshseg.data.mesh"),  # face areas
        ("hks", "meshseg.features.operators"),  # shared eigenpairs, handed in as `ops`
        ("sihks", "meshseg.features.operators"),
        ("agd", "meshseg.features.operators"),  # shared geodesics
        ("shape_context", "meshseg.features.operators"),
    ],
)
def test_editing_code_a_group_runs_changes_its_version(edited, group, module):
    before = cache.code_version(get_group(group))
    edited(module)
    assert cache.code_version(get_group(group)) != before


@pytest.mark.parametrize(
    "module, groups",
    [
        ("meshseg.features.pca", ("gc", "hks", "curvature")),
        ("meshseg.features.curvature", ("pca",)),  # pca's neighbourhoods are not curvature's code
        ("meshseg.features.operators", ("gc", "pca", "curvature", "cf0", "sdf")),  # groups that share nothing
    ],
)
def test_editing_unrelated_code_keeps_the_version(edited, module, groups):
    before = {g: cache.code_version(get_group(g)) for g in groups}
    edited(module)
    assert {g: cache.code_version(get_group(g)) for g in before} == before


def test_dependencies_are_transitive_and_skip_packages():
    deps = cache.dependencies("meshseg.features.pca")
    assert {
        "meshseg.features.pca",
        "meshseg.features.neighbourhoods",
        "meshseg.features.geometry",
        "meshseg.data.mesh",
    } <= set(deps)
    assert "meshseg.features" not in deps and "meshseg.features.agd" not in deps
    assert "meshseg.features.curvature" not in deps
    # every group module imports the registry: it must not reach the shared operators
    assert "meshseg.features.operators" not in cache.dependencies("meshseg.features.registry")
