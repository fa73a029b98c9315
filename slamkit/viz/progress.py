"""A progress bar that a saved notebook keeps: plain text on stdout, not a widget.

``tqdm.auto`` draws a widget in a notebook, which a saved (autosaved) notebook, GitHub's viewer and an
offline ``nbconvert --to html`` show as "model not found" or nothing. :func:`progress_bar` is tqdm's text
bar on stdout (a stream output, kept as text), redrawn at most every 3 seconds, with the count and the
elapsed time only: a rate would be a second speed beside the one a notebook defines and prints.
"""

from __future__ import annotations

import sys
from typing import TYPE_CHECKING

from tqdm.std import tqdm

if TYPE_CHECKING:  # pragma: no cover
    from ..pipeline import Slam

BAR_FORMAT = "{desc}: {percentage:3.0f}%|{bar:30}| {n_fmt}/{total_fmt} {unit}s [{elapsed} elapsed]"


def progress_bar(total: int, unit: str = "frame", desc: str = "progress") -> tqdm:
    """A text progress bar over ``total`` items (``unit``), on stdout; ``update(1)`` per item, ``close()``."""
    return tqdm(total=total, unit=unit, desc=desc, file=sys.stdout, bar_format=BAR_FORMAT, mininterval=3.0,
                ascii=False, dynamic_ncols=False, ncols=None)  # no width limit: a long description cut the line


def close_early(bar: tqdm, desc: str) -> None:
    """Close ``bar`` at the count it reached, as full: the work ended before the total it was given (e.g. a run
    stepped only to its first loop closure), which ``desc`` says; a bar is never left standing part-way."""
    bar.total = bar.n
    bar.set_description_str(desc, refresh=False)
    bar.close()


def run_with_bar(slam: "Slam", desc: str = "SLAM") -> list:
    """``slam.run()`` (every frame, then the final global bundle adjustment) with a :func:`progress_bar` over its
    frames, moved on by one of the pipeline's callbacks at every step and closed when the run ends; returns the
    step results."""
    bar = progress_bar(len(slam), "frame", desc)

    def advance(_slam, _result) -> None:
        bar.update(1)

    slam.callbacks.append(advance)
    try:
        return slam.run()
    finally:
        slam.callbacks.remove(advance)
        bar.close()


__all__ = ["progress_bar", "close_early", "run_with_bar", "BAR_FORMAT"]
