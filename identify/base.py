"""The identifier convention (scikit-learn style).

``__init__`` only stores settings; ``fit(data)`` validates, learns and returns ``self``;
learned values end in ``_``. :class:`Identifier` owns that bookkeeping.
"""

from __future__ import annotations

from typing import Any


class NotFittedError(RuntimeError):
    """A learned value was asked for before ``fit``."""


class Identifier:
    """Base class: settings in ``__init__``, learning in ``fit``, results end in ``_``."""

    fitted_: bool = False

    def get_params(self) -> dict[str, Any]:
        """The settings given to ``__init__`` (public attributes not ending in ``_``)."""
        return {k: v for k, v in vars(self).items()
                if not k.startswith("_") and not k.endswith("_")}

    def _require_fitted(self) -> None:
        if not self.fitted_:
            raise NotFittedError(f"{type(self).__name__} is not fitted yet: call fit(data)")
