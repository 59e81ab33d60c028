"""``python -m toolkit.recipe run|validate|list``."""

import os

# OpenMP threads that spin while waiting steal the cores from each other on a busy
# 2-core laptop (measured 10x slower splat training); must be set before torch loads.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from toolkit.recipe.cli import main  # noqa: E402

if __name__ == "__main__":
    raise SystemExit(main())
