"""The MPC and the detector declared on the public task API (common/builtin_tasks.py): their edge
sides are the Services `dynqos edge serve` runs, and the drone holds the MPC to the same declaration."""

from __future__ import annotations

from dataclasses import replace

import pytest

from dynqos.common import builtin_tasks
from dynqos.common.camera_messages import CameraFrame, Detections
from dynqos.common.config import Config
from dynqos.common.messages import Command, State
from dynqos.common.tasks import Service, TaskError, load
from dynqos.offload import Service as PublicService


@pytest.mark.parametrize(
    ("target", "task", "name"),
    [
        ("dynqos.edge.mpc.service:SERVICE", builtin_tasks.MPC, "mpc"),
        ("dynqos.edge.detector.service:SERVICE", builtin_tasks.DETECTOR, "detector"),
    ],
)
def test_each_built_in_service_is_a_declared_task_served_like_a_users(
    target: str, task: object, name: str
) -> None:
    served = load(target, Service)
    assert isinstance(served, PublicService)
    assert served.task is task
    assert served.service_name == name  # its logs, metrics and identity keep their names
    assert served.metrics is not None


def test_the_declarations_carry_the_wire_types_and_flows() -> None:
    assert (builtin_tasks.MPC.request, builtin_tasks.MPC.answer) == (State, Command)
    assert (builtin_tasks.DETECTOR.request, builtin_tasks.DETECTOR.answer) == (CameraFrame, Detections)
    assert (builtin_tasks.MPC.flow, builtin_tasks.MPC.stateless) == ("control", False)
    assert (builtin_tasks.DETECTOR.flow, builtin_tasks.DETECTOR.stateless) == ("bulk", True)


def test_the_declarations_are_the_configs_defaults() -> None:
    """The module-level declarations and a default config agree, so docs quoting either say one thing."""
    config = Config()
    assert builtin_tasks.mpc(config) == builtin_tasks.MPC
    assert builtin_tasks.detector(config) == builtin_tasks.DETECTOR


def test_a_config_sets_the_mpcs_rate_and_deadline_for_both_sides() -> None:
    from dynqos.onboard.core import OnboardCore

    config = Config()
    config = replace(
        config,
        control=replace(config.control, t_mpc_s=0.025),
        supervisor=replace(config.supervisor, watchdog_s=0.3),
    )
    mpc = builtin_tasks.mpc(config)
    assert (mpc.rate_hz, mpc.deadline_s) == (40.0, 0.3)
    core = OnboardCore(config, start_ns=0)
    assert core.mpc == mpc


def test_a_service_must_name_a_valid_process() -> None:
    with pytest.raises(TaskError, match=r"Service\.name"):
        Service(builtin_tasks.MPC, make=print, name="Not A Name")
