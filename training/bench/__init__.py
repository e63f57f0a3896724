"""``twomass bench`` targets: one private module per target, each with ``HELP``,
``add_arguments(parser)`` and ``run(args) -> int``; :data:`TARGETS` names them."""

#: target name -> module (imported only when the target runs)
TARGETS: dict[str, str] = {
    "identify": "training.bench._identify",
    "sim": "training.bench._sim",
    "som": "training.bench._som",
}

__all__ = ["TARGETS"]
