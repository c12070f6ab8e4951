"""Where the package's data lives, installed (colcon / pip) or in a source checkout."""

from __future__ import annotations

import sys
from pathlib import Path

PACKAGE = "vehicle_estimation"
_SOURCE_ROOT = Path(__file__).resolve().parent.parent
MODELS_DIR = Path(__file__).resolve().parent / "models"   # shipped weights (package data)


def params_dir() -> Path:
    """``share/vehicle_estimation/params`` of the install, else ``params/`` of the checkout."""
    candidates = []
    try:  # a sourced ROS 2 workspace
        from ament_index_python.packages import get_package_share_directory
        candidates.append(Path(get_package_share_directory(PACKAGE)) / "params")
    except Exception:  # not installed through ament, or no AMENT_PREFIX_PATH
        pass
    candidates += [_SOURCE_ROOT / "params", Path(sys.prefix) / "share" / PACKAGE / "params"]
    for candidate in candidates:
        if (candidate / "estimation.yaml").is_file():
            return candidate
    raise FileNotFoundError(f"cannot find the {PACKAGE} params directory (looked in {candidates})")


def shared_data_dir(name: str) -> Path:
    """``../shared/data/<name>`` beside the source checkout: the measured data sets the
    project works with (each with its README) live there, not in the repository."""
    return _SOURCE_ROOT.parent / "shared" / "data" / name


def params_file(name_or_path: str | Path) -> Path:
    """A params file by path, or by name (``sedan_d_class`` or ``sedan_d_class.yaml``)."""
    path = Path(name_or_path)
    if path.is_file():
        return path
    name = path.name if path.suffix == ".yaml" else f"{path.name}.yaml"
    candidate = params_dir() / name
    if candidate.is_file():
        return candidate
    raise FileNotFoundError(f"no params file '{name_or_path}' (not a file, not in {params_dir()})")
