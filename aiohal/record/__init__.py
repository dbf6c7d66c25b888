"""Recordings of runs: their MCAP messages (``cdr``), the ``[record]`` section, reading them
back as numpy arrays (``reader``) and drawing them (``plot``, extra ``plot``).

The recorder that writes them runs outside the tick (:mod:`aiohal.outside.recorder`).
``import aiohal.record`` imports neither mcap nor matplotlib: the reader and the figures load
them when used.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from .options import TICK_CHANNELS, RecordSection

if TYPE_CHECKING:
    from .reader import Recording, Series

__all__ = ["TICK_CHANNELS", "RecordSection", "Recording", "Series", "load"]


def load(path: Any) -> Recording:
    """A recording as numpy arrays: ``load("run.mcap")["/joint_states"].position``."""
    from .reader import load as _load

    return _load(path)


def __getattr__(name: str) -> Any:
    if name in ("Recording", "Series"):
        from . import reader

        return getattr(reader, name)
    raise AttributeError(name)
