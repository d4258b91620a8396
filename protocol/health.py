"""A column's formation health (design §7): the one owner of each follower's running mean and
worst formation error and of its broken ticks (ticks beyond ``--formation-tolerance``).

The world's recorder (``world.results``) counts every complete tick here, and what it reports,
``summary.json`` and the console table, reads these totals; the live view and the ROS 2 output
(live topics and the bag) show the same values tick by tick, as :meth:`ColumnHealth.add_tick`
adds them to the tick's rows. A replay or a bag export, which read ``ticks.csv`` back, count its
rows here again and get the same numbers.

The rule (design §7): a follower's formation error is measured on its true pose at every tick,
whether or not it settled in time: a follower that missed a tick stands where it stood while
the formation moves on, and the world sees it out of formation. Every tick with a formation
error counts towards the mean and the worst, and is broken if the error exceeds the tolerance.
A tick without one (its ideal place has left the surface's domain, so the world cannot say
the follower kept it) is broken too: it cannot count as kept formation.
"""
from __future__ import annotations

import math
from collections.abc import Iterable, Mapping

HEALTH_COLUMNS = ("mean_formation_error", "worst_formation_error", "broken_ticks")
"""What :meth:`FormationHealth.values` gives, and :meth:`ColumnHealth.add_tick` adds to each
follower's row."""


class ExactSum:
    """Running sum of floats, rounded exactly like ``math.fsum`` over every value added so far
    (Shewchuk's partials): the summary, rewritten after every tick, costs O(1) per tick.

    >>> s = ExactSum()
    >>> for x in (1e100, 1.0, -1e100, 0.1):
    ...     s.add(x)
    >>> s.value() == math.fsum([1e100, 1.0, -1e100, 0.1])
    True
    """

    def __init__(self) -> None:
        self._partials: list[float] = []
        self.count = 0

    def add(self, x: float) -> None:
        partials, i = self._partials, 0
        for y in partials:
            if abs(x) < abs(y):
                x, y = y, x
            hi = x + y
            lo = y - (hi - x)
            if lo:
                partials[i] = lo
                i += 1
            x = hi
        partials[i:] = [x]
        self.count += 1

    def value(self) -> float:
        return math.fsum(self._partials)

    def mean(self) -> float | None:
        return self.value() / self.count if self.count else None


class FormationHealth:
    """One follower's formation health so far.

    Parameters
    ----------
    tolerance : float
        ``--formation-tolerance``, m (> 0; ``inf`` counts no tick as broken).

    >>> h = FormationHealth(1.0)
    >>> for error in (0.25, 1.5, None, 0.5):
    ...     h.add(error)
    >>> h.values()
    {'mean_formation_error': 0.75, 'worst_formation_error': 1.5, 'broken_ticks': 2}
    """

    def __init__(self, tolerance: float) -> None:
        if isinstance(tolerance, bool) or not isinstance(tolerance, (int, float)) \
                or not tolerance > 0:
            raise ValueError(f"tolerance must be a number > 0 (m), got {tolerance!r}")
        self.tolerance = float(tolerance)
        self.total = ExactSum()
        self.worst: float | None = None
        self.broken = 0

    def add(self, error: float | None) -> None:
        """Count one tick's formation error (None: the world could not measure it, its ideal
        place being off the surface's domain; not in the mean or the worst, but broken)."""
        if error is None:
            self.broken += 1
            return
        self.total.add(error)
        self.worst = error if self.worst is None else max(self.worst, error)
        self.broken += bool(error > self.tolerance)

    def values(self) -> dict:
        """``mean_formation_error``, ``worst_formation_error`` (None before any tick, m) and
        ``broken_ticks``."""
        return {"mean_formation_error": self.total.mean(), "worst_formation_error": self.worst,
                "broken_ticks": self.broken}


class ColumnHealth:
    """Every follower's :class:`FormationHealth`, counted tick by tick from a tick's rows.

    Parameters
    ----------
    followers : int
        Followers 1..``followers`` (agent 0, the leader, has no formation error).
    tolerance : float
        ``--formation-tolerance``, m.
    """

    def __init__(self, followers: int, tolerance: float) -> None:
        if isinstance(followers, bool) or not isinstance(followers, int) or followers < 0:
            raise ValueError(f"followers must be an integer >= 0, got {followers!r}")
        self.followers = {k: FormationHealth(tolerance) for k in range(1, followers + 1)}

    def add_tick(self, rows: Iterable[Mapping]) -> list[dict]:
        """Count one complete tick's rows (``WorldSim.finish_tick``, or ``ticks.csv`` read
        back; ``formation_error`` on the followers' rows) and return them, each follower's
        row with its :data:`HEALTH_COLUMNS` so far (this tick included) added."""
        rows = list(rows)
        for row in rows:
            if row["agent"] in self.followers:
                self.followers[row["agent"]].add(row.get("formation_error"))
        return [{**row, **self.followers[row["agent"]].values()}
                if row["agent"] in self.followers else dict(row) for row in rows]

    def broken(self) -> bool:
        """Whether any follower has a broken tick."""
        return any(h.broken for h in self.followers.values())
