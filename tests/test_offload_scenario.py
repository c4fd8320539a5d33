"""The offload-example scenarios and a user's own scenario, read without flying: what each starts, what
the drone loads, which fault kills what; and a task module that does not load stops the run at once."""

from __future__ import annotations

from pathlib import Path

import pytest

from dynqos.common.config import ZenohConfig
from dynqos.common.errors import ConfigError
from dynqos.plan.offloaded import offloaded
from dynqos.plan.scenario import builtin_scenario, load_scenario, scenario_config

ROOT = Path(__file__).resolve().parent.parent
MODES = {
    "offload-example": "dynamic",
    "offload-example-noqos": "default",
    "offload-example-priority": "priority",
}


@pytest.mark.parametrize("name", sorted(MODES))
def test_each_offload_scenario_flies_the_example_in_its_mode_through_a_kill_of_its_service(name: str) -> None:
    scenario = builtin_scenario(name)
    assert scenario.qos == MODES[name]
    assert scenario.bg_start_s == 15
    assert [(f.kind, f.at_s, f.duration_s) for f in scenario.faults] == [("task_kill", 33, 3)]
    (task,) = offloaded(scenario.tasks)
    assert (task.name, task.process) == ("look-at", "task-look-at")
    assert task.edge == "dynqos.examples.look_at:EDGE"
    config = scenario_config(scenario, zenoh=ZenohConfig(), fc_port=14540, gcs_port=14550)
    assert config.onboard.tasks == ("dynqos.examples.look_at:ONBOARD",)
    assert config.onboard.yaw == "command"  # the task's heading is flown


def test_a_users_scenario_names_a_task_file_beside_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / "mine.py").write_text(
        (ROOT / "examples" / "look_at.py").read_text().replace("look-at", "mine")
    )
    (tmp_path / "mine.toml").write_text('[scenario]\nname = "mine"\ntasks = ["mine.py"]\n')
    monkeypatch.chdir(tmp_path)
    scenario = load_scenario(tmp_path / "mine.toml")
    (task,) = offloaded(scenario.tasks)
    assert task.name == "mine"
    assert task.edge == f"{tmp_path / 'mine.py'}:EDGE"  # absolute: the services start elsewhere


@pytest.mark.parametrize(
    ("source", "said"),
    [
        ("raise ImportError('no such thing')\n", "ImportError: no such thing"),
        ("X = 1\n", "EDGE is nothing"),
    ],
)
def test_a_task_module_that_does_not_load_stops_the_scenario_in_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, source: str, said: str
) -> None:
    (tmp_path / "broken.py").write_text(source)
    (tmp_path / "s.toml").write_text('[scenario]\nname = "s"\ntasks = ["broken.py"]\n')
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ConfigError, match="tasks") as caught:
        load_scenario(tmp_path / "s.toml")
    assert said in str(caught.value)
    assert "\n" not in str(caught.value)
