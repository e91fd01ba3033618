"""Shared fixtures: FMUs built once per session into the user cache; the checkout untouched.

The suite runs on every core with pytest-xdist (`-n auto --dist loadgroup`, pyproject.toml).
Invariant: an expensive run shared by a module-scoped fixture runs once per session, as it
does serially: every test using a module-scoped fixture joins its module's xdist group, so
they all land on one worker; the other tests are spread one by one.
"""

from __future__ import annotations

import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

from hil.fmu.build import BuiltFmu, build_fmu

ROOT = Path(__file__).resolve().parents[1]
CACHES = ("__pycache__", ".pytest_cache", ".ruff_cache", ".mypy_cache")


@pytest.hookimpl(tryfirst=True)  # before xdist's own hook reads the groups into node ids
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Tests sharing a module-scoped fixture join their module's xdist group (see above)."""
    for item in items:
        info = getattr(item, "_fixtureinfo", None)
        if info is None:
            continue
        if any(defs[-1].scope == "module" for defs in info.name2fixturedefs.values() if defs):
            item.add_marker(pytest.mark.xdist_group(item.nodeid.split("::")[0]))


@pytest.fixture(scope="session")
def drive_cylinder_fmu() -> BuiltFmu:
    return build_fmu("DriveCylinder")


@pytest.fixture(scope="session")
def fea_segment_fmu() -> BuiltFmu:
    return build_fmu("FeaSegment")


def checkout_status() -> list[str] | None:
    """`git status` of the checkout, ignored files included and caches aside; None outside a
    git checkout."""
    git = shutil.which("git")
    if git is None or not (ROOT / ".git").exists():
        return None
    result = subprocess.run(
        [git, "status", "--porcelain", "--ignored", "--untracked-files=all"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    if result.returncode != 0:
        return None
    return [line for line in result.stdout.splitlines() if not any(c in line for c in CACHES)]


@pytest.fixture(scope="session", autouse=True)
def checkout_stays_clean() -> Iterator[None]:
    """Tests never write into the checkout: its status is the same after the
    session as before it."""
    before = checkout_status()
    yield
    after = checkout_status()
    if before is not None and after is not None:
        added = sorted(set(after) - set(before))
        assert not added, f"the test session wrote into the checkout: {added}"
