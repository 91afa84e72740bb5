"""``topofusion evaluate``: the Monte Carlo studies (topofusion_lab.evaluation), tables and PNG
figures; each study writes ``{study}.md`` and its PNGs, ``REPORT.md`` joins them."""

from __future__ import annotations

import argparse
import importlib
import sys
import time
from pathlib import Path

from service.cli.common import Commands, add_command

#: The studies, each a module of topofusion_lab.evaluation with ``run(out, runs, seed, progress)``,
#: in the order of the report.
STUDIES = ("initiation", "correlation", "dense", "adsb", "system", "formation")


def register(commands: Commands) -> None:
    ev = add_command(
        commands, "evaluate", evaluate_main, help="Monte Carlo evaluation: tables and PNG figures"
    )
    ev.add_argument("--out", default="evaluation", help="output folder (default ./evaluation)")
    ev.add_argument(
        "--runs",
        type=int,
        help="Monte Carlo runs per point (default: each study's full count; the correlation "
        "study takes at least 10)",
    )
    ev.add_argument("--seed", type=int, default=0)
    ev.add_argument("--only", choices=STUDIES, help="run one study only")


def evaluate_main(args: argparse.Namespace) -> int:
    studies = [args.only] if args.only else list(STUDIES)
    # every study's module before anything is written
    modules = {name: importlib.import_module(f"topofusion_lab.evaluation.{name}") for name in studies}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cmd = " ".join(["topofusion evaluate", *getattr(args, "argv", [])])
    for name, module in modules.items():
        print(f"evaluate: {name} ...", file=sys.stderr, flush=True)
        t0 = time.monotonic()
        section = module.run(
            out, runs=args.runs, seed=args.seed, progress=lambda m: print(m, file=sys.stderr)
        )
        took = time.monotonic() - t0
        (out / f"{name}.md").write_text(f"{section}\n\n_Made by `{cmd}` in {took:.0f} s._\n")
    parts = [(out / f"{n}.md").read_text() for n in STUDIES if (out / f"{n}.md").is_file()]
    report = out / "REPORT.md"
    report.write_text("# TopoFusion evaluation\n\n" + "\n\n".join(parts))
    print(f"evaluate: wrote {report}", file=sys.stderr)
    return 0
