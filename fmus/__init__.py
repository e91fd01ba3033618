"""C sources of every softhil FMU, shipped as package data.

`fmus/common` holds the FMI 2.0 co-simulation glue written once, `fmus/include` the FMI 2.0
headers, and each other folder one model: `model.toml` (its variables, declared once) and
`model.c` (its physics). `hil.fmu.build` turns a folder into a `.fmu`.
"""

from importlib.resources import files
from pathlib import Path


def source_root() -> Path:
    """Folder holding `common/`, `include/` and one folder per model."""
    return Path(str(files(__name__)))


def model_names() -> list[str]:
    """Names of the models whose sources ship with this installation, sorted."""
    root = source_root()
    return sorted(p.name for p in root.iterdir() if (p / "model.toml").is_file())
