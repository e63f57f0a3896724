"""``twomass bench`` targets: one private module per target, each with ``HELP``,
``add_arguments(parser)`` and ``run(args) -> int``; :data:`TARGETS` names them and
:func:`run_target` runs one. Beside them: ``_report`` (tables, machine line, JSON), ``_numpy_rk4``
(the simulator's baseline), ``_remote_plant`` (an independent plant in another process behind the
SPEC 8.1 drive interface) and ``_oracle`` (the largest crossover a true linear plant allows)."""

from ._run import TARGETS, run_target

__all__ = ["TARGETS", "run_target"]
