"""A purpose-built ASTERIX decoder for the bridge: CAT048 plots, CAT034 service messages, CAT021 ADS-B.

Specifications (EUROCONTROL Specification for Surveillance Data Exchange, ASTERIX):
  - Part 4, Category 048 "Monoradar Target Reports", edition 1.32 (records of 1.27-1.31 frame
    the same way);
  - Part 2b, Category 034 "Transmission of Monoradar Service Messages", edition 1.29;
  - Part 12, Category 021 "ADS-B Target Reports", edition 2.7 (2.1-2.6 frame the same way).
The length tables are in ``service.asterix.uap``; docs/asterix.md ("The decoder: survey and
choice") is the survey that chose this design over the packages on PyPI (speed, licence).

Only the fields the bridge publishes are extracted (the report tuples below); every other item
is stepped over with the exact length rule of its edition, so that no known item is rejected.

**Speed.** Each distinct FSPEC of a category is turned into one straight-line Python function
(source generated from per-item snippets, compiled once and cached): no per-item dispatch at run
time.  A radar sends a handful of distinct FSPECs, so the cache stays small.  It is bounded
(``_Category.cache_max`` functions of about 3 kB; no FSPEC longer than the UAP needs is kept)
so that hostile input cannot grow memory without bound, and an FSPEC is compiled (about 0.2 ms)
on its second sighting only, so that corrupt or hostile data does not make the decoder compile
for every record.  The first sighting, and every FSPEC once the cache is full, go through the
generic path: an FSPEC walk with one ``if``/``elif`` branch per FRN, generated from the same
snippets (one source of truth for both paths).

**Robustness.** A data block is atomic: if any record of it cannot be framed (FSPEC past the
block, an FRN that is spare or beyond the UAP, an item past the block's LEN, an inconsistent
repetitive/compound/explicit length, or the mandatory data source identifier missing), none of
its records is kept and ``errors["undecodable"]`` counts the block.  A header that cannot be
read (an empty datagram too) or a LEN < 3 or beyond the bytes left counts as ``"truncated"``
and ends the walk (nothing after it can be trusted to start a block); another category is
skipped whole by its LEN and counted as ``"unsupported_category"``.  Every block is decoded
from its own slice of the input, so a record overrunning its block raises IndexError (caught)
instead of reading the next block.  No input raises and every loop advances by at least one
octet: the cost is linear in the input.

**Cost per datagram.**  ``decode_datagram(..., max_records=N)`` stops at N records: the block
that would go past them is dropped whole (atomic, as above), and the blocks after it are not
looked at; ``errors["too_many_records"]`` counts it.  The smallest record (FSPEC and SAC/SIC)
is 3 octets, so 64 KiB of them are 21 800 records and about 50 ms of work; the bridge caps a
live UDP datagram (``service.asterix.command.MAX_UDP_RECORDS``) so that a flood of such
datagrams costs each at most a few ms.
"""

from __future__ import annotations

import collections
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, NamedTuple

from service.asterix.uap import UAP021, UAP034, UAP048, FramingError, Uap, fspec_octets, skip, skip_code

#: 1 NM = 1852 m and 1 ft = 0.3048 m exactly (international definitions).
NM_M = 1852.0
FT_M = 0.3048


class Cat048Report(NamedTuple):
    """One CAT048 target report (fields absent from the record are None)."""

    sac: int
    sic: int
    tod_s: float | None  # I048/140 time of day, s since midnight UTC (1/128 s)
    rho_m: float | None  # I048/040 slant range (1/256 NM) in m
    theta_deg: float | None  # I048/040 azimuth (360/2^16), [0, 360)
    mode_3a: str | None  # I048/070, 4 octal digits
    flight_level: float | None  # I048/090 (1/4 FL)
    mode_s: str | None  # I048/220 ICAO address, 6 lower-case hex digits
    height_m: float | None  # I048/110 3-D height (25 ft) in m
    test_target: bool  # I048/020 TST (False if absent)


class Cat034Message(NamedTuple):
    """One CAT034 service message."""

    sac: int
    sic: int
    message_type: int  # I034/000: 1 north marker, 2 sector crossing, 3 geographical filtering, 4 jamming
    tod_s: float | None  # I034/030 (1/128 s)
    sector_deg: float | None  # I034/020 (360/2^8)


class Cat021Report(NamedTuple):
    """One CAT021 ADS-B report."""

    sac: int
    sic: int
    tod_s: float | None  # I021/073, else I021/071, else I021/077 (1/128 s)
    icao24: str | None  # I021/080, 6 lower-case hex digits
    latitude_deg: float | None  # I021/131 (180/2^30), else I021/130 (180/2^23)
    longitude_deg: float | None
    geometric_height_m: float | None  # I021/140 (6.25 ft) in m
    flight_level: float | None  # I021/145 (1/4 FL)
    mode_3a: str | None = None  # I021/070, 4 octal digits


@dataclass
class Decoded:
    """What the decoder appends to: the records of the blocks that framed, and the drop counts."""

    cat048: list[Cat048Report] = field(default_factory=list)
    cat034: list[Cat034Message] = field(default_factory=list)
    cat021: list[Cat021Report] = field(default_factory=list)
    errors: collections.Counter[str] = field(default_factory=collections.Counter)  # cause -> blocks
    blocks: int = 0  # data blocks seen (including dropped and unsupported ones)


class _TooManyRecordsError(Exception):
    """A block holds more records than the datagram's budget has left."""


# A record decoder: (block, offset of its first item, append) -> offset after the record.
_RecordFn = Callable[[bytes, int, Callable[[Any], None]], int]

#: Mode-3/A strings by 12-bit code: a table lookup instead of formatting every record.
_M3A = tuple(f"{i:04o}" for i in range(4096))


class _Snippet(NamedTuple):
    """How one item's fields are extracted into locals of the generated code.

    A fixed-size item (``size`` octets) is read with ``struct``: ``fmt`` (big-endian) unpacks its
    octets into the locals ``raws``, then ``lines`` compute the fields from them.  Consecutive
    fixed items are read by one ``unpack_from`` (fewer bytecodes than indexing octet by octet),
    and ``p`` is only advanced before a variable-length item and at the end of the record.  A
    variable-length item (``size`` None) has lines that read at ``p`` and step ``p`` over it.
    """

    size: int | None
    names: tuple[str, ...]  # the fields (locals) the lines set
    lines: tuple[str, ...]
    fmt: str = ""
    raws: tuple[str, ...] = ()


def _tod(name: str) -> _Snippet:
    # 24-bit unsigned, 1/128 s: struct has no 3-octet integer, so 1 + 2 octets
    return _Snippet(
        3, (name,), (f"{name} = ({name}_ << 16 | {name}__) * 0.0078125",), "BH", (f"{name}_", f"{name}__")
    )


def _lat_lon24(lat: str, lon: str) -> _Snippet:
    # 24-bit two's complement each: a signed high octet and an unsigned low pair
    lsb = 180 / 2**23
    return _Snippet(
        6,
        (lat, lon),
        (f"{lat} = ({lat}_ << 16 | {lat}__) * {lsb!r}", f"{lon} = ({lon}_ << 16 | {lon}__) * {lsb!r}"),
        "bHbH",
        (f"{lat}_", f"{lat}__", f"{lon}_", f"{lon}__"),
    )


# Extraction snippets by FRN.  ``b`` is the block.  Two's complement of an n-bit field x:
# (x ^ 2^(n-1)) - 2^(n-1).  Scale factors are the items' LSBs (a product by a power of two is
# exact; so is the NM -> m factor 1852/256 = 7.234375).
_S048 = {
    1: _Snippet(2, ("sac", "sic"), (), "BB", ("sac", "sic")),
    2: _tod("tod"),
    # TST is the first bit of the first extent; the descriptor has up to 6 one-octet parts.
    3: _Snippet(
        None,
        ("tst",),
        (
            "tst = False",
            "if b[p] & 1:",
            "    tst = b[p + 1] > 127",
            "    p += 1",
            "    while b[p] & 1:",
            "        p += 1",
            "p += 1",
        ),
    ),
    4: _Snippet(
        4,
        ("rho", "theta"),
        (f"rho = rho_ * {NM_M / 256!r}", f"theta = theta_ * {360 / 65536!r}"),
        "HH",
        ("rho_", "theta_"),
    ),
    5: _Snippet(2, ("m3a",), ("m3a = _M3A[m3a_ & 4095]",), "H", ("m3a_",)),
    6: _Snippet(2, ("fl",), ("fl = (((fl_ & 16383) ^ 8192) - 8192) * 0.25",), "H", ("fl_",)),
    8: _Snippet(3, ("adr",), ("adr = adr_.hex()",), "3s", ("adr_",)),
    19: _Snippet(2, ("h",), (f"h = (((h_ & 16383) ^ 8192) - 8192) * {25 * FT_M!r}",), "H", ("h_",)),
}
_L048 = {"sac": "None", "sic": "None", "tod": "None", "rho": "None", "theta": "None"}
_L048 |= {"m3a": "None", "fl": "None", "adr": "None", "h": "None", "tst": "False"}

_S034 = {
    1: _S048[1],
    2: _Snippet(1, ("mt",), (), "B", ("mt",)),
    3: _tod("tod"),
    4: _Snippet(1, ("sector",), (f"sector = sector_ * {360 / 256!r}",), "B", ("sector_",)),
}
_L034 = dict.fromkeys(("sac", "sic", "mt", "tod", "sector"), "None")

_S021 = {
    1: _S048[1],
    5: _tod("t071"),
    6: _lat_lon24("la0", "lo0"),
    7: _Snippet(
        8,
        ("la1", "lo1"),
        (f"la1 = la1_ * {180 / 2**30!r}", f"lo1 = lo1_ * {180 / 2**30!r}"),
        "ii",
        ("la1_", "lo1_"),
    ),
    11: _Snippet(3, ("icao",), ("icao = icao_.hex()",), "3s", ("icao_",)),
    12: _tod("t073"),
    16: _Snippet(2, ("gh",), (f"gh = gh_ * {6.25 * FT_M!r}",), "h", ("gh_",)),
    19: _S048[5],  # I021/070 Mode 3/A: the same 12 bits as I048/070
    21: _Snippet(2, ("fl",), ("fl = fl_ * 0.25",), "h", ("fl_",)),
    28: _tod("t077"),
}
_L021 = dict.fromkeys(("sac", "sic", "t071", "t073", "t077", "icao", "la0", "lo0", "la1", "lo1"), "None")
_L021 |= dict.fromkeys(("gh", "fl", "m3a"), "None")

# Bit k of an FSPEC octet (0 = most significant) -> its offset in the octet's 7 FRNs.
_BITS = tuple(tuple(k for k in range(7) if o & (0x80 >> k)) for o in range(256))


class _Category:
    """One category's decoder: UAP, extraction snippets, FSPEC cache and generic path."""

    cache_max = 4096

    def __init__(
        self,
        cat: int,
        uap: Uap,
        result: type,
        snippets: dict[int, _Snippet],
        local_defaults: dict[str, str],
        result_expr: str,
        mandatory: tuple[int, ...],
    ) -> None:
        self.cat = cat
        self.attr = f"cat{cat:03d}"
        self.uap = uap
        self.result = result
        self.snippets = snippets
        self.local_defaults = local_defaults
        self.result_expr = result_expr
        self.mandatory = mandatory
        self.fspec_max = fspec_octets(uap)
        self.cache: dict[bytes, _RecordFn] = {}
        self.seen: set[bytes] = set()  # FSPECs decoded once by the generic path (bounded)
        self.namespace = {
            "_new": tuple.__new__,
            "_R": result,
            "_M3A": _M3A,
            "_BITS": _BITS,
            "UAP": uap,
            "skip": skip,
            "FramingError": FramingError,
        }
        self.generic: _RecordFn = self._generic()

    def frns(self, fspec: bytes) -> list[int]:
        """The FRNs an FSPEC names; FramingError if one is spare or beyond the UAP, or if the
        FSPEC is longer than the UAP needs or lacks a mandatory item."""
        if len(fspec) > self.fspec_max:
            raise FramingError(f"CAT{self.cat:03d} FSPEC of {len(fspec)} octets")
        frns = [7 * i + k + 1 for i, o in enumerate(fspec) for k in _BITS[o]]
        n = len(self.uap)
        for frn in frns:
            if frn >= n or self.uap[frn] is None:
                raise FramingError(f"CAT{self.cat:03d} FRN {frn} undefined")
        for frn in self.mandatory:
            if frn not in frns:
                raise FramingError(f"CAT{self.cat:03d} FRN {frn} missing")
        return frns

    def _fixed(self, frn: int) -> _Snippet | None:
        """Item ``frn`` as a fixed-size snippet (a skipped fixed item: pad octets), else None."""
        snippet = self.snippets.get(frn)
        if snippet is not None:
            return snippet if snippet.size is not None else None
        item = self.uap[frn]
        assert item is not None
        return _Snippet(item.size, (), (), f"{item.size}x") if item.kind == "F" else None

    def _variable(self, frn: int) -> list[str]:
        """Lines stepping ``p`` over the variable-length item ``frn`` (extracting its fields)."""
        snippet = self.snippets.get(frn)
        if snippet is not None:
            return list(snippet.lines)
        item = self.uap[frn]
        assert item is not None
        return skip_code(item, f"UAP[{frn}]")

    def _read(self, run: list[_Snippet], ns: dict[str, Any]) -> tuple[list[str], int]:
        """Lines reading the consecutive fixed items ``run`` at ``p`` with one unpack_from (its
        Struct is put into ``ns``), and their total size."""
        size = sum(s.size or 0 for s in run)
        raws = [r for s in run for r in s.raws]
        if not raws:
            return [], size
        fmt = ">" + "".join(s.fmt for s in run).rstrip("0123456789x")  # trailing pads: not read
        name = f"_u{len(ns)}"
        ns[name] = struct.Struct(fmt).unpack_from
        return [f"{', '.join(raws)}, = {name}(b, p)", *(line for s in run for line in s.lines)], size

    def _compile(self, src: list[str], ns: dict[str, Any], name: str, label: str) -> _RecordFn:
        exec(compile("\n".join(src), label, "exec"), ns)
        fn: _RecordFn = ns[name]
        return fn

    def source(self, fspec: bytes) -> tuple[list[str], dict[str, Any]]:
        """The source of the straight-line decoder of one record's items after ``fspec``, and
        its namespace."""
        frns = self.frns(fspec)
        ns = dict(self.namespace)
        assigned = {n for frn in frns if frn in self.snippets for n in self.snippets[frn].names}
        body = [f"{n} = {v}" for n, v in self.local_defaults.items() if n not in assigned]
        run: list[_Snippet] = []
        for frn in frns:
            fixed = self._fixed(frn)
            if fixed is not None:
                run.append(fixed)
                continue
            lines, k = self._read(run, ns)
            body += lines + ([f"p += {k}"] if k else []) + self._variable(frn)
            run = []
        lines, k = self._read(run, ns)
        body += lines
        body += [f"append(_new(_R, {self.result_expr}))", f"return p + {k}" if k else "return p"]
        return ["def _record(b, p, append):", *("    " + line for line in body)], ns

    def compile(self, fspec: bytes) -> _RecordFn:
        """The straight-line decoder of one record's items after ``fspec`` (FramingError if the
        FSPEC itself is invalid: ``frns``)."""
        src, ns = self.source(fspec)
        return self._compile(src, ns, "_record", f"<CAT{self.cat:03d} FSPEC {fspec.hex()}>")

    def _generic(self) -> _RecordFn:
        """The uncached path: ``p`` at the FSPEC; one branch per defined FRN."""
        src = ["def _generic(b, p, append):"]
        src += [f"    {k} = {v}" for k, v in self.local_defaults.items()]
        src += [
            "    frns = []",
            "    base = 1",
            "    while True:",
            "        o = b[p]",
            "        p += 1",
            "        for k in _BITS[o]:",
            "            frns.append(base + k)",
            "        if not o & 1:",
            "            break",
            "        base += 7",
            f"        if base > {7 * self.fspec_max}:",
            "            raise FramingError('FSPEC too long')",
            "    for frn in frns:",
        ]
        ns = dict(self.namespace)
        first = True
        for frn, item in enumerate(self.uap):
            if item is None:
                continue
            fixed = self._fixed(frn)
            if fixed is not None:
                lines, k = self._read([fixed], ns)
                lines.append(f"p += {k}")
            else:
                lines = self._variable(frn)
            src.append(f"        {'if' if first else 'elif'} frn == {frn}:")
            first = False
            src += ["            " + line for line in lines]
        src += ["        else:", "            raise FramingError(frn)"]
        for frn in self.mandatory:
            src += [f"    if {frn} not in frns:", f"        raise FramingError({frn})"]
        src += [f"    append(_new(_R, {self.result_expr}))", "    return p"]
        return self._compile(src, ns, "_generic", f"<CAT{self.cat:03d} generic>")

    def decode_block(self, b: bytes, out: list[Any], limit: int | None = None) -> None:
        """Append the records of the data block ``b`` (its header included) to ``out``, all or
        none; more than ``limit`` records raise _TooManyRecordsError."""
        cache = self.cache
        p = 3
        end = len(b)
        records: list[Any] = []
        append = records.append
        # a record is at least 3 octets: a block cannot hold ``end`` of them
        budget = end if limit is None else limit
        while p < end:
            if len(records) >= budget:
                raise _TooManyRecordsError
            q = p
            while b[q] & 1:
                q += 1
            q += 1
            if q - p > self.fspec_max:  # names FRNs beyond the UAP; never a key of seen/cache
                raise FramingError(f"CAT{self.cat:03d} FSPEC of {q - p} octets")
            f = cache.get(b[p:q])
            if f is None:
                # Compiled on its second sighting (a radar repeats its few FSPECs all the time;
                # corrupt or hostile data rarely repeats one: no compile storm), while the cache
                # has room; otherwise the generic path.
                key = b[p:q]
                seen = self.seen
                if key in seen and len(cache) < self.cache_max:
                    f = cache[key] = self.compile(key)
                else:
                    if len(seen) >= 4 * self.cache_max:
                        seen.clear()
                    seen.add(key)
                    p = self.generic(b, p, append)
                    continue
            p = f(b, q, append)
        if p != end:  # the last item ran past the block's LEN
            raise FramingError(f"CAT{self.cat:03d} record past LEN")
        out += records


_CAT048 = _Category(
    48,
    UAP048,
    Cat048Report,
    _S048,
    _L048,
    "(sac, sic, tod, rho, theta, m3a, fl, adr, h, tst)",
    (1,),
)
_CAT034 = _Category(34, UAP034, Cat034Message, _S034, _L034, "(sac, sic, mt, tod, sector)", (1, 2))
_CAT021 = _Category(
    21,
    UAP021,
    Cat021Report,
    _S021,
    _L021,
    "(sac, sic, t073 if t073 is not None else t071 if t071 is not None else t077, icao,"
    " la1 if la1 is not None else la0, lo1 if lo1 is not None else lo0, gh, fl, m3a)",
    (1,),
)
_CATEGORIES = {48: _CAT048, 34: _CAT034, 21: _CAT021}


def decode_datagram(data: bytes, out: Decoded, max_records: int | None = None) -> None:
    """Decode every data block of ``data`` (CAT, LEN, records; LEN counts the 3-octet header)
    into ``out``, at most ``max_records`` records (module docstring, "Cost per datagram").
    Never raises on any bytes (module docstring)."""
    if type(data) is not bytes:
        data = bytes(data)
    n = len(data)
    pos = 0
    errors = out.errors
    left = max_records
    if n == 0:  # an empty datagram: a data block cut before its header (counted, not silent)
        out.blocks += 1
        errors["truncated"] += 1
        return
    while pos < n:
        out.blocks += 1
        if n - pos < 3:
            errors["truncated"] += 1
            return
        length = data[pos + 1] << 8 | data[pos + 2]
        if length < 3 or length > n - pos:
            errors["truncated"] += 1
            return
        cat = _CATEGORIES.get(data[pos])
        if cat is None:
            errors["unsupported_category"] += 1
        else:
            b = data if length == n else data[pos : pos + length]
            records = getattr(out, cat.attr)
            before = len(records)
            try:
                cat.decode_block(b, records, left)
            except (FramingError, IndexError, struct.error):
                errors["undecodable"] += 1
            except _TooManyRecordsError:
                errors["too_many_records"] += 1
                return
            if left is not None:
                left -= len(records) - before
        pos += length
