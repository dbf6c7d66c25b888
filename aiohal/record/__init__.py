"""Recording a run to MCAP, reading it back, and serving it live (extra ``record``).

``import aiohal.record`` imports neither mcap nor numba's kernels: the recorder, the reader and
the live server load them when used.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from .options import TICK_CHANNELS, RecordSection

if TYPE_CHECKING:
    from .reader import Recording, Series
    from .recorder import Recorder

__all__ = ["TICK_CHANNELS", "RecordSection", "Recorder", "Recording", "Series", "load"]


def load(path: Any) -> Recording:
    """A recording as numpy arrays: ``load("run.mcap")["/joint_state"].position``."""
    from .reader import load as _load

    return _load(path)


def __getattr__(name: str) -> Any:
    if name == "Recorder":
        from .recorder import Recorder

        return Recorder
    if name in ("Recording", "Series"):
        from . import reader

        return getattr(reader, name)
    raise AttributeError(name)
