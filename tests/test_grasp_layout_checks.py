"""A grasp scenario's given layout and gripper are checked before the run, one line naming the key:
an object started overlapping the arm's start pose (backbone from the base, fingers), another
object, or a place on the base (the contact would push it out with the overlap's energy: a pick
in the arm once left at 700 m/s), and finger bend angles the finger pair cannot reach (they
were a traceback from the controller's configuration)."""

from __future__ import annotations

from pathlib import Path

import pytest

from hil.errors import ScenarioError
from hil.scenario import load_scenario, resolve_scenario

GRASP = resolve_scenario("planar-grasp").read_text()
OBJECT = "objects = [{ radius = 0.0125, mass = 0.005, height = 0.05 }]"
# seed 1's drawn layout: clear of the arm, reachable
PICK, PLACE = (0.246, 0.1496), (-0.0997, 0.345)


def scenario_text(
    pick: tuple[float, float] = PICK,
    place: tuple[float, float] = PLACE,
    extra_object: str = "",
    gripper: str = "",
) -> str:
    text = GRASP.replace(OBJECT, OBJECT[:-1] + extra_object + "]")
    text = text.replace("[robot.gripper]\n", f"[robot.gripper]\n{gripper}")
    return text + f"pick = [{pick[0]}, {pick[1]}]\nplace = [{place[0]}, {place[1]}]\n"


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "s.toml"
    path.write_text(text)
    return path


def test_a_given_layout_clear_of_the_arm_loads(tmp_path: Path) -> None:
    load_scenario(write(tmp_path, scenario_text()))


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (  # on the straight arm's backbone, 50 mm from the base (the audit's case)
            scenario_text(pick=(0.0, 0.05)),
            r"task\.pick: an object of radius 0\.0125 m at \(0, 0\.05\) m overlaps the arm's "
            r"start pose by 22\.5 mm",
        ),
        (  # behind the base
            scenario_text(pick=(0.0, -0.015)),
            r"task\.pick: .* overlaps the arm's start pose by 7\.5 mm",
        ),
        (  # clear of the backbone (36 mm from the tip), on the right finger
            scenario_text(pick=(0.03, 0.38)),
            r"task\.pick: .* overlaps the fingers at their start",
        ),
        (
            scenario_text(extra_object=", { x = 0.25, y = 0.16, radius = 0.01 }"),
            r"robot\.environment\.objects\[1\]: an object at \(0\.25, 0\.16\) m overlaps "
            r"task\.pick by",
        ),
        (
            scenario_text(extra_object=", { x = 0.0, y = 0.2, radius = 0.01 }"),
            r"robot\.environment\.objects\[1\]: .* overlaps the arm's start pose",
        ),
        (
            scenario_text(place=(0.0, 0.0)),
            r"task\.place: \(0, 0\) m overlaps the arm's base by 22\.5 mm",
        ),
        (
            scenario_text(extra_object=", { x = -0.1, y = 0.35, radius = 0.01 }"),
            r"task\.place: .* overlaps robot\.environment\.objects\[1\]",
        ),
    ],
    ids=[
        "on-the-arm",
        "behind-the-base",
        "on-a-finger",
        "on-the-pick",
        "other-on-the-arm",
        "place-on-the-base",
        "place-on-another",
    ],
)
def test_an_object_started_in_the_arm_or_another_object_is_refused(
    tmp_path: Path, text: str, message: str
) -> None:
    with pytest.raises(ScenarioError, match=message) as caught:
        load_scenario(write(tmp_path, text))
    assert "\n" not in str(caught.value)


@pytest.mark.parametrize(
    ("line", "key", "value"),
    [
        ("theta_closed = 5.0\n", "theta_closed", "5"),
        ("theta_closed = 1.7\n", "theta_closed", "1.7"),
        ("theta_open = -1.5\n", "theta_open", "-1.5"),
    ],
)
def test_finger_bends_beyond_the_reachable_range_are_refused(
    tmp_path: Path, line: str, key: str, value: str
) -> None:
    text = GRASP.replace("theta_closed = 1.35", "# theta_closed").replace(
        "[robot.gripper]\n", f"[robot.gripper]\n{line}"
    )
    pattern = (
        rf"robot\.gripper\.{key}: {value} rad is outside the fingers' reachable bend "
        r"\[-1\.4, 1\.4\] rad"
    )
    with pytest.raises(ScenarioError, match=pattern):
        load_scenario(write(tmp_path, text))


def test_hil_run_says_so_in_one_line_without_a_traceback(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from hil.cli import main

    path = write(tmp_path, GRASP.replace("theta_closed = 1.35", "theta_closed = 1.7"))
    assert main(["run", str(path), "--out", str(tmp_path / "run"), "--no-progress"]) != 0
    out, err = capsys.readouterr()
    assert "Traceback" not in out + err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "robot.gripper.theta_closed: 1.7 rad is outside" in lines[0], err
    assert not (tmp_path / "run" / "signals.csv").exists()  # refused before the run


@pytest.mark.parametrize(
    ("old", "new", "reason"),
    [
        (  # an arm 0.5 m wide in a 50 mm pipe (it started 233 mm into the walls)
            "[robot.environment]",
            "[robot.environment]\nwidth = 0.5",
            r"robot\.environment\.walls\[0\]: the arm's start pose overlaps the wall by 232\.8 mm",
        ),
        (  # bent back through the bay's wall
            "theta_start = [0.948, 0, -0.948, -0.948, 0, 0.948]",
            "theta_start = [1.2, 1.2, 0.0, 0.0, 0.0, 0.0]",
            r"robot\.environment\.walls\[0\]: the arm's start pose overlaps the wall by 7\.9 mm",
        ),
    ],
)
def test_an_arm_started_in_a_wall_is_refused_naming_the_wall(
    tmp_path: Path, old: str, new: str, reason: str
) -> None:
    """The walls' penalty would have thrown the arm out of them at the first step."""
    text = resolve_scenario("planar-pipe-1").read_text()
    assert old in text
    load_scenario(write(tmp_path, text))  # the shipped start: clear
    with pytest.raises(ScenarioError, match=reason + r" at \(.*\) m: start the arm clear"):
        load_scenario(write(tmp_path, text.replace(old, new, 1)))
