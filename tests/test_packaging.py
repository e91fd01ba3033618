"""A non-editable install carries the FMU sources and builds FMUs from them."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_non_editable_install_ships_fmu_sources_and_builds(tmp_path: Path) -> None:
    target = tmp_path / "site"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "install",
            "--quiet",
            "--no-deps",
            "--no-build-isolation",
            "--target",
            str(target),
            str(ROOT),
        ],
        check=True,
        capture_output=True,
        text=True,
        timeout=240,
    )
    for relative in (
        "fmus/common/fmu_glue.c",
        "fmus/common/glue.h",
        "fmus/include/fmi2Functions.h",
        "fmus/DriveCylinder/model.toml",
        "fmus/FeaSegment/model.c",
        "hil/cli/fmu.py",
        "hil/kernel/kernel.c",
    ):
        assert (target / relative).is_file(), relative
    env = {**os.environ, "PYTHONPATH": str(target), "SOFTHIL_CACHE_DIR": str(tmp_path / "cache")}
    script = (
        "import fmus; from hil.fmu.build import build_fmu; "
        "b = build_fmu('FeaSegment'); print(fmus.source_root()); print(b.path)"
    )
    result = subprocess.run(
        [sys.executable, "-c", script],
        env=env,
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    source_root, fmu_path = result.stdout.split()
    assert Path(source_root) == target / "fmus"
    assert Path(fmu_path).is_file() and Path(fmu_path).is_relative_to(tmp_path / "cache")
