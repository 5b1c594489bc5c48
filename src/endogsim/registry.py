"""Named implementations of an extension point (flow estimators, depth and segmentation back-ends,
identification loss terms, dataset formats).

    FLOW_ESTIMATORS = Registry("optical-flow estimator", ModelError)

    @FLOW_ESTIMATORS.register("dis")
    def _dis(weights=None, device="cpu"):
        return DISFlow()

    FLOW_ESTIMATORS.get("dis")      # the registered object; an unknown name raises, listing the known ones

Adding an implementation is one registration next to its code; callers look names up, never branch on them.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Generic, TypeVar

from endogsim.errors import EndoGSimError

__all__ = ["Registry"]

T = TypeVar("T")


class Registry(Generic[T]):
    """An ordered name -> implementation table.

    Args:
        what: what the entries are, for error messages ("optical-flow estimator").
        error: the exception type an unknown name raises.
    """

    def __init__(self, what: str, error: type[EndoGSimError] = EndoGSimError) -> None:
        self.what = what
        self.error = error
        self._entries: dict[str, T] = {}

    def register(self, name: str, obj: T | None = None):
        """Register ``obj`` under ``name``, or use as a decorator (``@registry.register(name)``)."""
        if obj is not None:
            self._entries[name] = obj
            return obj

        def deco(fn: T) -> T:
            self._entries[name] = fn
            return fn

        return deco

    def get(self, name: str) -> T:
        if name not in self._entries:
            raise self.error(f"unknown {self.what} {name!r}; use one of {', '.join(self._entries)}")
        return self._entries[name]

    def names(self) -> list[str]:
        return list(self._entries)

    def items(self) -> Iterator[tuple[str, T]]:
        return iter(list(self._entries.items()))

    def __contains__(self, name: object) -> bool:
        return name in self._entries
