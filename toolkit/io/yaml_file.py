"""Reading a user's YAML file with errors that name it."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml


def load_yaml(path: Path | str, error: type[Exception] = ValueError,
              not_found: str = "file not found",
              missing_error: type[Exception] | None = None) -> Any:
    """The document in ``path``. A missing file raises ``missing_error`` (default
    ``error``) with ``not_found``, a YAML syntax error ``error``; both name the file."""
    path = Path(path)
    if not path.exists():
        raise (missing_error or error)(f"{path}: {not_found}")
    if path.is_dir():
        raise error(f"{path}: is a folder; give the YAML file in it")
    try:
        return yaml.safe_load(path.read_text(encoding="utf-8-sig"))
    except yaml.YAMLError as e:
        raise error(f"{path}: not valid YAML: {e}") from None
    except (OSError, UnicodeDecodeError) as e:
        raise error(f"{path}: cannot be read as YAML text: {e}") from None
