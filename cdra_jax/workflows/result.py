"""What every workflow result shares: ``to_json()`` and ``save()`` from its ``to_dict()``.

Each result of :mod:`cdra_jax.workflows` is a frozen dataclass with ``to_dict()`` (its file
content as a JSON-ready mapping), ``report()`` (the text the command line prints) and ``plot()``
(a matplotlib figure); :class:`JsonResult` derives the JSON text and the atomic file write from
``to_dict()``. Results whose file is not JSON (a measurement CSV, a sweep table) override
``save``.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from ..io.files import json_text, write_text_atomic


class JsonResult:
    """Mixin: :meth:`to_json` and :meth:`save` from the subclass's ``to_dict()``."""

    def to_dict(self) -> dict[str, Any]:
        """The result as a JSON-ready mapping."""
        raise NotImplementedError

    def to_json(self) -> str:
        """:meth:`to_dict` as JSON text (floats exact, each flat list of numbers on one line)."""
        return json_text(self.to_dict())

    def save(self, path: str | os.PathLike, *, force: bool = False) -> Path:
        """Write :meth:`to_json` atomically; an existing file is replaced only with ``force``."""
        return write_text_atomic(path, self.to_json(), force=force)
