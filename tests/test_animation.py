"""`hil run --animate` (issue 12): which rows become frames, what a planar-arm frame holds (the
recorded truth: backbone, fingers, objects), that the drawing shows it, the files and the errors.

Most tests animate synthetic signals (no simulation); one runs the CLI on a one-second,
one-segment scenario (the curvature-profile task: the arm animates without a task plan too).
"""

from __future__ import annotations

import errno
import math
import shutil
from pathlib import Path

import matplotlib
import numpy as np
import pytest
from PIL import Image

from controllers import kinematics
from hil import results
from hil.animation import MAX_FPS, MAX_FRAMES, frame_rows, playback_fps
from hil.cli import main as hil_main
from hil.errors import HilError
from hil.results import WriteError
from hil.run import RunOptions, run_scenario
from hil.scenario import load_scenario
from hil.summary import read_signals
from robots.fish.plant.animation import animate_fish
from robots.planar_arm.controller.gripper import GripperGeometry, finger_points
from robots.planar_arm.plant.animation import animate_arm, arm_frame, arm_scene
from robots.planar_arm.plant.rig import ROBOT

SCENARIOS = Path(__file__).parents[1] / "robots" / "planar_arm" / "scenarios"
TINY = """
name = "tiny"
seed = 1
duration = 1.0
[robot]
segments = 1
[task]
steps = [[0.0, 0.0], [0.2, 10.0]]
"""
GREEN = np.array([44, 160, 44])  # tab:green, the fingers
ORANGE = 0.7 * np.array([255, 127, 14]) + 0.3 * 255  # tab:orange at alpha 0.7 on white: objects


def times(duration: float, step: float) -> np.ndarray:
    return np.arange(round(duration / step) + 1) * step


# ---------------------------------------------------------------------- frames


@pytest.mark.parametrize(
    ("duration", "step"),
    [
        (1.0, 0.01),
        (20.0, 0.01),
        (100.0, 0.01),
        (2.0, 0.002),
        (0.05, 0.01),
        (2.0, 1.0),
        (0.0, 0.01),
        (299.0, 1.0),  # 300 rows, the rate no limit: every row
        (300.0, 1.0),  # 301 rows: every other one
    ],
)
def test_frames_are_evenly_spaced_within_the_rate_and_the_count(
    duration: float, step: float
) -> None:
    t = times(duration, step)
    rows = frame_rows(t)
    assert rows[0] == 0 and rows.size <= MAX_FRAMES
    if rows.size < 2:
        assert t.size * step <= 1.0 / MAX_FPS + step  # a single frame only when nothing is longer
        return
    stride = np.unique(np.diff(rows))
    assert stride.size == 1  # evenly spaced
    gap = stride[0] * step
    assert gap >= 1.0 / MAX_FPS - 1e-12  # at most MAX_FPS frames a second of simulated time
    assert rows[-1] > t.size - 1 - stride[0]  # up to the end
    if stride[0] > 1:  # the smallest stride within both limits: one row fewer breaks one of them
        finer = stride[0] - 1
        assert finer * step < 1.0 / MAX_FPS - 1e-12 or (t.size - 1) // finer + 1 > MAX_FRAMES
    assert playback_fps(t, rows) == pytest.approx(1.0 / gap)  # plays at the simulated speed


def test_a_twenty_second_run_has_286_frames_seven_rows_apart() -> None:
    """100 Hz rows, 15 fps: a stride of ceil(6.67) = 7 rows; 2001 rows -> 286 frames (< 300)."""
    rows = frame_rows(times(20.0, 0.01))
    assert rows.size == 286 and rows[1] == 7


def test_the_gif_palette_holds_colours_the_first_frame_lacks() -> None:
    """Frames share the first frame's palette: a colour drawn only later (fingers that close
    once the gripper lands) must be in it too, with its antialiasing blends."""
    from hil.animation import _palette

    palette = _palette(Image.new("RGB", (64, 64), "white"), [tuple(GREEN / 255)])
    later = np.full((4, 4, 3), 255, dtype=np.uint8)
    later[:2] = GREEN
    later[2] = (0.5 * GREEN + 0.5 * 255).round()  # a line's edge blended into white
    shown = Image.fromarray(later).quantize(palette=palette, dither=Image.Dither.NONE)
    assert np.abs(np.asarray(shown.convert("RGB"), dtype=float) - later).max() < 12


# ---------------------------------------------------------------------- the planar arm's frames


@pytest.fixture(scope="module")
def pipe(tmp_path_factory: pytest.TempPathFactory):  # noqa: ANN201 - a Scenario
    """planar-pipe-1 with one disk object in the pipe."""
    text = (SCENARIOS / "planar-pipe-1.toml").read_text()
    text = text.replace(
        "[robot.environment]\n",
        "[robot.environment]\nobjects = [{ x = 0.3, y = 0.0, radius = 0.01 }]\n",
    )
    path = tmp_path_factory.mktemp("pipe") / "pipe.toml"
    path.write_text(text)
    return load_scenario(path)


def arm_signals(duration: float, segments: int = 6, gripper_from: float | None = None) -> dict:
    """Recorded-like columns: curvatures bending and unbending, one object moving along +x
    from 0.28 to 0.33 m, the fingers' bend angle recorded from `gripper_from` on (NaN before)."""
    t = times(duration, 0.01)
    signals: dict[str, np.ndarray] = {"time": t}
    for n in range(1, segments + 1):
        signals[f"kappa_{n}"] = (-1) ** n * 8.0 * np.sin(math.pi * t / max(duration, 1e-9))
    signals["object1_x"] = 0.28 + 0.05 * t / duration
    signals["object1_y"] = np.zeros_like(t)
    if gripper_from is not None:
        signals["gripper_theta"] = np.where(t >= gripper_from, 0.5 * t, np.nan)
    return signals


def test_a_frame_is_the_recorded_truth_at_its_row(pipe) -> None:  # noqa: ANN001
    scene = arm_scene(ROBOT, pipe)
    signals = arm_signals(2.0, gripper_from=1.0)
    row = 150
    frame = arm_frame(scene, signals, row)
    kappas = [signals[f"kappa_{n}"][row] for n in range(1, 7)]
    tip = kinematics.forward(kappas, scene.lengths, scene.base)[-1]
    assert frame.time == signals["time"][row]
    np.testing.assert_allclose(frame.backbone[0], scene.base[:2])
    np.testing.assert_allclose(frame.backbone[-1], tip[:2], atol=1e-12)
    expected = finger_points(GripperGeometry(), tuple(tip), signals["gripper_theta"][row])
    assert len(frame.fingers) == 2
    for got, want in zip(frame.fingers, expected, strict=True):
        np.testing.assert_allclose(got, want)
    assert frame.objects == ((signals["object1_x"][row], 0.0, 0.01),)  # the scenario's radius
    assert arm_frame(scene, signals, 50).fingers == ()  # not yet recorded
    del signals["gripper_theta"]
    assert arm_frame(scene, signals, row).fingers == ()  # no gripper: no fingers


def test_the_scene_takes_the_gripper_and_the_placed_object_from_the_scenario(
    tmp_path: Path,
) -> None:
    text = (SCENARIOS / "planar-grasp.toml").read_text()
    path = tmp_path / "grasp.toml"
    path.write_text(text.replace("[robot.gripper]\n", "[robot.gripper]\nfinger_length = 0.05\n"))
    scenario = load_scenario(path)
    scene = arm_scene(ROBOT, scenario)
    assert scene.gripper.finger_length == 0.05
    assert scene.plan is not None and scene.plan.kind == "grasp"
    assert scene.object_radii == (scene.plan.object_radius,)  # the object the task places
    assert scene.grasp == ROBOT.grasp_layout(scenario)


def colour_mask(image: Image.Image, colour: np.ndarray, tolerance: float = 30.0) -> np.ndarray:
    rgb = np.asarray(image.convert("RGB"), dtype=float)
    return np.linalg.norm(rgb - colour, axis=2) < tolerance


def test_the_gif_shows_each_frame_at_the_simulated_speed(pipe, tmp_path: Path) -> None:  # noqa: ANN001
    """Frames as frame_rows picks them; the object drawn where it was recorded (its pixels move
    right as it does); the fingers drawn exactly while their bend angle is recorded."""
    signals = arm_signals(1.0, gripper_from=0.5)
    path = tmp_path / "arm.gif"
    animate_arm(ROBOT, pipe, signals, path, "gif")
    rows = frame_rows(signals["time"])
    with Image.open(path) as gif:
        assert gif.format == "GIF"
        assert gif.n_frames == rows.size == 15
        assert gif.info["duration"] == 70  # ms: 7 rows of 10 ms
        centroids, fingers = [], []
        for k in range(gif.n_frames):
            gif.seek(k)
            frame = gif.convert("RGB")
            centroids.append(np.argwhere(colour_mask(frame, ORANGE))[:, 1].mean())
            fingers.append(colour_mask(frame, GREEN).sum())
    # the disk's pixels follow its recorded x (the arm passing over it blurs a pixel or so)
    assert np.corrcoef(signals["object1_x"][rows], centroids)[0, 1] > 0.99
    assert centroids[-1] - centroids[0] > 30  # pixels: 5 cm of the ~50 cm wide view
    legend = min(fingers)  # the legend's green line: in every frame
    recorded = signals["time"][rows] >= 0.5
    assert all(f > legend + 50 for f, r in zip(fingers, recorded, strict=True) if r)
    assert all(f == legend for f, r in zip(fingers, recorded, strict=True) if not r)


@pytest.mark.skipif(shutil.which("ffmpeg") is None, reason="ffmpeg is not on PATH")
def test_mp4_through_ffmpeg(pipe, tmp_path: Path) -> None:  # noqa: ANN001
    path = tmp_path / "arm.mp4"
    animate_arm(ROBOT, pipe, arm_signals(0.5), path, "mp4")
    assert path.read_bytes()[4:8] == b"ftyp"  # an ISO media file


def test_the_fish_animates_its_recorded_outline(tmp_path: Path) -> None:
    t = times(1.0, 0.002)
    signals: dict[str, np.ndarray] = {"time": t, "x": 0.1 * t, "y": np.zeros_like(t)}
    for name, offset in (("nose", 0.14), ("tail_1", -0.08), ("tail_2", -0.16), ("tail_3", -0.24)):
        signals[f"{name}_x"], signals[f"{name}_y"] = 0.1 * t + offset, 0.01 * np.sin(t)
    animate_fish("fish", signals, tmp_path / "fish.gif", "gif")
    with Image.open(tmp_path / "fish.gif") as gif:
        assert gif.n_frames == frame_rows(t).size == 15


def test_a_full_disk_leaves_no_animation_behind(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def full(fd: int, data: bytes) -> int:
        raise OSError(errno.ENOSPC, "No space left on device")

    t = times(0.2, 0.01)
    signals = {"time": t, "x": t, "y": t}
    for name in ("nose", "tail_1", "tail_2", "tail_3"):
        signals[f"{name}_x"], signals[f"{name}_y"] = t, t
    monkeypatch.setattr(results, "write_bytes", full)
    with pytest.raises(WriteError, match="fish.gif: cannot write: No space left"):
        animate_fish("fish", signals, tmp_path / "fish.gif", "gif")
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------------- the command


@pytest.mark.parametrize("reports", [True, False])
def test_hil_run_animate_writes_arm_gif_and_lists_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], reports: bool
) -> None:
    """--animate draws arm.gif, with the plots or, asked for by name, with --no-reports alone."""
    scenario = tmp_path / "tiny.toml"
    scenario.write_text(TINY)
    out = tmp_path / "run"
    # can.csv: no estimation report, which this test does not need (a second saved)
    argv = ["run", str(scenario), "--inprocess", "--no-progress", "--out", str(out)]
    argv += [] if reports else ["--no-reports"]
    assert hil_main([*argv, "--can-log", "can.csv", "--animate"]) == 0
    listed = (
        "can.csv, *.png, arm.gif, summary.json" if reports else "can.csv, arm.gif, summary.json"
    )
    assert listed in capsys.readouterr().out
    assert bool(list(out.glob("*.png"))) is reports
    assert "arm.gif" in (out / ".softhil-manifest").read_text().split()
    assert '"animation": "arm.gif"' in (out / "summary.json").read_text()
    rows = frame_rows(read_signals(out / "signals.csv")["time"])
    with Image.open(out / "arm.gif") as gif:
        assert gif.format == "GIF" and gif.n_frames == rows.size > 1
    assert matplotlib.get_backend().lower() == "agg"


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["{tiny}", "--animate", "avi"], "--animate: unknown format 'avi' (known: gif, mp4)"),
        (["--animate", "planar-path"], "a scenario goes before it: hil run NAME --animate"),
    ],
)
def test_an_unknown_format_is_a_one_line_error_before_anything_runs(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str], message: str
) -> None:
    scenario = tmp_path / "tiny.toml"
    scenario.write_text(TINY)
    out = tmp_path / "never"
    argv = [a.format(tiny=scenario) for a in argv]
    assert hil_main(["run", *argv, "--out", str(out), "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("hil: error: --animate") and message in err
    assert not out.exists()


def test_mp4_without_ffmpeg_is_a_one_line_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(matplotlib.rcParams, "animation.ffmpeg_path", str(tmp_path / "no-ffmpeg"))
    scenario = tmp_path / "tiny.toml"
    scenario.write_text(TINY)
    out = tmp_path / "never"
    assert hil_main(["run", str(scenario), "--animate", "mp4", "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert err == "hil: error: --animate mp4: ffmpeg is not on PATH; install it, or use gif\n"
    assert not out.exists()


def test_a_robot_without_an_animation_says_so_before_the_run(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    build = type(ROBOT).build

    def without_animation(self, scenario):  # noqa: ANN001, ANN202
        rig = build(self, scenario)
        rig.animation = None
        return rig

    monkeypatch.setattr(type(ROBOT), "build", without_animation)
    scenario = tmp_path / "tiny.toml"
    scenario.write_text(TINY)
    options = RunOptions(out=tmp_path / "run", inprocess=True, progress=False, animate="gif")
    with pytest.raises(HilError, match="^--animate: robot kind 'planar_arm' has no animation$"):
        run_scenario(load_scenario(scenario), options)
    assert not (tmp_path / "run" / "signals.csv").exists()  # the run never started
