"""Scale-out of the suites: every entry of a suite is one task, run on Ray.

One interface, :func:`run_tasks`, serves every suite (``mosiv data suite``,
``mosiv diagnose-suite``, the benchmark scripts). docs/ARCHITECTURE.md ("Scale-out") describes
the model: a local Ray by default, a cluster with ``ray_address``, GPU fractions per task,
tasks rerun after their worker died, progress logged per entry.
"""

from mosiv_framework.scale.runner import Outcome, Task, TaskDied, run_command, run_tasks

__all__ = ["Outcome", "Task", "TaskDied", "run_command", "run_tasks"]
