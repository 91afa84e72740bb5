"""Command groups of other distributions, found through the entry points ``topofusion.commands``.

Each entry point names a ``register(commands)`` function, as the runtime's own group modules
have (:mod:`service.cli.common`).  The runtime depends on none of them; the one it knows of is
the lab (the distribution ``topofusion-lab``, lab/ in a checkout: the simulator, its scenarios
and the evaluation), which adds ``demo``, ``simulate`` and ``evaluate``.  Where the lab is not
installed, those commands still exist: each exits 2 with one line saying how to install it.
"""

from __future__ import annotations

import argparse
import sys
import textwrap
from dataclasses import dataclass
from importlib import metadata

from service.cli.common import Commands, add_command

#: The entry point group of ``topofusion`` command groups.
ENTRY_POINTS = "topofusion.commands"


@dataclass(frozen=True)
class KnownGroup:
    """A group of another distribution whose commands ``topofusion`` names where it is absent."""

    entry_point: str
    commands: tuple[str, ...]
    #: what the commands need
    needs: str
    #: how to install it, said where it is not
    install: str
    #: more on that, for ``--help``
    install_more: str = ""
    #: flags that answer on their own (as ``--help`` does), named in the message where given
    own_flags: tuple[str, ...] = ()


LAB = KnownGroup(
    entry_point="lab",
    commands=("demo", "simulate", "evaluate"),
    needs="the TopoFusion lab (topofusion_lab: simulator, scenarios, evaluation)",
    install="install it from a checkout with `pip install -e lab`",
    install_more="the runtime and the lab together, as `make install-demo` does: `pip install -e . -e lab`",
    own_flags=("--list",),  # simulate --list
)
KNOWN = {LAB.entry_point: LAB}


def register(commands: Commands) -> str:
    """Add every installed group's commands and, for a known group that is not installed, its
    commands that say so; what ``topofusion --help`` says of the groups, after the commands."""
    notes = []
    seen = set()
    for ep in sorted(metadata.entry_points(group=ENTRY_POINTS), key=lambda ep: ep.name):
        before = set(commands.choices)
        try:
            ep.load()(commands)
        except Exception as exc:
            if isinstance(exc, ModuleNotFoundError) and _root(exc.name or "") == _root(ep.module):
                continue  # its package is gone (a stale install): as if it were not installed
            problem = f"is installed but cannot be loaded ({type(exc).__name__}: {exc})"
            notes.append(f"the command group {ep.name!r} ({ep.value}) {problem}")
            if ep.name in KNOWN:
                _absent(commands, KNOWN[ep.name], problem)
        else:
            added = ", ".join(c for c in commands.choices if c not in before)
            source = f"{ep.dist.name} {ep.dist.version}" if ep.dist is not None else ep.value
            notes.append(f"{added}: from {source} (entry point {ep.name!r} of {ENTRY_POINTS})")
        seen.add(ep.name)
    for name, group in KNOWN.items():
        if name not in seen:
            _absent(commands, group, None)
            more = f" ({group.install_more})" if group.install_more else ""
            notes.append(
                f"not installed: {', '.join(group.commands)}; they need {group.needs}; {group.install}{more}"
            )
    return "\n".join(textwrap.fill(note, width=78, subsequent_indent="  ") for note in notes)


def _root(module: str) -> str:
    return module.partition(".")[0]


def _absent(commands: Commands, group: KnownGroup, problem: str | None) -> None:
    """The commands of a group that is not there (``problem``: why, if it is installed): each
    takes any arguments and exits 2 saying why it cannot run."""
    where = f"which is not installed; {group.install}" if problem is None else f"which {problem}"
    for command in group.commands:
        if command in commands.choices:  # (added by the group before it broke)
            continue

        def handler(args: argparse.Namespace, command: str = command) -> int:
            given = [flag for flag in group.own_flags if flag in args.arguments]
            said = " ".join([f"`topofusion {command}", *given]) + "`"
            print(f"topofusion: {said} needs {group.needs}, {where}", file=sys.stderr)
            return 2

        # every argument is taken as it is (no prefix characters: no options, not even --help)
        parser = add_command(commands, command, handler, prefix_chars="\0", add_help=False)
        parser.add_argument("arguments", nargs="*")
