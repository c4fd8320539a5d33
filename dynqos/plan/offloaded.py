"""A scenario's offloaded tasks (docs/offload.md): the modules it names, each defining EDGE (served by
`dynqos edge serve`, one process a task) and ONBOARD (loaded into every drone's daemon).

A module is a dotted name on the Python path ("dynqos.examples.look_at") or a file ("my_task.py",
relative to the folder the flight is started from, as a fault's trace file). Each is loaded once here,
when the scenario is read, so a module that fails to import or declares nonsense stops the run before
anything starts, in one line."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from dynqos.common.errors import ConfigError
from dynqos.common.tasks import Edge, Onboard, TaskError, load

MAX_SCENARIO_TASKS = 8


@dataclass(frozen=True, slots=True)
class Offloaded:
    name: str  # the task's, from its declaration
    edge: str  # `dynqos edge serve` target
    onboard: str  # [onboard] tasks entry

    @property
    def process(self) -> str:
        """Its edge service's process name in the run (and its log file)."""
        return f"task-{self.name}"


def offloaded(modules: tuple[str, ...]) -> list[Offloaded]:
    """Each module's task, checked; ConfigError (key `tasks`) naming the first that fails."""
    if len(modules) > MAX_SCENARIO_TASKS:
        raise ConfigError("tasks", f"at most {MAX_SCENARIO_TASKS} tasks")
    out = []
    for module in modules:
        where = str(Path(module).resolve()) if module.endswith(".py") else module
        try:
            edge = load(f"{where}:EDGE", Edge)
            onboard = load(f"{where}:ONBOARD", Onboard)
        except TaskError as exc:
            raise ConfigError("tasks", f"{module}: {exc}") from None
        if edge.task != onboard.task:
            raise ConfigError("tasks", f"{module}: EDGE and ONBOARD declare different tasks")
        out.append(Offloaded(edge.task.name, f"{where}:EDGE", f"{where}:ONBOARD"))
    if len({o.name for o in out}) != len(out):
        raise ConfigError("tasks", "two modules declare tasks of one name")
    return out
