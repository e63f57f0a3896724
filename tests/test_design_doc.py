"""docs/design.md lists the stages and rules of the refinement, the identification's answer and the
commissioning as the registries hold them: the same names in the same order, so the page a newcomer
reads cannot drift from the code."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from training.commissioning._chain import STAGES as CHAIN_STAGES
from training.commissioning._excitation import EXCITATION_RULES
from training.commissioning._rules import CONTROLLER_RULES
from training.identification._assembly import ADJUSTMENTS
from training.identification._policy import REFINED_WHEN
from training.identification._refine._pipeline import PIPELINE
from training.identification._refine._pipeline import STAGES as REFINE_STAGES

DESIGN = Path(__file__).resolve().parents[1] / "docs" / "design.md"
#: A listed step: a list item that starts with the step's name in backticks and a colon.
STEP = re.compile(r"^- `([^`]+)`:", re.MULTILINE)

#: Each list's heading in docs/design.md (its start) and the registry's names, in order.
REGISTRIES: dict[str, tuple[str, ...]] = {
    "### The refinement: `STAGES`, `PIPELINE`": PIPELINE,
    "### Which answers are refined: `REFINED_WHEN`": tuple(rule.__name__ for rule in REFINED_WHEN),
    "### The answer: `ADJUSTMENTS`": tuple(step.__name__ for step in ADJUSTMENTS),
    "### The commissioning chain: `STAGES`": tuple(name for name, _ in CHAIN_STAGES),
    "### The test signal's rules: `EXCITATION_RULES`": tuple(rule.__name__ for rule in EXCITATION_RULES),
    "### The controller rules: `CONTROLLER_RULES`": tuple(rule.__name__ for rule in CONTROLLER_RULES),
}


def _listed(heading: str) -> tuple[str, ...]:
    """The step names listed under the one heading that starts with ``heading``, up to the next heading."""
    lines = DESIGN.read_text(encoding="utf-8").splitlines()
    starts = [i for i, line in enumerate(lines) if line.startswith(heading)]
    assert len(starts) == 1, f"docs/design.md: expected one heading {heading!r}, found {len(starts)}"
    section = []
    for line in lines[starts[0] + 1:]:
        if line.startswith("#"):
            break
        section.append(line)
    return tuple(STEP.findall("\n".join(section)))


@pytest.mark.parametrize("heading", REGISTRIES, ids=lambda heading: heading.split(": ")[0].removeprefix("### "))
def test_design_lists_each_registry_in_order(heading):
    assert _listed(heading) == REGISTRIES[heading]


def test_the_refinement_pipeline_runs_every_registered_stage():
    assert set(PIPELINE) == set(REFINE_STAGES)
