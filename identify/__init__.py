"""From run logs to model.yaml: data checks, fits, bounds and validation.

``identify(logs)`` does what the ``identify`` command does and returns an
:class:`~pneutune.identify.pipeline.IdentifyResult` (``.model`` is model.yaml's contract,
``.save(folder)`` writes it and the report)::

    from pneutune.identify import identify
    result = identify("data/run.mcap")

The names are imported on first use, so that ``import pneutune.identify`` stays light.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from pneutune.identify.pipeline import IdentifyResult, identify

__all__ = ["IdentifyResult", "identify"]


def __getattr__(name: str) -> Any:
    if name in __all__:
        from pneutune.identify import pipeline

        return getattr(pipeline, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
