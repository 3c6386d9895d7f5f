"""Where the shipped data files (``config/``: EDS files, model files, example configs) are found.

In a source checkout or an editable install they are the repository's ``config/`` directory. A
wheel installs the same files under ``<prefix>/share/stagectl/config`` (see ``pyproject.toml``).
"""

from __future__ import annotations

import sys
from pathlib import Path


def config_dir() -> Path:
    """The directory holding ``eds/``, ``models/`` and the shipped YAML files."""
    repo = Path(__file__).resolve().parents[1] / "config"
    if (repo / "eds").is_dir():
        return repo
    return Path(sys.prefix) / "share" / "stagectl" / "config"


#: directory of the EDS files written for stagectl
EDS_DIR = config_dir() / "eds"
