"""YAML recipes that chain stages, with caching and resume: ``python -m toolkit.recipe``.

Importing this package stays cheap (no torch, no open3d): stage classes are imported only
when a recipe names them.
"""

from toolkit.recipe.runner import RunResult, run_recipe
from toolkit.recipe.schema import Recipe, RecipeError, StageSpec, load_recipe, parse_recipe
from toolkit.recipe.stage import Stage, StageConfig, StageContext, StageError

__all__ = [
    "Recipe",
    "RecipeError",
    "RunResult",
    "Stage",
    "StageConfig",
    "StageContext",
    "StageError",
    "StageSpec",
    "load_recipe",
    "parse_recipe",
    "run_recipe",
]
