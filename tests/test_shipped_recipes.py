"""Every recipe shipped in recipes/ reads: its stages, their settings and where each takes
its inputs from (a renamed key or stage id breaks here, not in a user's run)."""

from pathlib import Path

import pytest

from toolkit.recipe.schema import load_recipe

RECIPES = sorted((Path(__file__).parents[1] / "recipes").glob("*.yaml"))


def test_the_recipes_folder_is_found() -> None:
    assert {"quickstart.yaml", "paper_benchmark.yaml", "bench_exposure.yaml"} <= {
        p.name for p in RECIPES}


@pytest.mark.parametrize("path", RECIPES, ids=[p.stem for p in RECIPES])
def test_shipped_recipe_loads(path: Path) -> None:
    recipe = load_recipe(path)
    assert recipe.stages and len({s.id for s in recipe.stages}) == len(recipe.stages)
