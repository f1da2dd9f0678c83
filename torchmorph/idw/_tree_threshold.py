"""The search for the tree's acceptance threshold ``η`` (:mod:`torchmorph.idw.tree`): a
trial traversal at ``η`` gives the worst error, the certified bound or the error at the
sampled targets; ``η`` is raised while that error is far below the goal and lowered
when it is above, a few traversals per call at most, and the factor is remembered for
the module's later calls."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

__all__ = ["search"]

CERTIFY_ATTEMPTS = 4
"""Traversals per call at most: ``η`` lowered after an error above the goal (aiming at
half of it), raised after one below ``goal / LOOSEN`` (certified) or ``goal /
SAMPLED_LOOSEN`` (sampled)."""

LOOSEN = 4.0

SAMPLED_LOOSEN = 2.0
"""``error_control="sampled"``: ``η`` is raised while the sampled error is below
``tolerance / (SAMPLE_SAFETY · SAMPLED_LOOSEN)``."""

SAMPLED_GROWTH = 1.6
"""``error_control="sampled"``: the measured error grows about as ``η^0.6`` on the
benchmark's clouds, so ``η`` is raised by ``(goal / (2 error))^SAMPLED_GROWTH``."""

CEILING_CALLS = 32
"""Calls without a failed trial after which a ceiling is raised by :data:`CEILING_EASE`
(a field that turned easier may then allow a larger ``η``; where it did not, a probe
fails: about one traversal more per this many calls)."""

CEILING_EASE = 1.5

RAISE_LEAST = 1.25
"""``η`` is not raised by less than this factor: below it, an ``η`` that failed is too
close (the trial would cost a traversal for little)."""

Trial = Callable[[float], tuple[float, Any]]


def search(
    eta: float,
    trial: Trial,
    goal: float,
    largest: float,
    *,
    certified: bool,
    stop: bool,
    ceiling: float | None = None,
    attempts: int = CERTIFY_ATTEMPTS,
    probes: int | None = 1,
) -> tuple[tuple[float, Any] | None, tuple[float, Any], float, float | None]:
    """``trial(η)`` gives the worst error (bound or sampled) and what the caller keeps;
    below ``goal`` and far below it ``η`` is raised, above it lowered, up to ``attempts``
    trials. An ``η`` that failed is the ``ceiling``: raises go at most halfway to it
    (geometrically), ``probes`` of them per call (None: as many as the attempts allow),
    and none when that is less than :data:`RAISE_LEAST` (without it, a cloud whose error
    jumps past the goal between two ``η`` made every call raise, fail and traverse 2-4
    times; the caller loosens it after :data:`CEILING_CALLS` calls). Returns ``(η,
    kept)`` of the last trial within ``goal`` (None if none was) and of the last trial,
    the ``η`` the next call starts from and the ceiling. ``stop``: keep the first within
    ``goal``."""
    best, last, start, raises, best_error = None, (eta, None), eta, 0, 0.0
    loosen = LOOSEN if certified else SAMPLED_LOOSEN
    for _ in range(attempts):
        worst, kept = trial(eta)
        last = (eta, kept)
        if worst <= goal:
            best, best_error, start = last, worst, eta
        else:  # η failed: later raises stay below it
            ceiling = eta if ceiling is None else min(ceiling, eta)
        if best is None:  # none within the goal yet: lower η
            factor = max(0.5 * goal / worst, 1 / 64) if math.isfinite(worst) else 1 / 4
            eta = start = min(largest, eta * factor)
            continue
        good = best[0]
        if best_error > goal / loosen or good >= largest or stop:
            break
        # far below the goal: accept more nodes (the check is repeated)
        factor = 0.5 * goal / max(best_error, 1e-300)
        factor = min(factor, 1e3) if certified else min(factor**SAMPLED_GROWTH, 1e2)
        raised = min(largest, good * factor)
        if ceiling is not None:
            raised = min(raised, math.sqrt(good * ceiling))
            if probes is not None and raises >= probes:
                break
        if raised < RAISE_LEAST * good:
            break
        eta, raises = raised, raises + 1
    return best, last, start, ceiling
