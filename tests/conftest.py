"""Shared fixtures: FMUs built once per session into the user cache."""

from __future__ import annotations

import pytest

from hil.fmu.build import BuiltFmu, build_fmu


@pytest.fixture(scope="session")
def drive_cylinder_fmu() -> BuiltFmu:
    return build_fmu("DriveCylinder")


@pytest.fixture(scope="session")
def fea_segment_fmu() -> BuiltFmu:
    return build_fmu("FeaSegment")
