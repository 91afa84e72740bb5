"""The ASTERIX decoder against libasterix, an independent implementation (test extra).

- The length tables of service.asterix.uap equal libasterix's generated specifications for
  every item of every edition we frame (CAT048 1.27-1.32, CAT034 1.27-1.29, CAT021 2.1-2.7).
- Records libasterix encodes with random subsets of *all* items and random values (compound,
  repetitive, FX-repetitive, explicit and extended items included) are all framed and their
  fields equal libasterix's own reading of them.
- Several blocks per datagram, mixed and unsupported categories; malformed blocks are dropped
  whole under the right cause while the other blocks of the datagram are kept.
- The cached per-FSPEC functions and the generic path agree, and no bytes make the decoder raise.
"""

from __future__ import annotations

import random
import time
from collections import Counter
from functools import cache
from typing import Any

import asterix.generated as gen
import pytest
from asterix.base import (
    Compound,
    Element,
    Explicit,
    Extended,
    Group,
    Repetitive,
    RuleVariationContextFree,
    UapItem,
    Unsigned,
)
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from service.asterix import decode as dec
from service.asterix.decode import Cat021Report, Cat034Message, Cat048Report, Decoded, decode_datagram
from service.asterix.uap import UAP021, UAP034, UAP048, ItemSpec, Uap, fspec_octets

CATS = gen.manifest["CATS"]
EDITIONS: dict[int, list[Any]] = {
    48: list(CATS[48]),
    34: list(CATS[34]),
    21: [c for c in CATS[21] if c.cv_edition[0] == 2],  # 0.2x is another UAP (not supported)
}
NEWEST = {48: gen.Cat_048_1_32, 34: gen.Cat_034_1_29, 21: gen.Cat_021_2_7}
UAPS: dict[int, Uap] = {48: UAP048, 34: UAP034, 21: UAP021}
ALL_EDITIONS = [c for cat in (48, 34, 21) for c in EDITIONS[cat]]
MANDATORY = {48: ("010",), 34: ("010", "000"), 21: ("010",)}


def _ed(c: Any) -> str:
    return f"{c.cv_category:03d}_{c.cv_edition[0]}_{c.cv_edition[1]}"


# ---------------------------------------------------------------- libasterix specifications


def _variation(nsp: Any) -> Any:
    rule = nsp.cv_rule
    return rule.cv_variation if issubclass(rule, RuleVariationContextFree) else rule.cv_default_variation


def _spec_of(name: str, var: Any) -> ItemSpec:
    """libasterix's item as our length class (an extended item's number of extents left out)."""
    if issubclass(var, (Element, Group)):
        assert var.cv_bit_size % 8 == 0, name
        return ItemSpec(name, "F", var.cv_bit_size // 8)
    if issubclass(var, Extended):  # every extent: its items and the FX bit
        sizes = {sum(x[1] for x in g if x is not None) + (g[-1] is None) for g in var.cv_items_list}
        assert len(sizes) == 1, name
        (bits,) = sizes
        assert bits % 8 == 0, name
        return ItemSpec(name, "X", bits // 8)
    if issubclass(var, Repetitive):
        if var.cv_rep_bytes is None:  # FX-repetitive: the element and its FX bit
            bits = var.cv_variation.cv_bit_size + 1
            assert bits % 8 == 0, name
            return ItemSpec(name, "RX", bits // 8)
        inner = _spec_of(name, var.cv_variation)
        assert var.cv_rep_bytes == 1 and inner.kind == "F", name
        return ItemSpec(name, "R", inner.size)
    if issubclass(var, Explicit):
        return ItemSpec(name, "E")
    if issubclass(var, Compound):
        sub = tuple(None if n is None else _spec_of(n.cv_name, _variation(n)) for n in var.cv_items_list)
        return ItemSpec(name, "C", 0, sub, var.cv_fspec_max_bytes)
    raise AssertionError((name, var))


def _uap_of(c: Any) -> tuple[ItemSpec | None, ...]:
    items = c.cv_uap.cv_record.cv_items_list
    return (
        None,
        *(
            _spec_of(i.cv_non_spare.cv_name, _variation(i.cv_non_spare)) if issubclass(i, UapItem) else None
            for i in items
        ),
    )


def _unnamed(s: ItemSpec | None) -> Any:
    """The length structure without the names (compound subfields were renamed across editions)."""
    if s is None:
        return None
    return (s.kind, s.size, tuple(_unnamed(x) for x in s.sub), s.fspec_max)


@pytest.mark.parametrize("c", ALL_EDITIONS, ids=_ed)
def test_length_tables_equal_libasterix(c: Any) -> None:
    ours, theirs = UAPS[c.cv_category], _uap_of(c)
    assert len(ours) == len(theirs)
    for frn, (a, b) in enumerate(zip(ours, theirs, strict=True)):
        assert _unnamed(a) == _unnamed(b), (frn, a, b)
        if a is not None and b is not None:
            assert a.name == b.name, frn
    assert fspec_octets(ours) == c.cv_uap.cv_record.cv_fspec_max_bytes


@pytest.mark.parametrize("cat", [48, 34, 21])
def test_newest_edition_names_every_subfield_alike(cat: int) -> None:
    assert UAPS[cat] == _uap_of(NEWEST[cat])


# ---------------------------------------------------------------- random libasterix records


def _random_arg(var: Any, rnd: random.Random) -> Any:
    """A random valid argument of libasterix's ``create`` for a variation (raw integers)."""
    if issubclass(var, (Element, Group)):
        return rnd.getrandbits(var.cv_bit_size)
    if issubclass(var, Extended):
        n = rnd.randint(1, len(var.cv_items_list))
        return tuple(rnd.getrandbits(sum(x[1] for x in g if x is not None)) for g in var.cv_items_list[:n])
    if issubclass(var, Repetitive):
        lo = 1 if var.cv_rep_bytes is None else 0
        return [_random_arg(var.cv_variation, rnd) for _ in range(rnd.randint(lo, 3))]
    if issubclass(var, Explicit):
        return rnd.randbytes(rnd.randint(0, 6))
    if issubclass(var, Compound):
        subs = [n for n in var.cv_items_list if n is not None]
        return {
            n.cv_name: _random_arg(_variation(n), rnd) for n in rnd.sample(subs, rnd.randint(1, len(subs)))
        }
    raise AssertionError(var)


def _random_record(c: Any, rnd: random.Random, p_item: float = 0.5) -> Any:
    args = {}
    for i in c.cv_uap.cv_record.cv_items_list:
        if not issubclass(i, UapItem):
            continue
        name = i.cv_non_spare.cv_name
        if name in MANDATORY[c.cv_category] or rnd.random() < p_item:
            args[name] = _random_arg(_variation(i.cv_non_spare), rnd)
    return c.cv_record.create(args)


def _sub(rec: Any, item: str, sub: str | None) -> Any:
    i = rec.get_item(item)
    if i is None:
        return None
    if sub is None:
        return i.variation
    s = i.variation.get_item(sub)
    return None if s is None else s.variation


def _q(rec: Any, item: str, sub: str | None, unit: str, scale: float = 1.0) -> float | None:
    v = _sub(rec, item, sub)
    return None if v is None else v.content.as_quantity(unit) * scale


def _fl048(rec: Any) -> float | None:
    """I048/090 as libasterix reads it, in two's complement.  libasterix's specifications of
    1.27-1.31 read it unsigned, of 1.32 signed; the item's range (down to -12 FL) needs the
    sign in every edition, and the decoder reads all of them with the 1.32 rule."""
    fl = _sub(rec, "090", "FL")
    if fl is None:
        return None
    x: float = fl.content.as_quantity("FL")
    if issubclass(fl.content.cv_signedness, Unsigned) and x >= 2048:
        x -= 4096
    return x


def _expected(rec: Any, cat: int) -> tuple[Any, ...]:
    """libasterix's reading of a record, as our report tuple."""
    sac, sic = _sub(rec, "010", "SAC").as_uint(), _sub(rec, "010", "SIC").as_uint()
    if cat == 48:
        m3a, adr, tst = _sub(rec, "070", "MODE3A"), _sub(rec, "220", None), _sub(rec, "020", "TST")
        return Cat048Report(
            sac,
            sic,
            _q(rec, "140", None, "s"),
            _q(rec, "040", "RHO", "NM", 1852.0),
            _q(rec, "040", "THETA", "°"),
            None if m3a is None else m3a.content.as_string(),
            _fl048(rec),
            None if adr is None else f"{adr.as_uint():06x}",
            _q(rec, "110", "3DH", "ft", 0.3048),
            tst is not None and tst.as_uint() == 1,
        )
    if cat == 34:
        return Cat034Message(
            sac, sic, _sub(rec, "000", None).as_uint(), _q(rec, "030", None, "s"), _q(rec, "020", None, "°")
        )
    tods = [_q(rec, i, None, "s") for i in ("073", "071", "077")]
    pos = ("131", "130") if rec.get_item("131") is not None else ("130", "130")
    adr = _sub(rec, "080", None)
    return Cat021Report(
        sac,
        sic,
        next((t for t in tods if t is not None), None),
        None if adr is None else f"{adr.as_uint():06x}",
        _q(rec, pos[0], "LAT", "°"),
        _q(rec, pos[0], "LON", "°"),
        _q(rec, "140", None, "ft", 0.3048),
        _q(rec, "145", None, "FL"),
        None if (m3a21 := _sub(rec, "070", "MODE3A")) is None else m3a21.content.as_string(),
    )


def _same(got: tuple[Any, ...], want: tuple[Any, ...]) -> bool:
    if type(got) is not type(want):
        return False
    for a, b in zip(got, want, strict=True):
        if isinstance(b, float):
            if not isinstance(a, float) or a != pytest.approx(b, rel=1e-12, abs=1e-9):
                return False
        elif a != b or type(a) is not type(b):
            return False
    return True


@cache
def _corpus(c: Any, n_blocks: int = 6, seed: int = 0) -> tuple[list[bytes], list[tuple[Any, ...]]]:
    """Data blocks libasterix encodes (1-5 random records each) and libasterix's reading of them."""
    rnd = random.Random(f"{_ed(c)}-{seed}")
    blocks, expected = [], []
    for _ in range(n_blocks):
        recs = [_random_record(c, rnd) for _ in range(rnd.randint(1, 5))]
        blocks.append(c.create(recs).unparse().to_bytes())
        expected += [_expected(r, c.cv_category) for r in recs]
    return blocks, expected


def _records(d: Decoded) -> list[tuple[Any, ...]]:
    return [*d.cat048, *d.cat034, *d.cat021]


@pytest.mark.parametrize("c", ALL_EDITIONS, ids=_ed)
def test_every_item_of_every_edition_is_framed(c: Any) -> None:
    blocks, expected = _corpus(c)
    d = Decoded()
    for b in blocks:
        decode_datagram(b, d)
    assert d.errors == Counter() and d.blocks == len(blocks)
    got = getattr(d, f"cat{c.cv_category:03d}")
    assert len(got) == len(expected)
    for g, e in zip(got, expected, strict=True):
        assert _same(g, e), (g, e)


def test_items_the_extraction_skips_are_covered() -> None:
    """The corpus holds the hard item kinds: I048/130 and /120 (compound), /250 (repetitive),
    /030 (FX-repetitive), SP and RE (explicit), /020 and /170 with extents, I021/110, /295."""
    rnd = random.Random(5)
    c = gen.Cat_048_1_32
    hard = {"130": 0, "120": 0, "250": 0, "030": 0, "SP": 0, "RE": 0}
    recs = []
    for _ in range(20):
        rec = _random_record(c, rnd, p_item=0.9)
        recs.append(rec)
        for k in hard:
            hard[k] += rec.get_item(k) is not None
    assert all(hard.values()), hard
    d = Decoded()
    decode_datagram(c.create(recs).unparse().to_bytes(), d)
    assert all(_same(g, _expected(r, 48)) for g, r in zip(d.cat048, recs, strict=True))
    c21 = gen.Cat_021_2_7
    recs21 = [_random_record(c21, rnd, p_item=0.9) for _ in range(10)]
    d = Decoded()
    decode_datagram(c21.create(recs21).unparse().to_bytes(), d)
    assert len(d.cat021) == 10 and not d.errors
    assert all(_same(g, _expected(r, 21)) for g, r in zip(d.cat021, recs21, strict=True))


# ---------------------------------------------------------------- datagrams


def _blk(cat: int, body: bytes) -> bytes:
    return bytes((cat,)) + (len(body) + 3).to_bytes(2, "big") + body


REC048 = (
    bytes.fromhex("f0") + bytes((7, 9)) + (12800).to_bytes(3, "big") + b"\x60" + bytes.fromhex("0a000000")
)
GOOD048 = _blk(48, REC048 * 2)
GOOD034 = _blk(34, bytes.fromhex("e0") + bytes((7, 9, 1)) + (256).to_bytes(3, "big"))
GOOD021 = _blk(21, bytes.fromhex("c0") + bytes((7, 9, 0)))


def test_small_records_decode_to_their_values() -> None:
    d = Decoded()
    decode_datagram(GOOD048 + GOOD034 + GOOD021, d)
    r = Cat048Report(7, 9, 100.0, 10 * 1852.0, 0.0, None, None, None, None, False)
    assert d.cat048 == [r, r]
    assert d.cat034 == [Cat034Message(7, 9, 1, 2.0, None)]
    assert d.cat021 == [Cat021Report(7, 9, None, None, None, None, None, None)]
    assert d.blocks == 3 and not d.errors


def test_several_blocks_and_categories_per_datagram() -> None:
    b48, e48 = _corpus(gen.Cat_048_1_30)
    b34, e34 = _corpus(gen.Cat_034_1_29)
    b21, e21 = _corpus(gen.Cat_021_2_4)
    other = gen.Cat_062_1_21.create([_random_record_062()]).unparse().to_bytes()
    datagram = b"".join([b48[0], b34[0], other, b21[0], _blk(1, b"\x00\x01"), b48[1], _blk(48, b""), b21[1]])
    d = Decoded()
    decode_datagram(datagram, d)
    n48 = [len(_recs_of(b)) for b in b48[:2]]
    n21 = [len(_recs_of(b)) for b in b21[:2]]
    assert d.blocks == 8
    assert d.errors == Counter(unsupported_category=2)
    assert all(_same(g, e) for g, e in zip(d.cat048, e48[: sum(n48)], strict=True))
    assert all(_same(g, e) for g, e in zip(d.cat034, e34[: len(_recs_of(b34[0]))], strict=True))
    assert all(_same(g, e) for g, e in zip(d.cat021, e21[: sum(n21)], strict=True))


def _random_record_062() -> Any:
    c = gen.Cat_062_1_21
    return c.cv_record.create({"010": 0x0102, "040": 7})


def _recs_of(block: bytes) -> list[Any]:
    d = Decoded()
    decode_datagram(block, d)
    assert not d.errors
    return _records(d)


def test_bytes_like_inputs() -> None:
    for data in (bytearray(GOOD048), memoryview(GOOD048)):
        d = Decoded()
        decode_datagram(data, d)
        assert len(d.cat048) == 2


# ---------------------------------------------------------------- malformed input

# FSPEC bits: CAT048 FRN 1 = 0x80 (010); CAT021 FRN 43 is spare (7th octet, bit 1).
_REC021_SPARE = bytes.fromhex("81010101010180") + bytes((7, 9))
_REC034_050_SPARE = bytes.fromhex("c4") + bytes((7, 9, 1)) + bytes.fromhex("40") + b"\x00"  # 050: spare bit
_REC048_130_LONG = bytes.fromhex("82") + bytes((7, 9)) + bytes.fromhex("0100")  # 130: 2-octet primary
_REC048_SP_ZERO = bytes.fromhex("81010104") + bytes((7, 9)) + b"\x00"  # SP (FRN 27), LEN 0
_REC048_FSPEC5 = bytes.fromhex("8101010100") + bytes((7, 9))  # a 5th FSPEC octet: beyond the UAP
_REC048_250_OVER = bytes.fromhex("8120") + bytes((7, 9)) + b"\x09" + bytes(8)  # 250: 9 reps, 1 there
_REC048_NO_010 = bytes.fromhex("40") + (1).to_bytes(3, "big")
_REC034_NO_000 = bytes.fromhex("80") + bytes((7, 9))


@pytest.mark.parametrize(
    "bad",
    [
        _blk(21, _REC021_SPARE),
        _blk(34, _REC034_050_SPARE),
        _blk(48, _REC048_130_LONG),
        _blk(48, _REC048_SP_ZERO),
        _blk(48, _REC048_FSPEC5),
        _blk(48, _REC048_250_OVER),
        _blk(48, _REC048_NO_010),
        _blk(34, _REC034_NO_000),
        _blk(48, REC048 + REC048[:-1]),  # the last record overruns LEN
        _blk(48, REC048 + b"\xff\xff\xff"),  # FSPEC runs past the block
        _blk(48, REC048 + REC048 + b"\x00"),  # trailing octet: a record without 010
        _blk(48, REC048[:5]),
    ],
)
def test_an_unframeable_block_is_dropped_whole(bad: bytes) -> None:
    d = Decoded()
    decode_datagram(GOOD034 + bad + GOOD048, d)
    assert d.errors == Counter(undecodable=1)
    assert d.blocks == 3
    assert len(d.cat034) == 1 and len(d.cat048) == 2 and not d.cat021  # nothing of the bad block


@pytest.mark.parametrize(
    "tail",
    [
        b"\x30",  # 1 octet left
        b"\x30\x00",  # 2 octets left: no LEN
        b"\x30\x00\x02" + GOOD048,  # LEN < 3
        b"\x30\x00\x00" + GOOD048,
        GOOD048[:-1],  # LEN beyond the bytes left
        bytes((48, 0xFF, 0xFF)) + GOOD048,
    ],
)
def test_a_truncated_block_stops_the_walk(tail: bytes) -> None:
    d = Decoded()
    decode_datagram(GOOD034 + tail, d)
    assert d.errors == Counter(truncated=1)
    assert d.blocks == 2
    assert len(d.cat034) == 1 and not d.cat048


def test_an_empty_datagram_is_counted_as_a_truncated_block() -> None:
    """An empty UDP datagram holds no block: counted (the bridge reports it under
    ``blocks_truncated``), not passed over in silence."""
    d = Decoded()
    decode_datagram(b"", d)
    assert d.errors == Counter(truncated=1) and d.blocks == 1 and not d.cat048


def test_a_len_cutting_a_record_drops_that_block_only() -> None:
    short = bytes((48,)) + (len(GOOD048) - 4).to_bytes(2, "big") + GOOD048[3:-4]
    d = Decoded()
    decode_datagram(short + GOOD034, d)
    assert d.errors == Counter(undecodable=1)
    assert not d.cat048 and len(d.cat034) == 1


def test_the_fspec_cache_is_bounded_and_full_means_generic(monkeypatch: pytest.MonkeyPatch) -> None:
    cat = dec._CAT048
    monkeypatch.setattr(cat, "cache", {})
    monkeypatch.setattr(cat, "cache_max", 16)
    rnd = random.Random(3)
    c = gen.Cat_048_1_32
    recs = [_random_record(c, rnd) for _ in range(40)]
    monkeypatch.setattr(cat, "seen", set())
    fspecs = {r.unparse().to_bytes()[:4] for r in recs}
    assert len(fspecs) > 16
    data = c.create(recs).unparse().to_bytes()
    for sighting in (1, 2, 3):
        d = Decoded()
        decode_datagram(data, d)
        assert len(cat.cache) == (0 if sighting == 1 else 16)  # compiled when seen again
        assert all(_same(g, _expected(r, 48)) for g, r in zip(d.cat048, recs, strict=True))


# ---------------------------------------------------------------- generic path and fuzzing


@cache
def _valid_datagrams() -> list[bytes]:
    out = []
    for c in (gen.Cat_048_1_32, gen.Cat_048_1_27, gen.Cat_034_1_29, gen.Cat_021_2_7, gen.Cat_021_2_1):
        blocks = _corpus(c)[0]
        out += [blocks[0] + blocks[1], blocks[2]]
    out.append(GOOD048 + GOOD034 + GOOD021)
    return out


def _decode_both(data: bytes) -> tuple[Decoded, Decoded]:
    """Decoded through the per-FSPEC functions and through the generic path only."""
    first, fast = Decoded(), Decoded()
    decode_datagram(data, first)  # new FSPECs: the generic path, compiled when seen again
    decode_datagram(data, fast)
    _assert_same(first, fast)
    saved = [(c, c.cache, c.cache_max) for c in dec._CATEGORIES.values()]
    try:
        for c in dec._CATEGORIES.values():
            c.cache, c.cache_max = {}, 0
        slow = Decoded()
        decode_datagram(data, slow)
    finally:
        for c, cached, cache_max in saved:
            c.cache, c.cache_max = cached, cache_max
    return fast, slow


def _assert_same(a: Decoded, b: Decoded) -> None:
    assert a.errors == b.errors and a.blocks == b.blocks
    for x, y in ((a.cat048, b.cat048), (a.cat034, b.cat034), (a.cat021, b.cat021)):
        assert len(x) == len(y)
        assert all(_same(g, e) for g, e in zip(x, y, strict=True))


def test_generic_path_equals_the_generated_functions(monkeypatch: pytest.MonkeyPatch) -> None:
    for c in dec._CATEGORIES.values():
        monkeypatch.setattr(c, "cache", {})
        monkeypatch.setattr(c, "seen", set())
    for data in _valid_datagrams():
        fast, slow = _decode_both(data)
        assert not fast.errors
        _assert_same(fast, slow)
    assert all(len(c.cache) >= 5 for c in dec._CATEGORIES.values())  # the fast path was taken


FUZZ = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@FUZZ
@given(st.binary(max_size=600))
def test_random_bytes_never_raise(data: bytes) -> None:
    for prefix in (b"", b"\x30", b"\x22", b"\x15"):
        fast, slow = _decode_both(prefix + data)
        _assert_same(fast, slow)
        assert sum(fast.errors.values()) <= fast.blocks


@FUZZ
@given(
    st.integers(0, 10),
    st.lists(st.tuples(st.integers(0, 10_000), st.integers(0, 255)), max_size=6),
    st.integers(0, 10_000),
    st.binary(max_size=8),
)
def test_mutated_datagrams_never_raise(
    which: int, flips: list[tuple[int, int]], cut: int, insert: bytes
) -> None:
    base = _valid_datagrams()
    data = bytearray(base[which % len(base)])
    for pos, val in flips:
        data[pos % len(data)] = val
    at = cut % (len(data) + 1)
    data[at:at] = insert
    fast, slow = _decode_both(bytes(data))
    _assert_same(fast, slow)


def test_hostile_input_costs_linear_time(monkeypatch: pytest.MonkeyPatch) -> None:
    """FSPECs of all ones, FSPECs with random bits, and valid records that each have another
    FSPEC (no compile storm: an FSPEC is compiled when seen again): all quick."""
    cat = dec._CAT048
    monkeypatch.setattr(cat, "cache", {})
    monkeypatch.setattr(cat, "seen", set())
    rnd = random.Random(9)
    junk = [bytes((48, 0xFF, 0xFF)) + b"\xff" * 65532, bytes((21, 0xFF, 0xFF)) + b"\x81" * 65532]
    junk.append(bytes((48, 0xFF, 0xFF)) + bytes(rnd.getrandbits(8) | 0x80 for _ in range(65532)))
    junk.append(bytes((48, 0xFF, 0xFF)) + b"\x81" * 30000 + b"\x80" + bytes(35531))  # a 30 001-octet FSPEC
    fixed = [frn for frn, item in enumerate(UAP048) if item is not None and item.kind == "F" and frn > 1]
    records = []
    for _ in range(3000):
        frns = [1, *(f for f in fixed if rnd.random() < 0.5)]
        fspec = bytearray(4)
        for f in frns:
            fspec[(f - 1) // 7] |= 0x80 >> ((f - 1) % 7)
        n = (max(frns) - 1) // 7 + 1
        for i in range(n - 1):
            fspec[i] |= 1
        records.append(bytes(fspec[:n]) + bytes(sum(UAP048[f].size for f in frns)))
    assert len({r[:4] for r in records}) > 2500
    t0 = time.perf_counter()
    for data in junk:
        d = Decoded()
        decode_datagram(data * 4, d)
        assert d.errors["undecodable"] == 4
    d = Decoded()
    for i in range(0, 3000, 1000):
        decode_datagram(_blk(48, b"".join(records[i : i + 1000])), d)
    assert len(d.cat048) == 3000 and not d.errors
    assert len(cat.cache) < 50
    assert all(len(k) <= 4 for k in cat.seen)  # no FSPEC longer than the UAP's is remembered
    assert time.perf_counter() - t0 < 2.0


def test_a_datagram_is_decoded_up_to_max_records() -> None:
    """Past ``max_records`` the block that goes over is dropped whole and the walk ends; the
    blocks before it stay.  A datagram of the smallest records costs only up to the cap."""
    small = bytes((0x80, 25, 11))  # FSPEC and I048/010 only: the smallest CAT048 record
    first, over, after = _blk(48, small * 5), _blk(48, small * 10), _blk(48, small * 2)
    d = Decoded()
    decode_datagram(first + over + after, d, max_records=12)
    assert (len(d.cat048), dict(d.errors)) == (5, {"too_many_records": 1})
    d = Decoded()
    decode_datagram(first + over + after, d, max_records=17)  # exactly enough
    assert (len(d.cat048), dict(d.errors)) == (17, {})
    d = Decoded()
    decode_datagram(first + over + after, d)  # no cap
    assert len(d.cat048) == 17
    full = _blk(48, small * ((65_507 - 3) // 3))  # 21 834 records in one datagram
    # the fastest of ten runs each, so that a moment of load on the machine weighs on neither
    capped = uncapped = float("inf")
    for _ in range(10):
        d = Decoded()
        t0 = time.perf_counter()
        decode_datagram(full, d, max_records=1000)
        capped = min(capped, time.perf_counter() - t0)
        assert d.errors == {"too_many_records": 1} and not d.cat048
        t0 = time.perf_counter()
        decode_datagram(full, Decoded())
        uncapped = min(uncapped, time.perf_counter() - t0)
    assert capped < uncapped / 5  # the cost follows the cap, not the size
