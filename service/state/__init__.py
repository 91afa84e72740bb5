"""What takes minutes to learn survives a restart (``--state-dir``, contract §4.6 "State").

:class:`~service.state.keeper.StateKeeper` reads and writes ``DIR/state.bin``
(:mod:`.fileformat`) for the engine's :meth:`~service.engine.Engine.export_state` and
:meth:`~service.engine.Engine.restore_state`.  No numerics of its own, no Zenoh, no HTTP.
"""

from service.state.keeper import StateKeeper

__all__ = ["StateKeeper"]
