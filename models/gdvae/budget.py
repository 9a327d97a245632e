"""A training stage's wall-clock budget (a lent accelerator's minutes), checked the same way by
every stage: past it, the stage ends where it is, says so once, and records it in stages.json."""

from __future__ import annotations

import logging
import time

log = logging.getLogger(__name__)


def budget_spent(stage: str, budget_seconds: float | None, started: float, iteration: int, total: int) -> bool:
    """Whether `stage`, started at `started` (time.monotonic()), has used its budget (None: none)."""
    if budget_seconds is None or time.monotonic() - started <= budget_seconds:
        return False
    log.info("%s: time budget of %.0f s reached at iteration %d of %d; the stage ends here",
             stage, budget_seconds, iteration, total)
    return True
