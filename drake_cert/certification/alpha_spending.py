"""One failure probability for a whole drive: alpha spent over its decisions (DESIGN 6.2).

A drive takes one certified decision per camera tick. Each holds with probability at least
``1 - alpha_k`` over its own noise; by the union bound every decision of the drive holds at
once with probability at least ``1 - sum_k alpha_k``. With one fixed alpha per decision that
sum grows with the drive (about 170 decisions at 0.001 on dry_to_snow: only 0.83 for the
drive). An :class:`AlphaSpending` fixes the drive's total first and hands each tick its share,
so the sum never exceeds the total, however long the drive runs:

* ticks ``0 .. planned - 1`` get ``planned_share * total / planned`` each;
* tick ``planned + j`` (j >= 0), past the plan, gets ``(1 - planned_share) * total /
  ((j + 1) (j + 2))``, whose sum over all j is ``(1 - planned_share) * total``.

So ``sum_k alpha_k <= total`` for any number of ticks (the tail telescopes). The plan is the
number of ticks the drive should need (the route and the lead-in at the slowest moving design
speed, :func:`planned_decisions`); a drive that takes longer (a stop, a held car) keeps sound
decisions that grow ever harder to certify, and abstain once its samples can no longer reach
the shrinking alpha (the envelope: conservative, never unsound). The price inside the plan is
a log factor: a sequential decision needs about ``log(planned / (planned_share alpha))``
instead of ``log(1 / alpha)`` unanimous samples.
"""

from __future__ import annotations

import dataclasses
import math

from drake_cert.certification.statistics import check_alpha, check_count

PLANNED_SHARE = 0.9  # share of the drive's alpha spread over the planned ticks


@dataclasses.dataclass(frozen=True)
class AlphaSpending:
    """The failure probability of each decision of a drive whose decisions together fail with
    probability at most ``total`` (module docstring)."""

    total: float
    planned: int
    planned_share: float = PLANNED_SHARE

    def __post_init__(self):
        check_alpha(self.total, "total alpha")
        check_count(self.planned, "planned decisions")
        check_alpha(self.planned_share, "planned_share")

    @property
    def planned_alpha(self) -> float:
        """The alpha of each planned tick (the largest any tick gets)."""
        return self.planned_share * self.total / self.planned

    def alpha(self, tick: int) -> float:
        """The failure probability decision ``tick`` (0, 1, ...) is taken at."""
        if tick < 0:
            raise ValueError(f"tick = {tick} must be >= 0")
        if tick < self.planned:
            return self.planned_alpha
        j = tick - self.planned
        return (1.0 - self.planned_share) * self.total / ((j + 1) * (j + 2))

    def spent(self, ticks: int) -> float:
        """``sum_{k < ticks} alpha(k)`` in closed form: the union bound of ``ticks`` decisions
        (never above ``total``)."""
        inside = min(ticks, self.planned)
        beyond = max(0, ticks - self.planned)
        tail = (1.0 - self.planned_share) * self.total * (1.0 - 1.0 / (beyond + 1))
        return min(self.total, inside * self.planned_alpha + tail)


def planned_decisions(distance_m: float, slowest_speed_mps: float, rate_hz: float,
                      duration_s: float = 0.0) -> int:
    """Ticks a drive of ``distance_m`` (route and lead-in, m) takes at the slowest moving speed
    (m/s) with a camera at ``rate_hz``, at most the ticks of ``duration_s`` when that is > 0
    (a drive stopped by time); at least 1."""
    if not (slowest_speed_mps > 0 and rate_hz > 0 and distance_m >= 0):
        raise ValueError("planned_decisions needs a positive speed and rate and a distance >= 0")
    ticks = math.ceil(rate_hz * distance_m / slowest_speed_mps) + 1
    if duration_s > 0:
        ticks = min(ticks, math.floor(rate_hz * duration_s) + 1)
    return max(1, ticks)
