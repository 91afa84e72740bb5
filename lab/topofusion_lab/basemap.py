"""The operator picture's coastlines and borders (``service/api/static/basemap.json``).

Source: Natural Earth 1:50m (public domain), as the TopoJSON of the npm package
``world-atlas@2.0.2`` (ISC licence, Mike Bostock; ``countries-50m.json``: its ``land`` and
``countries`` objects share one set of arcs).  Reproduce the committed asset with::

    PYTHONPATH=lab .venv/bin/python -m topofusion_lab.basemap          # runs `npm pack`
    PYTHONPATH=lab .venv/bin/python -m topofusion_lab.basemap --tarball world-atlas-2.0.2.tgz

The output is a compact format of our own rather than GeoJSON (a third of the size, and the
page needs no GeoJSON reader): ``{"unit": u, "land": [ring, ...], "borders": [line, ...]}``
where every ring and line is a flat list of integers ``[x0, y0, dx1, dy1, ...]``: longitude
and latitude in units of ``u`` degrees, each point after the first as the difference from the
one before.  ``land`` are the outer and inner rings of the land polygons (filled even-odd,
their outlines are the coastlines); ``borders`` are the arcs two different countries share
(land borders, without the coast).  Each arc is simplified once (Douglas-Peucker) before
rings and lines are assembled from it, so that a border and the coast meet where they did.
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import subprocess
import tarfile
import tempfile
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

PACKAGE = "world-atlas@2.0.2"
#: sha256 of ``npm pack world-atlas@2.0.2`` (what the committed asset was made from).
TARBALL_SHA256 = "032e7765f2ce00edaeafec23ff22bc3b77e42987c257da944cc585b452c05b97"
MEMBER = "package/countries-50m.json"
OUT = Path(__file__).resolve().parents[2] / "service" / "api" / "static" / "basemap.json"
#: Douglas-Peucker tolerance (degrees, about 2 km): finer than a pixel at the picture's usual
#: zoom on a radar network (a few hundred metres per pixel is the closest anyone looks at a
#: coastline there), coarse enough to keep the asset a few hundred KB.
TOLERANCE_DEG = 0.02
#: Coordinates are quantised to this many degrees (about 1 km): below the tolerance.
UNIT_DEG = 0.01
#: Rings with a smaller area (square degrees, about 25 km^2) are left out: islets a radar
#: picture does not need.
MIN_RING_AREA_DEG2 = 0.002


def read_topology(tarball: Path | None) -> dict[str, Any]:
    """``countries-50m.json`` of the package tarball (``npm pack`` it when not given)."""
    if tarball is None:
        with tempfile.TemporaryDirectory() as tmp:
            subprocess.run(["npm", "pack", PACKAGE], cwd=tmp, check=True, capture_output=True)
            (packed,) = Path(tmp).glob("world-atlas-*.tgz")
            data = packed.read_bytes()
    else:
        try:
            data = tarball.read_bytes()
        except OSError as exc:
            raise SystemExit(
                f"--tarball {tarball}: {exc.strerror} (make it with `npm pack {PACKAGE}`, or leave "
                "--tarball out to have npm fetch the package)"
            ) from None
    digest = hashlib.sha256(data).hexdigest()
    if digest != TARBALL_SHA256:
        raise SystemExit(f"{PACKAGE}: sha256 {digest}, expected {TARBALL_SHA256}")
    with tarfile.open(fileobj=io.BytesIO(data), mode="r:gz") as tar:
        member = tar.extractfile(MEMBER)
        assert member is not None, MEMBER
        topology: dict[str, Any] = json.load(member)
    return topology


def decode_arcs(topology: dict[str, Any]) -> list[np.ndarray]:
    """Every arc as an (n, 2) array of longitude, latitude (TopoJSON's quantised deltas)."""
    scale = np.asarray(topology["transform"]["scale"], dtype=float)
    translate = np.asarray(topology["transform"]["translate"], dtype=float)
    return [np.cumsum(np.asarray(arc, dtype=float), axis=0) * scale + translate for arc in topology["arcs"]]


def simplify(points: np.ndarray, tolerance: float) -> np.ndarray:
    """Douglas-Peucker: the points of ``points`` within ``tolerance`` of the line kept
    (an iterative stack instead of recursion: the longest arcs have thousands of points)."""
    n = len(points)
    if n < 3:
        return points
    keep = np.zeros(n, dtype=bool)
    keep[0] = keep[-1] = True
    stack = [(0, n - 1)]
    while stack:
        i, j = stack.pop()
        if j - i < 2:
            continue
        a, b = points[i], points[j]
        seg = b - a
        inner = points[i + 1 : j] - a
        length = float(np.hypot(*seg))
        if length == 0.0:
            dist = np.hypot(inner[:, 0], inner[:, 1])
        else:
            dist = np.abs(seg[0] * inner[:, 1] - seg[1] * inner[:, 0]) / length
        k = int(np.argmax(dist))
        if dist[k] > tolerance:
            m = i + 1 + k
            keep[m] = True
            stack += [(i, m), (m, j)]
    return points[keep]


def chain(arcs: list[np.ndarray], refs: list[int]) -> np.ndarray:
    """The points of arcs ``refs`` joined (``~i``: arc ``i`` reversed), shared ends once."""
    parts = [arcs[r] if r >= 0 else arcs[~r][::-1] for r in refs]
    return np.concatenate([parts[0], *(p[1:] for p in parts[1:])])


def polygons(geometry: dict[str, Any]) -> Iterator[list[list[int]]]:
    """The polygons (lists of rings of arc references) of a TopoJSON geometry."""
    kind = geometry["type"]
    if kind == "Polygon":
        yield geometry["arcs"]
    elif kind == "MultiPolygon":
        yield from geometry["arcs"]
    elif kind == "GeometryCollection":
        for g in geometry["geometries"]:
            yield from polygons(g)


def ring_area(ring: np.ndarray) -> float:
    x, y = ring[:, 0], ring[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def encode(points: np.ndarray) -> list[int]:
    """A flat list of quantised, delta-encoded coordinates; repeated points dropped."""
    q = np.rint(points / UNIT_DEG).astype(np.int64)
    keep = np.ones(len(q), dtype=bool)
    keep[1:] = np.any(q[1:] != q[:-1], axis=1)
    q = q[keep]
    deltas = np.concatenate([q[:1], np.diff(q, axis=0)])
    return [int(v) for v in deltas.ravel()]


def basemap(topology: dict[str, Any]) -> dict[str, Any]:
    arcs = [simplify(a, TOLERANCE_DEG) for a in decode_arcs(topology)]
    land: list[list[int]] = []
    for polygon in polygons(topology["objects"]["land"]):
        for refs in polygon:
            ring = chain(arcs, refs)
            if len(ring) >= 4 and ring_area(ring) >= MIN_RING_AREA_DEG2:
                land.append(encode(ring))
    # an arc two different countries use is a land border (TopoJSON's mesh with a != b)
    users: Counter[int] = Counter()
    for geometry in topology["objects"]["countries"]["geometries"]:
        used = {r if r >= 0 else ~r for polygon in polygons(geometry) for ring in polygon for r in ring}
        users.update(used)
    borders = [encode(arcs[i]) for i, n in sorted(users.items()) if n >= 2]
    return {
        "source": f"Natural Earth 1:50m (public domain), via the npm package {PACKAGE} (ISC)",
        "unit": UNIT_DEG,
        "land": land,
        "borders": [b for b in borders if len(b) >= 4],
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tarball", type=Path, help=f"`npm pack {PACKAGE}`'s file (default: run npm pack)")
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args(argv)
    result = basemap(read_topology(args.tarball))
    text = json.dumps(result, separators=(",", ":"))
    args.out.write_text(text + "\n", encoding="utf-8")
    points = sum(len(r) for r in result["land"] + result["borders"]) // 2
    print(
        f"{args.out}: {len(text) / 1024:.0f} KiB, {len(result['land'])} rings, "
        f"{len(result['borders'])} borders, {points} points"
    )


if __name__ == "__main__":
    main()
