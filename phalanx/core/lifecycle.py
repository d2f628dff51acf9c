"""`with` for anything that has a `close()`: the one context-manager shape phalanx's
sessions, sinks, clients and simulated devices share.
"""

from __future__ import annotations

from types import TracebackType
from typing import Self


class Closing:
    """Mixin: `with thing:` gives `thing` and calls `thing.close()` on the way out, error or
    not (`close` itself must be safe to call twice).
    """

    def close(self) -> None:
        """Release what the object holds (subclasses)."""
        raise NotImplementedError

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
