"""What a recipe says about quality: its features (nominal and tolerance) and its feedback.

A recipe's content is the machine's program; these lines ride in it, so they are versioned and approved
with it (the ERS owns them; sql/070_quality.sql reads them with the same grammar):

    FEATURE DIAMETER 25.00 0.05                    nominal 25.00, tolerance +/- 0.05
    FEEDBACK EWMA 0.3 STEP 0.02 LIMIT 0.12         run-to-run feedback on: EWMA weight, largest step,
                                                   largest total offset (past it the tool is worn out)

A machine that knows nothing of them (the thesis's CMM program, a dummy) ignores unknown lines.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

FEATURE = re.compile(
    r"^FEATURE[ \t]+([A-Za-z][A-Za-z0-9_]*)[ \t]+([-+]?[0-9]+(?:\.[0-9]*)?)[ \t]+([0-9]+(?:\.[0-9]*)?)[ \t\r]*$", re.M
)
FEEDBACK = re.compile(
    r"^FEEDBACK[ \t]+EWMA[ \t]+([0-9]*\.?[0-9]+)[ \t]+STEP[ \t]+([0-9]*\.?[0-9]+)"
    r"[ \t]+LIMIT[ \t]+([0-9]*\.?[0-9]+)[ \t\r]*$",
    re.M,
)


@dataclass(frozen=True)
class Feature:
    """One dimension of a part: measured values within nominal +/- tol pass."""

    name: str
    nominal: float
    tol: float

    def passes(self, value: float) -> bool:
        return abs(value - self.nominal) <= self.tol + 1e-12

    @property
    def lsl(self) -> float:
        return self.nominal - self.tol

    @property
    def usl(self) -> float:
        return self.nominal + self.tol


@dataclass(frozen=True)
class FeedbackSettings:
    """The run-to-run controller of a recipe: EWMA weight, largest step and largest total offset."""

    weight: float
    step_limit: float
    total_limit: float


def features_of(text: str) -> list[Feature]:
    """The FEATURE lines of a recipe, in order (a name given twice: the first counts)."""
    seen: dict[str, Feature] = {}
    for name, nominal, tol in FEATURE.findall(text):
        seen.setdefault(name, Feature(name, float(nominal), float(tol)))
    return list(seen.values())


def feedback_of(text: str) -> FeedbackSettings | None:
    """The recipe's FEEDBACK line, or None: feedback is off for it."""
    m = FEEDBACK.search(text)
    if m is None:
        return None
    weight, step, total = (float(g) for g in m.groups())
    if not 0 < weight <= 1:
        return None
    return FeedbackSettings(weight, step, total)
