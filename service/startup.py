"""The engine of a start: built from its configuration and restored from the state directory
(``--state-dir``) before any input.  The node (``service.transport.node``) takes it built."""

from __future__ import annotations

from service.config import EngineConfig
from service.engine import Engine
from service.settings import Settings
from service.state import StateKeeper
from service.state.lock import lock_directory


def build_engine(
    config: EngineConfig, correlation_process: bool = False, state: StateKeeper | None = None
) -> Engine:
    """A new engine (``correlation_process``: its correlation stage in a child process),
    restored from ``state``'s directory when given (``OSError`` when it cannot be used; the
    engine is closed then)."""
    engine = Engine(config, correlation_process=correlation_process)
    if state is not None:
        try:
            state.restore(engine)
        except BaseException:
            engine.close()
            raise
    return engine


def state_keeper(settings: Settings) -> StateKeeper | None:
    """This worker's keeper of ``--state-dir`` (None without one)."""
    if settings.state_dir is None:
        return None
    config = settings.engine
    return StateKeeper(settings.state_dir, config.prefix, str(config.partition), settings.state_interval_s)


def start_engine(settings: Settings) -> tuple[Engine, StateKeeper | None]:
    """The engine of the settings, restored from their state directory, and its keeper.

    Raises :class:`service.config.ConfigError` naming a bad engine parameter, and
    ``RuntimeError`` naming a state directory that cannot be used."""
    state = state_keeper(settings)
    try:
        if state is not None:
            state.prepare()  # before the engine (and its correlation process) starts
            lock_directory(state.directory)  # one process to a directory (its epoch, its file)
        return build_engine(settings.engine, settings.two_processes, state), state
    except OSError as exc:  # the state directory (the only file the engine's start opens)
        if settings.state_dir is None:
            raise
        why = exc.strerror or exc
        raise RuntimeError(f"state directory {settings.state_dir} cannot be used: {why}") from exc
