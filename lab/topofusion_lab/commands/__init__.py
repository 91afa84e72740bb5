"""The lab's commands of ``topofusion``: ``demo``, ``simulate`` and ``evaluate``.

``topofusion`` finds :func:`register` through the entry point ``lab`` of the group
``topofusion.commands`` (lab/pyproject.toml).  It runs at every start of ``topofusion``, so these
modules import only what parsing needs; the simulator, the publisher and the studies are imported
when their command runs.
"""

from __future__ import annotations

from service.cli.common import Commands
from topofusion_lab.commands import demo, evaluate, simulate


def register(commands: Commands) -> None:
    demo.register(commands)
    simulate.register(commands)
    evaluate.register(commands)
