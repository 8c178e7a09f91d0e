"""A budget of work for one integration (fleetmap): what bounds its cost, whatever its two maps.

An integration's cost grows with its maps' segments and with how densely they lie: two maps of
5,000 segments strewn over a few rooms compare tens of millions of segment pairs. A clock cannot
bound it here: which integrations finish would depend on the machine's load, and a replay, which
integrates again, would no longer rebuild the live map. So the work is counted, as a SAT solver's
propagation budget bounds a search deterministically (MiniSat's ``setPropBudget``, Eén &
Sörensson 2003; Z3's ``rlimit``): each stage charges, before it runs (or, where only the running
tells, as soon as it knows), the elementary steps it does, each at its cost in *units*, one unit
about the time of one grid lookup (measured on two maps of 5,000 random segments, and on 120 and
300; record 013):

- a sample point looked up in another map's grid (the grid score of the large-map path), a pair
  of segments tested for crossing under a candidate (Algorithm 4, steps 6-8), a pair of
  segments taken from the pairs sorted by rotation, a sample point of a registration near a
  prediction in each of its iterations (charged for the most iterations): one unit;
- a pair of a map's own long segments tested for crossing (once per map pair):
  :data:`SELF_CROSSING` units;
- a pair of segments whose matching value is computed for many candidates (Algorithm 4, steps
  9-20, a block's pairs): :data:`PAIR_VALUED` units;
- a pair of segments found near each other by S1's k-d tree (one transformation's pairs, large
  maps): :data:`PAIR_FOUND` units.

A stage whose units would take the count past the limit does not run: :class:`WorkExhausted`
unwinds the integration, which is then reported not valid and marked ``exhausted`` (it never
gives a transformation it could not finish judging). The count depends only on the two maps and
the parameters, so the same pair stops at the same stage on any machine and in a replay.
"""

from __future__ import annotations

from dataclasses import dataclass

SELF_CROSSING = 4
"""Units of a pair of a map's own long segments tested for crossing (both ways, four ends each)."""
PAIR_VALUED = 5
"""Units of a pair of segments whose matching value is computed for one candidate of many."""
PAIR_FOUND = 20
"""Units of a pair of segments S1's k-d tree finds near each other (and of each query)."""


class WorkExhausted(Exception):
    """An integration's work would pass its budget (:class:`Work`); caught where the integration began."""


@dataclass
class Work:
    """Units of work done so far (see the module docstring), and at most how many (0: no limit)."""

    limit: int = 0
    spent: int = 0

    def charge(self, units: int) -> None:
        """Count ``units`` about to be done (or just found to be due); :class:`WorkExhausted`, and
        nothing counted, if they would take the count past the limit."""
        if 0 < self.limit < self.spent + units:
            raise WorkExhausted(f"{self.spent} units of work done, {units} more would pass the budget of {self.limit}")
        self.spent += int(units)
