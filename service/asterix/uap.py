"""Item length tables (User Application Profiles) of the ASTERIX categories we read, and skipping.

The tables follow the EUROCONTROL Specification for Surveillance Data Exchange (ASTERIX):
  - Part 4, Category 048 "Monoradar Target Reports", edition 1.32;
  - Part 2b, Category 034 "Transmission of Monoradar Service Messages", edition 1.29;
  - Part 12, Category 021 "ADS-B Target Reports", edition 2.7.

A decoder only needs an item's *length class* to step over it, whatever it means.  These are
the length rules of the standard:
  - ``F`` fixed: ``size`` octets;
  - ``X`` extended: extents of ``size`` octets, each with the FX bit (the lowest bit of its last
    octet) saying whether another one follows;
  - ``RX`` FX-repetitive (I048/030): repetitions of ``size`` octets chained by the same FX bit,
    so it is framed exactly like ``X``; the kind is kept apart to mirror the specification;
  - ``R`` repetitive: a one-octet count ``n``, then ``n`` repetitions of ``size`` octets;
  - ``C`` compound: a primary subfield (an FSPEC of at most ``fspec_max`` octets, 7 presence
    bits and an FX bit each) naming the subfields ``sub`` that follow, in order;
  - ``E`` explicit (SP, RE): the first octet is the item's length including itself.

Extended items are walked until their FX bit is clear, not up to the number of extents of one
edition: the newer editions only append extents (I048/020 has 2 in 1.27-1.30, 3 in 1.31 and 6
in 1.32; I021/040 and I021/090 grow likewise across 2.1-2.7), so the newest tables frame
records of every edition from CAT048 1.27, CAT034 1.27 and CAT021 2.1 on (the tests check
these tables against the independent libasterix specifications of each of those editions).
CAT021 editions 0.2x have another UAP and are not supported.
"""

from __future__ import annotations

from typing import NamedTuple, TypeAlias


class FramingError(ValueError):
    """A record cannot be framed: an undefined FRN or subfield, or an inconsistent length."""


class ItemSpec(NamedTuple):
    """One data item's length class (module docstring), enough to step over it."""

    name: str
    kind: str
    size: int = 0
    sub: tuple[ItemSpec | None, ...] = ()
    fspec_max: int = 0


#: FRN -> item (index 0 unused); ``None`` marks a spare FRN.
Uap: TypeAlias = "tuple[ItemSpec | None, ...]"


def _f(name: str, size: int) -> ItemSpec:
    return ItemSpec(name, "F", size)


def _x(name: str, size: int = 1) -> ItemSpec:
    return ItemSpec(name, "X", size)


def _rx(name: str, size: int) -> ItemSpec:
    return ItemSpec(name, "RX", size)


def _r(name: str, size: int) -> ItemSpec:
    return ItemSpec(name, "R", size)


def _c(name: str, fspec_max: int, *sub: ItemSpec | None) -> ItemSpec:
    return ItemSpec(name, "C", 0, tuple(sub), fspec_max)


def _e(name: str) -> ItemSpec:
    return ItemSpec(name, "E")


# CAT048 edition 1.32 (28 FRNs, FSPEC up to 4 octets).
UAP048: Uap = (
    None,
    _f("010", 2),  # 1 data source identifier
    _f("140", 3),  # 2 time of day
    _x("020"),  # 3 target report descriptor
    _f("040", 4),  # 4 measured position, polar
    _f("070", 2),  # 5 Mode-3/A code
    _f("090", 2),  # 6 flight level
    _c("130", 1, *(_f(n, 1) for n in ("SRL", "SRR", "SAM", "PRL", "PAM", "RPD", "APD"))),  # 7 plot chars
    _f("220", 3),  # 8 aircraft address
    _f("240", 6),  # 9 aircraft identification
    _r("250", 8),  # 10 BDS register data
    _f("161", 2),  # 11 track number
    _f("042", 4),  # 12 calculated position, Cartesian
    _f("200", 4),  # 13 calculated track velocity, polar
    _x("170"),  # 14 track status
    _f("210", 4),  # 15 track quality
    _rx("030", 1),  # 16 warning/error conditions
    _f("080", 2),  # 17 Mode-3/A code confidence
    _f("100", 4),  # 18 Mode-C code and confidence
    _f("110", 2),  # 19 height measured by a 3-D radar
    _c("120", 1, _f("CAL", 2), _r("RDS", 6)),  # 20 radial Doppler speed
    _f("230", 2),  # 21 communications/ACAS capability
    _f("260", 7),  # 22 ACAS resolution advisory report
    _f("055", 1),  # 23 Mode-1 code
    _f("050", 2),  # 24 Mode-2 code
    _f("065", 1),  # 25 Mode-1 code confidence
    _f("060", 2),  # 26 Mode-2 code confidence
    _e("SP"),  # 27 special purpose field
    _e("RE"),  # 28 reserved expansion field
)

# CAT034 edition 1.29 (14 FRNs, FSPEC up to 2 octets).  The compound items' second and third
# primary bits are spare.
UAP034: Uap = (
    None,
    _f("010", 2),  # 1 data source identifier
    _f("000", 1),  # 2 message type
    _f("030", 3),  # 3 time of day
    _f("020", 1),  # 4 sector number
    _f("041", 2),  # 5 antenna rotation period
    _c("050", 1, _f("COM", 1), None, None, _f("PSR", 1), _f("SSR", 1), _f("MDS", 2)),  # 6 system config.
    _c("060", 1, _f("COM", 1), None, None, _f("PSR", 1), _f("SSR", 1), _f("MDS", 1)),  # 7 processing mode
    _r("070", 2),  # 8 message count values
    _f("100", 8),  # 9 generic polar window
    _f("110", 1),  # 10 data filter
    _f("120", 8),  # 11 3-D position of data source
    _f("090", 2),  # 12 collimation error
    _e("RE"),  # 13 reserved expansion field
    _e("SP"),  # 14 special purpose field
)

_I021_295 = [
    "AOS",
    "TRD",
    "M3A",
    "QI",
    "TI1",
    "MAM",
    "GH",
    "FL",
    "SAL",
    "FSA",
    "AS",
    "TAS",
    "MH",
    "BVR",
    "GVR",
    "GV",
    "TAR",
    "TI2",
    "TS",
    "MET",
    "ROA",
    "ARA",
    "SCC",
]

# CAT021 edition 2.7 (49 FRNs, FSPEC up to 7 octets; FRNs 43-47 are spare).
UAP021: Uap = (
    None,
    _f("010", 2),  # 1 data source identification
    _x("040"),  # 2 target report descriptor
    _f("161", 2),  # 3 track number
    _f("015", 1),  # 4 service identification
    _f("071", 3),  # 5 time of applicability for position
    _f("130", 6),  # 6 position in WGS-84 co-ordinates
    _f("131", 8),  # 7 high-resolution position in WGS-84 co-ordinates
    _f("072", 3),  # 8 time of applicability for velocity
    _f("150", 2),  # 9 air speed
    _f("151", 2),  # 10 true airspeed
    _f("080", 3),  # 11 target address
    _f("073", 3),  # 12 time of message reception for position
    _f("074", 4),  # 13 time of message reception of position, high precision
    _f("075", 3),  # 14 time of message reception for velocity
    _f("076", 4),  # 15 time of message reception of velocity, high precision
    _f("140", 2),  # 16 geometric height
    _x("090"),  # 17 quality indicators
    _f("210", 1),  # 18 MOPS version
    _f("070", 2),  # 19 Mode 3/A code
    _f("230", 2),  # 20 roll angle
    _f("145", 2),  # 21 flight level
    _f("152", 2),  # 22 magnetic heading
    _f("200", 1),  # 23 target status
    _f("155", 2),  # 24 barometric vertical rate
    _f("157", 2),  # 25 geometric vertical rate
    _f("160", 4),  # 26 airborne ground vector
    _f("165", 2),  # 27 track angle rate
    _f("077", 3),  # 28 time of report transmission
    _f("170", 6),  # 29 target identification
    _f("020", 1),  # 30 emitter category
    _c("220", 1, _f("WS", 2), _f("WD", 2), _f("TMP", 2), _f("TRB", 1)),  # 31 met information
    _f("146", 2),  # 32 selected altitude
    _f("148", 2),  # 33 final state selected altitude
    _c("110", 1, _x("TIS"), _r("TID", 15)),  # 34 trajectory intent
    _f("016", 1),  # 35 service management
    _f("008", 1),  # 36 aircraft operational status
    _x("271"),  # 37 surface capabilities and characteristics
    _f("132", 1),  # 38 message amplitude
    _r("250", 8),  # 39 Mode S MB data
    _f("260", 7),  # 40 ACAS resolution advisory report
    _f("400", 1),  # 41 receiver ID
    _c("295", 4, *(_f(n, 1) for n in _I021_295)),  # 42 data ages
    None,  # 43 spare
    None,  # 44 spare
    None,  # 45 spare
    None,  # 46 spare
    None,  # 47 spare
    _e("RE"),  # 48 reserved expansion field
    _e("SP"),  # 49 special purpose field
)


def fspec_octets(uap: Uap) -> int:
    """The longest FSPEC that names only FRNs of ``uap`` (7 FRNs per octet)."""
    return (len(uap) - 1 + 6) // 7


def skip(b: bytes, p: int, item: ItemSpec) -> int:
    """The offset after ``item`` starting at ``b[p]``.

    Raises FramingError on an inconsistent length (an explicit length of 0, a compound naming
    an undefined subfield or with too long a primary subfield) and IndexError where the item
    runs past ``b``.  A fixed, repetitive or explicit item may end past ``len(b)`` without an
    error: the caller checks that the records end exactly at the end of their block.
    """
    kind = item.kind
    if kind == "F":
        return p + item.size
    if kind == "X" or kind == "RX":
        n = item.size
        while b[p + n - 1] & 1:
            p += n
        return p + n
    if kind == "R":
        return p + 1 + b[p] * item.size
    if kind == "E":
        n = b[p]
        if not n:  # the length counts its own octet: 0 cannot frame anything
            raise FramingError(item.name)
        return p + n
    # compound: the primary subfield first, then the subfields it names, in order
    sub = item.sub
    present = []
    base = 0
    while True:
        octet = b[p]
        p += 1
        for k in range(7):
            if octet & (0x80 >> k):
                i = base + k
                s = sub[i] if i < len(sub) else None
                if s is None:
                    raise FramingError(item.name)
                present.append(s)
        if not octet & 1:
            break
        base += 7
        if base >= 7 * item.fspec_max:
            raise FramingError(item.name)
    for s in present:
        p = skip(b, p, s)
    return p


def skip_code(item: ItemSpec, ref: str) -> list[str]:
    """Python lines stepping ``p`` over ``item`` in ``b``, for generated decoders.

    ``ref`` is an expression naming ``item`` in the generated code's namespace (for the
    compound items, which call ``skip``); the names ``skip`` and ``FramingError`` must be in
    that namespace too.
    """
    kind, n = item.kind, item.size
    if kind == "F":
        return [f"p += {n}"]
    if kind == "X" or kind == "RX":
        last = "p" if n == 1 else f"p + {n - 1}"
        return [f"while b[{last}] & 1:", f"    p += {n}", f"p += {n}"]
    if kind == "R":
        return [f"p += 1 + b[p] * {n}"]
    if kind == "E":
        return ["if not b[p]:", f"    raise FramingError({item.name!r})", "p += b[p]"]
    return [f"p = skip(b, p, {ref})"]
