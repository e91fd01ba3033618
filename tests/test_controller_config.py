"""Reading a controller configuration (controllers.config.read_config, what the controller
program does with its controller.json): every value is checked against its field's type, and a
wrong one is a ValueError naming the key, nested keys and list elements by their path; JSON's
true and false are not numbers, a list must have as many elements as its tuple, a number must be
finite, an optional may be null."""

from __future__ import annotations

import json
from typing import Any

import pytest

from controllers.config import read_config
from hil.run import controller_config
from hil.scenario import load_scenario, resolve_scenario


def config_data(scenario: str) -> dict[str, Any]:
    """The controller.json of a shipped scenario, as data."""
    data: dict[str, Any] = json.loads(
        controller_config(load_scenario(resolve_scenario(scenario))).to_json()
    )
    return data


def fish() -> dict[str, Any]:
    return config_data("fish-escape")


def test_a_written_configuration_reads_back_equal() -> None:
    for scenario in ("fish-escape", "default", "planar-grasp"):
        config = controller_config(load_scenario(resolve_scenario(scenario)))
        assert read_config(config.to_json()) == config


@pytest.mark.parametrize(
    ("key", "value", "message"),
    [
        ("cycles", True, "cycles: must be an integer, got True"),
        ("cycles", 1.5, "cycles: must be an integer, got 1.5"),
        ("duty", True, "duty: must be a number, got True"),
        ("duty", "0.1", "duty: must be a number, got '0.1'"),
        ("duty", 10**400, "duty: must be finite, got 1000"),
        ("task", 3, "task: must be a string, got 3"),
        ("calibration", "none", "calibration: must be a list, got 'none'"),
        ("calibration", [[0.0, 0.0], [0.1]], "calibration[1]: must have 2 elements"),
        ("calibration", [[0.0, 0.0], [0.1, 1.0, 2.0]], "calibration[1]: must have 2 elements"),
        (
            "calibration",
            [[0.0, 0.0], [0.1, False]],
            "calibration[1][1]: must be a number, got False",
        ),
        ("camera_timing", 6, "camera_timing: must be an object"),
        ("colour", "red", "colour: unknown key"),
    ],
)
def test_a_wrong_value_is_a_value_error_naming_its_key(key: str, value: Any, message: str) -> None:
    data = fish() | {key: value}
    with pytest.raises(ValueError) as error:
        read_config(json.dumps(data))
    assert str(error.value).startswith(message)


def test_nested_keys_are_named_by_their_path_and_a_missing_one_is_named() -> None:
    data = fish()
    data["camera_timing"]["period_ticks"] = True
    with pytest.raises(
        ValueError, match=r"^camera_timing.period_ticks: must be an integer, got True$"
    ):
        read_config(json.dumps(data))
    data = fish()
    del data["cycles"]
    with pytest.raises(ValueError, match=r"^cycles: missing key$"):
        read_config(json.dumps(data))


def test_true_and_false_are_the_only_booleans() -> None:
    data = config_data("default") | {"latency_compensation": 1}
    with pytest.raises(ValueError, match=r"^latency_compensation: must be true or false, got 1$"):
        read_config(json.dumps(data))
    assert (
        read_config(json.dumps(data | {"latency_compensation": False})).latency_compensation
        is False
    )


def test_an_optional_value_is_null_or_of_its_type() -> None:
    data = config_data("default")
    assert read_config(json.dumps(data | {"torque_std": None})).torque_std is None
    assert read_config(json.dumps(data | {"torque_std": 2})).torque_std == 2.0
    with pytest.raises(ValueError, match=r"^torque_std: must be a number, got 'x'$"):
        read_config(json.dumps(data | {"torque_std": "x"}))
