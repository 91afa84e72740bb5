"""The operator's helpers: ``config`` (the effective engine configuration), ``partition`` (who
owns what among N workers), ``schemas`` (the payloads' JSON Schemas) and ``healthcheck``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pydantic import ValidationError

from service.cli.common import Commands, add_command, invalid_settings, settings_from
from service.pipeline.partition import PAIR_KM
from service.settings import Settings


def register(commands: Commands) -> None:
    add_command(
        commands,
        "healthcheck",
        healthcheck_main,
        help="exit 0 if the local service answers GET /healthz (container HEALTHCHECK)",
    )
    cfg = add_command(
        commands, "config", config_main, help="the engine's effective configuration, every parameter"
    )
    cfg.add_argument("--show", action="store_true", help="print it (YAML) with its defaults")
    cfg.add_argument("--config", metavar="FILE", help="a config file to apply (TOML/YAML/JSON)")
    cfg.add_argument("--format", choices=("yaml", "json"), default="yaml")
    part = add_command(
        commands, "partition", partition_main, help="which worker of N owns which radar and radar pair"
    )
    part.add_argument("--count", type=int, required=True, metavar="N", help="number of workers")
    part.add_argument("--sites", metavar="FILE", help="the radars of a sites file (a JSON list of RadarSite)")
    part.add_argument("ids", nargs="*", metavar="ID", help="radar ids")
    part.add_argument(
        "--reference",
        action="append",
        default=[],
        metavar="ID",
        help="a reference source (AIS, ADS-B): its pairs with the radars go with each radar's "
        "owner (repeatable)",
    )
    part.add_argument(
        "--salt", type=int, default=0, metavar="S", help="the salt of the hashing (TOPOFUSION_PARTITION_SALT)"
    )
    part.add_argument(
        "--balance",
        action="store_true",
        help="find the salt that shares the radars and radar pairs most evenly, and use it",
    )
    part.add_argument(
        "--pair-km",
        type=float,
        default=PAIR_KM,
        metavar="KM",
        help=f"with --sites: count only pairs of sites at most this far apart, those whose cover can "
        f"overlap (default {PAIR_KM:g}: two 300 km radars)",
    )
    sch = add_command(
        commands, "schemas", schemas_main, help="write JSON Schemas of every payload into schemas/"
    )
    sch.add_argument("--out", default="schemas", help="output folder (default ./schemas)")


def partition_main(args: argparse.Namespace) -> int:
    """``topofusion partition --count N``: each worker's radars and radar pairs (rendezvous
    hashing, contract §6), with each worker's share; ``--balance``: with the salt that shares
    them most evenly."""
    from service.config import load_sites
    from service.pipeline.partition import (
        MAX_SALT,
        MAX_WORKERS,
        Partition,
        balanced_salt,
        candidate_pairs,
        pair_name,
        shares,
    )

    if not 1 <= args.count <= MAX_WORKERS or not 0 <= args.salt <= MAX_SALT:
        print(f"--count must be in 1..{MAX_WORKERS} and --salt in 0..{MAX_SALT}", file=sys.stderr)
        return 2
    sites = {s.radar_id: s for s in load_sites(args.sites)} if args.sites else {}
    references = sorted(set(args.reference))
    ids = sorted((set(args.ids) | set(sites)) - set(references))
    if not ids:
        print("give radar ids or --sites FILE", file=sys.stderr)
        return 2

    positions = {rid: (site.latitude_deg, site.longitude_deg) for rid, site in sites.items()}
    pairs = candidate_pairs(ids, positions, args.pair_km * 1000.0)
    salt = balanced_salt(args.count, ids, pairs) if args.balance else args.salt
    if args.balance:
        print(f"salt {salt}: give every worker TOPOFUSION_PARTITION_SALT={salt} (or --partition-salt {salt})")
    share = shares(args.count, salt, ids, pairs)
    for k in range(1, args.count + 1):
        p = Partition(k, args.count, salt)
        radars = [i for i in ids if p.owns(i)]
        owned = [f"{a}/{b}" for a, b in pairs if p.owns_pair(a, b)]
        print(
            f"worker {k}/{args.count}: {len(radars)} radars, {len(owned)} of {len(pairs)} pairs "
            f"(share {share[k - 1]:.3f})"
        )
        print(f"  radars: {' '.join(radars) or '-'}")
        print(f"  pairs:  {' '.join(owned) or '-'}")
        if references:  # (each radar's owner's, whatever the names hash to)
            with_references = [pair_name(r, x) for r in radars for x in references]
            print(f"  with references: {' '.join(with_references)}")
    return 0


def config_main(args: argparse.Namespace) -> int:
    """``topofusion config --show``: the effective settings and engine configuration (file,
    environment, flags and defaults; secrets redacted), validated; exit 2 with the key named
    when it is not valid."""
    settings = settings_from(args)
    text = settings.render(args.format)
    check_start(settings)
    if not args.show:
        print("configuration is valid (use --show to print it)", file=sys.stderr)
        return 0
    print(text, end="")
    return 0


def check_start(settings: Settings) -> None:
    """What ``run`` checks at start beyond the settings' own types, checked here too (a
    ValueError naming the setting): the engine built from them (a name only the engine knows,
    such as the initiator's), the Zenoh configuration taken by Zenoh (the file, the endpoints,
    its TLS files there), the state directory usable."""
    from service.startup import build_engine, state_keeper
    from service.transport.session import ZenohOptions

    try:
        build_engine(settings.engine).close()
    except ValueError as exc:
        raise ValueError(f"engine configuration: {exc}") from None
    ZenohOptions.from_settings(settings)  # (what Zenoh refuses of the file, endpoints, TLS files)
    keeper = state_keeper(settings)
    if keeper is not None:
        try:
            keeper.check()
        except OSError as exc:
            why = exc.strerror or exc
            raise ValueError(f"TOPOFUSION_STATE_DIR {settings.state_dir} cannot be used: {why}") from None


def schemas_main(args: argparse.Namespace) -> int:
    from service.schema_files import write_schemas

    written = write_schemas(Path(args.out))
    print(f"schemas: wrote {len(written)} files into {args.out}", file=sys.stderr)
    return 0


def healthcheck_main(args: argparse.Namespace) -> int:
    import urllib.request

    try:  # (the contract's exit status is 0 or 1: a setting it cannot read is "not healthy")
        settings = Settings()
    except ValidationError as exc:
        print(f"healthcheck: {invalid_settings(exc)}", file=sys.stderr)
        return 1
    except (ValueError, OSError) as exc:  # (ConfigError is a ValueError)
        print(f"healthcheck: {exc}", file=sys.stderr)
        return 1
    host = "127.0.0.1" if settings.http_host in ("0.0.0.0", "::") else settings.http_host
    try:
        with urllib.request.urlopen(f"http://{host}:{settings.http_port}/healthz", timeout=2) as resp:
            return 0 if resp.status == 200 else 1
    except OSError as exc:
        print(f"healthcheck: {exc}", file=sys.stderr)
        return 1
