"""``python -m toolkit.recipe run|validate|list``."""

from toolkit.recipe.cli import main

if __name__ == "__main__":
    raise SystemExit(main())
