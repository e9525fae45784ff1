"""The evaluation entry a run is judged by: what picks ``best.pt``, what a confirmation
scores and what ``threshold`` is compared with (``--select-by``, ``--select-mode``)."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Literal

__all__ = ["Metric"]


@dataclass(frozen=True)
class Metric:
    """An entry of the run's evaluations and which way is better.

    Args:
        key (str): an entry [`evaluate`][rl_pg.evaluation.evaluate] reports:
            ``"mean_return"``, or a rate or a mean of the recipe's
            (``"arrive_dest_rate"``, ``"mean_route_completion"``, ``"crashed_rate"``).
            Defaults to ``"mean_return"``.
        mode (str): ``"max"`` (the highest value is best) or ``"min"`` (the lowest: a
            crash rate). Defaults to ``"max"``.

    Examples:
        >>> from rl_pg.training.metric import Metric
        >>> crashes = Metric("crashed_rate", "min")
        >>> crashes.better(0.1, than=0.2), crashes.reaches(0.25, threshold=0.2)
        (True, False)
        >>> crashes.worst([0.1, 0.3])
        0.3
    """

    key: str = "mean_return"
    mode: Literal["max", "min"] = "max"

    def __post_init__(self) -> None:
        if not isinstance(self.key, str) or not self.key:
            raise TypeError(f"A metric's key is an evaluation entry's name, got {self.key!r}.")
        if self.mode not in ("max", "min"):
            raise ValueError(
                f"A metric's mode is 'max' (highest is best) or 'min' (lowest is best), "
                f"got {self.mode!r}."
            )

    @classmethod
    def of(cls, settings) -> Metric:
        """The metric a config (or its evaluation settings) selects by."""
        return cls(settings.select_by, settings.select_mode)

    @classmethod
    def of_summary(cls, summary: Mapping) -> Metric:
        """The metric a run's summary (or report) says it selected by; the mean return
        for runs that predate the choice."""
        return cls(summary.get("select_by", "mean_return"), summary.get("select_mode", "max"))

    @property
    def logged(self) -> str:
        """Its name in the run's logs and ``last_eval``: ``eval/<key>``."""
        return f"eval/{self.key}"

    def check(self, available: Iterable[str]) -> Metric:
        """Itself, if its key is among the ``available`` evaluation entries; else a
        ValueError naming them."""
        available = tuple(available)
        if self.key not in available:
            raise ValueError(
                f"--select-by {self.key}: the run's evaluations report no such entry. "
                f"Choose one of {', '.join(available)} (a recipe's rates and means come from "
                f"its evaluation flags and values)."
            )
        return self

    def read(self, evaluation: Mapping[str, float]) -> float:
        """Its value in a logged evaluation (keys ``eval/...``); a KeyError naming what
        the evaluation holds when it is not there (an environment that never reports
        the flag or value)."""
        try:
            return evaluation[self.logged]
        except KeyError:
            have = sorted(k for k in evaluation if k.startswith("eval/"))
            raise KeyError(
                f"The evaluation reported no {self.key} (it has {', '.join(have)}): the "
                f"environment never set the entry that --select-by {self.key} reads. Select "
                f"by one it reports."
            ) from None

    def better(self, value: float, than: float | None) -> bool:
        """Whether ``value`` is strictly better than ``than`` (anything beats None; NaN
        beats nothing)."""
        if math.isnan(value):
            return False
        if than is None:
            return True
        return value > than if self.mode == "max" else value < than

    def reaches(self, value: float, threshold: float) -> bool:
        """Whether ``value`` is at ``threshold`` or better."""
        return value >= threshold if self.mode == "max" else value <= threshold

    def worst(self, values: Iterable[float]) -> float:
        """The worst of ``values`` (the lower for ``"max"``)."""
        return min(values) if self.mode == "max" else max(values)

    def text(self, value: float) -> str:
        """``value`` as reports print it: a rate in percent, a return to two decimals,
        another mean to three.

        Examples:
            >>> from rl_pg.training.metric import Metric
            >>> Metric("arrive_dest_rate").text(0.61), Metric("mean_route_completion").text(0.7434)
            ('61%', '0.743')
        """
        if self.key.endswith("_rate"):
            return f"{value:.0%}"
        return f"{value:.2f}" if self.key.endswith("_return") else f"{value:.3f}"

    def __str__(self) -> str:
        return f"{self.key} ({'highest' if self.mode == 'max' else 'lowest'} is best)"
