"""The tools around a service: ``record`` and ``replay`` (MCAP), ``assess`` (radar performance
over a recording) and ``asterix`` (the ASTERIX bridge).  Their Zenoh sessions are clients
unless told otherwise."""

from __future__ import annotations

import argparse

from service import recording
from service.asterix import command as asterix
from service.cli.common import (
    Commands,
    add_command,
    settings_from,
    stop_on_signals,
    zenoh_flags,
    zenoh_options,
)
from service.recording.assess import add_assess_arguments, assess_main


def register(commands: Commands) -> None:
    rec = add_command(
        commands, "record", record_main, help="record samples under {prefix}/** into an MCAP file"
    )
    zenoh_flags(rec, default_mode="client")
    recording.add_record_arguments(rec)
    rep = add_command(commands, "replay", replay_main, help="republish an MCAP recording")
    zenoh_flags(rep, default_mode="client")
    recording.add_replay_arguments(rep)
    add_assess_arguments(
        add_command(
            commands, "assess", assess_main, help="radar performance against ADS-B / AIS over a recording"
        )
    )
    ast = add_command(
        commands,
        "asterix",
        asterix_main,
        help="bridge an ASTERIX feed (CAT048/034/021; UDP, pcap, raw) to the service",
    )
    zenoh_flags(ast, default_mode="client")
    asterix.add_arguments(ast)


def record_main(args: argparse.Namespace) -> int:
    settings = settings_from(args)
    args.prefix = settings.prefix
    return int(recording.record_main(args, zenoh_options(settings, default_mode="client")))


def replay_main(args: argparse.Namespace) -> int:
    settings = settings_from(args)
    args.prefix = settings.prefix
    return int(recording.replay_main(args, zenoh_options(settings, default_mode="client")))


def asterix_main(args: argparse.Namespace) -> int:
    settings = settings_from(args)
    options = zenoh_options(settings, default_mode="client")
    return asterix.asterix_main(args, options, settings.prefix, settings.sites, stop_on_signals())
