"""A non-editable install carries the FMU sources and builds FMUs from them; the suite's own
configuration (its parallel run) does what it says.

The install builds from a copy of the project in tmp_path: setuptools writes `build/` and
`*.egg-info` next to the sources it builds, and tests never write into the checkout.
"""

from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytest_plugins = ["pytester"]

ROOT = Path(__file__).resolve().parents[1]
# what a build reads
PROJECT = ("pyproject.toml", "README.md", "fmus", "hil", "controllers", "rigbus", "robots")


def copy_project(target: Path) -> Path:
    target.mkdir()
    ignore = shutil.ignore_patterns("__pycache__", "*.egg-info", "build", "*.so", "*.fmu")
    for name in PROJECT:
        source = ROOT / name
        if source.is_dir():
            shutil.copytree(source, target / name, ignore=ignore)
        else:
            shutil.copy2(source, target / name)
    return target


def test_non_editable_install_ships_fmu_sources_and_builds(tmp_path: Path) -> None:
    before = sorted(p.name for p in ROOT.iterdir())
    source = copy_project(tmp_path / "source")
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
            str(source),
        ],
        check=True,
        capture_output=True,
        text=True,
        timeout=240,
        cwd=tmp_path,
    )
    # the build happened in the copy, and left nothing in the checkout
    assert sorted(p.name for p in ROOT.iterdir()) == before
    assert (source / "build").is_dir() or any(source.glob("*.egg-info"))
    for relative in (
        "fmus/common/fmu_glue.c",
        "fmus/common/glue.h",
        "fmus/include/fmi2Functions.h",
        "fmus/DriveCylinder/model.toml",
        "fmus/FeaSegment/model.c",
        "hil/cli/fmu.py",
        "hil/cosim/kernel/kernel.c",
        "rigbus/_ccodec.c",
        "controllers/_cukf.c",
        "robots/planar_arm/scenarios/default.toml",
        "robots/fish/scenarios/fish-escape.toml",
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


def test_tests_sharing_a_module_fixture_run_on_one_xdist_worker(pytester: pytest.Pytester) -> None:
    """The suite's conftest puts every test that uses a module-scoped fixture, directly or
    through another fixture, into its module's xdist group (one worker: the shared run runs
    once); the other tests stay free to spread."""
    spec = importlib.util.spec_from_file_location("suite_conftest", ROOT / "tests" / "conftest.py")
    assert spec is not None and spec.loader is not None
    conftest = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(conftest)
    items = pytester.getitems(
        """
        import pytest

        @pytest.fixture(scope="module")
        def shared_run():
            return 1

        @pytest.fixture
        def reads_the_shared_run(shared_run):
            return shared_run

        @pytest.fixture(scope="session")
        def session_wide():
            return 2

        def test_direct(shared_run): pass
        def test_indirect(reads_the_shared_run, tmp_path): pass
        def test_alone(tmp_path, session_wide): pass
        """
    )
    conftest.pytest_collection_modifyitems(items)
    groups = {item.name: [m.args[0] for m in item.iter_markers("xdist_group")] for item in items}
    module = items[0].nodeid.split("::")[0]
    assert groups == {"test_direct": [module], "test_indirect": [module], "test_alone": []}
