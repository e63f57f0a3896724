"""``twomass bench`` targets: one private module per target, each with ``HELP``,
``add_arguments(parser)`` and ``run(args) -> int``; :data:`TARGETS` names them and
:func:`run_target` runs one."""

from ._run import TARGETS, run_target

__all__ = ["TARGETS", "run_target"]
