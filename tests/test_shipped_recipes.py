"""Every recipe shipped in recipes/ reads: its stages, their settings and where each takes
its inputs from (a renamed key or stage id breaks here, not in a user's run)."""

from pathlib import Path

import pytest

from toolkit.recipe.schema import RecipeError, load_recipe

RECIPES = sorted((Path(__file__).parents[1] / "recipes").glob("*.yaml"))


def test_the_recipes_folder_is_found() -> None:
    assert {"quickstart.yaml", "paper_benchmark.yaml", "bench_exposure.yaml"} <= {
        p.name for p in RECIPES}


@pytest.mark.parametrize("path", RECIPES, ids=[p.stem for p in RECIPES])
def test_shipped_recipe_loads(path: Path) -> None:
    recipe = load_recipe(path)
    assert recipe.stages and len({s.id for s in recipe.stages}) == len(recipe.stages)


def test_the_set_example_in_the_error_is_a_setting_of_the_quickstart() -> None:
    # The message for a malformed --set shows an example; followed as written it must
    # work, not stop at "unknown key" (it named slam2d.window_m, which slam2d lacks).
    quickstart = next(p for p in RECIPES if p.name == "quickstart.yaml")
    with pytest.raises(RecipeError, match="expected KEY=VALUE") as err:
        load_recipe(quickstart, ["slam2d.use_odometry"])
    example = str(err.value).rsplit("e.g. ", 1)[1].split()[0]
    load_recipe(quickstart, [example])
