"""Compact binary encoding for the hot path, laid out from the pydantic message models.

Each message is ``magic (1 B) | version (1 B) | fields in model order``, little-endian: int -> uint64,
float -> float64, bool -> uint8. The field order and types come from the models in
``schemas.messages``, so the JSON Schema and the wire layout cannot drift apart. Decoding checks the
size, the magic and version bytes, that every float is finite, and that every field is within its model's bounds
(``Codec.ranges``: what the code after the decoder can hold, e.g. seq below 2^53), and names the field it rejects.
"""

from __future__ import annotations

import operator
import struct
from math import isfinite
from typing import get_args

import annotated_types
from pydantic import BaseModel

from schemas.messages import (
    Allocation,
    Command,
    Estimate,
    GridSample,
    Interaction,
    LayerSource,
    LayerTick,
    LayerWindow,
    LoopRecord,
    Measurement,
    Plant,
    TickInput,
)

VERSION = 1
_TYPE_CODES = {int: "Q", float: "d", bool: "B"}
# what each struct code is called in the JSON Schemas' x-wire-type (schemas.generate); a bool field's "B" is "bool/u8"
WIRE_TYPE_NAMES = {"Q": "u64", "d": "f64", "B": "u8"}
_ENDIANNESS = {"<": "little", ">": "big", "!": "big"}


class DecodeError(ValueError):
    """A payload that is not a valid message; ``field`` names what was wrong."""

    def __init__(self, message: str, field: str, reason: str):
        super().__init__(f"{message}.{field}: {reason}")
        self.message, self.field, self.reason = message, field, reason


def _py_type(annotation) -> type:
    if annotation in _TYPE_CODES:
        return annotation
    for a in get_args(annotation):  # Optional[...] etc.
        if a in _TYPE_CODES:
            return a
    raise TypeError(f"no wire type for {annotation!r}")


# a bound of a model's field (pydantic keeps annotated_types objects in FieldInfo.metadata): (its attribute, the
# comparison a value must pass against it, the bracket it is written with)
_BOUNDS = {annotated_types.Ge: ("ge", operator.ge, "["), annotated_types.Gt: ("gt", operator.gt, "("),
           annotated_types.Le: ("le", operator.le, "]"), annotated_types.Lt: ("lt", operator.lt, ")")}


def _number(x) -> str:
    """A bound as the docs write it: 2^53 rather than 9007199254740992."""
    if x and x == int(x) and abs(x) >= 2**16 and (ax := abs(int(x))) & (ax - 1) == 0:
        return f"{'-' if x < 0 else ''}2^{ax.bit_length() - 1}"
    return f"{x:g}" if isinstance(x, float) else str(x)


def field_ranges(model: type[BaseModel]) -> dict[str, tuple]:
    """Each bounded field's admissible range, from the model's own bounds (ge/gt/le/lt; a bool's u8 is 0 or 1): name
    -> (low or None, its comparison, high or None, its comparison, the range as text, e.g. '[0, 2^53)')."""
    out = {}
    for name, f in model.model_fields.items():
        if _py_type(f.annotation) is bool:
            out[name] = (0, operator.ge, 1, operator.le, "[0, 1]")
            continue
        lo = hi = None
        lo_op = hi_op = None
        left, right = "(-inf", "inf)"
        for m in f.metadata:
            kind = _BOUNDS.get(type(m))
            if kind is None:
                continue
            attr, op, bracket = kind
            if bracket in "[(":
                lo, lo_op, left = getattr(m, attr), op, f"{bracket}{_number(getattr(m, attr))}"
            else:
                hi, hi_op, right = getattr(m, attr), op, f"{_number(getattr(m, attr))}{bracket}"
        if lo_op is not None or hi_op is not None:
            out[name] = (lo, lo_op, hi, hi_op, f"{left}, {right}")
    return out


def admits(r: tuple, x) -> bool:
    """Whether x is inside a range of ``field_ranges``."""
    lo, lo_op, hi, hi_op, _text = r
    return (lo_op is None or lo_op(x, lo)) and (hi_op is None or hi_op(x, hi))


def _inline(r: tuple) -> tuple:
    """(low, high, high included) of a range [low, high) or [low, high], checked inline by decode; (None, None,
    False) for a range of another form (checked by ``admits``)."""
    if r[1] is operator.ge and r[3] in (operator.lt, operator.le):
        return r[0], r[2], r[3] is operator.le
    return None, None, False


def out_of_range(message: str, field: str, r: tuple, x) -> DecodeError:
    """The DecodeError of a field outside its range r, e.g. ``seq: 18446744073709551615 not in [0, 2^53)``."""
    return DecodeError(message, field, f"{x!r} not in {r[4]}")


class Codec:
    """struct-based codec for one message model.

    ``ranges``: each bounded field's admissible range (``field_ranges`` of the model, or narrower ones given here),
    checked by ``decode`` after finiteness; the one place a decoder learns what a field may hold."""

    def __init__(self, model: type[BaseModel], magic: int, ranges: dict[str, tuple] | None = None):
        self.model = model
        self.name = model.__name__
        self.fields = tuple(model.model_fields)
        types = [_py_type(f.annotation) for f in model.model_fields.values()]
        self.floats = tuple(k for k, t in enumerate(types) if t is float)
        self.struct = struct.Struct("<BB" + "".join(_TYPE_CODES[t] for t in types))
        self.size = self.struct.size
        self.magic = magic
        self.ranges = field_ranges(model) if ranges is None else ranges
        # per bounded field: position, low, high and whether high is included when checked inline, name, range
        self._checks = tuple((self.fields.index(n), *_inline(r), n, r) for n, r in self.ranges.items())

    def encode(self, *values) -> bytes:
        """Values in model field order (no validation: the hot path builds them itself)."""
        return self.struct.pack(self.magic, VERSION, *values)

    def decode(self, payload: bytes) -> tuple:
        """Field values in model order; raises DecodeError naming the field."""
        if len(payload) != self.size:
            raise DecodeError(self.name, "<payload>", f"{len(payload)} bytes, expected {self.size}")
        vals = self.struct.unpack(payload)
        if vals[0] != self.magic:
            raise DecodeError(self.name, "<magic>", f"0x{vals[0]:02x}, expected 0x{self.magic:02x}")
        if vals[1] != VERSION:
            raise DecodeError(self.name, "<version>", f"{vals[1]}, expected {VERSION}")
        vals = vals[2:]
        if not isfinite(sum(vals)):  # one sum for the common case: any NaN or inf makes it non-finite
            for k in self.floats:  # (or finite values overflowed it: then none is named and all pass)
                if not isfinite(vals[k]):
                    raise DecodeError(self.name, self.fields[k], f"not finite ({vals[k]!r})")
        for k, lo, hi, closed, name, r in self._checks:
            x = vals[k]
            if not ((lo <= x <= hi if closed else lo <= x < hi) if lo is not None else admits(r, x)):
                raise out_of_range(self.name, name, r, x)
        return vals

    def half_open_ranges(self) -> dict[str, tuple]:
        """Each bounded field's range as (low, high) of [low, high), for a decoder elsewhere (the compiled tick) that
        checks the same; ValueError if one has another form."""
        out = {}
        for _k, lo, hi, closed, name, r in self._checks:
            if lo is None or closed:
                raise ValueError(f"{self.name}.{name}: range {r[4]} is not of the form [low, high)")
            out[name] = (lo, hi)
        return out

    def to_dict(self, vals: tuple) -> dict:
        return dict(zip(self.fields, vals, strict=True))

    def json_template(self) -> str:
        """A %-format string giving the same JSON as json.dumps(to_dict(vals)) for finite values
        (Python's float repr is the JSON float text); bools must be passed as 'true'/'false'."""
        codes = {"Q": "%d", "d": "%r", "B": "%s"}
        assert not any("nan" in f or "inf" in f for f in self.fields), "the recorder detects nan/inf by these tokens"
        fmt = self.struct.format.lstrip("<")[2:]
        return "{" + ",".join(f'"{f}":{codes[c]}' for f, c in zip(self.fields, fmt, strict=True)) + "}"

    @property
    def bool_positions(self) -> tuple[int, ...]:
        fmt = self.struct.format.lstrip("<")[2:]
        return tuple(k for k, c in enumerate(fmt) if c == "B")

    @property
    def endianness(self) -> str:
        return _ENDIANNESS[self.struct.format[0]]

    def layout(self) -> list[tuple[str, str, int, int]]:
        """(name, wire type, offset in bytes, size in bytes) of the header's ``magic`` and ``version`` bytes and of
        each field in wire order, read off the struct format the codec packs with (what the JSON Schemas' x-wire-*
        keys state: schemas.generate)."""
        order, codes = self.struct.format[0], self.struct.format[1:]
        kinds = [_py_type(f.annotation) for f in self.model.model_fields.values()]
        out = []
        for k, (name, c) in enumerate(zip(("magic", "version", *self.fields), codes, strict=True)):
            wire = "bool/u8" if k >= 2 and kinds[k - 2] is bool else WIRE_TYPE_NAMES[c]
            out.append((name, wire, struct.calcsize(order + codes[:k]), struct.calcsize(order + c)))
        return out


MEAS = Codec(Measurement, 0xE1)
CMD = Codec(Command, 0xC1)
Z = Codec(Interaction, 0x21)
TICK_IN = Codec(TickInput, 0x71)
EST = Codec(Estimate, 0x51)
LOOP = Codec(LoopRecord, 0x4C)
PLANT = Codec(Plant, 0x50)  # only recorded (the HIL plant's true state), never sent
ALLOC = Codec(Allocation, 0xA1)
WINDOW = Codec(LayerWindow, 0xA2)  # the layer per window to each source (its P^{r,in} it forms itself)
LAYER_SRC = Codec(LayerSource, 0x4D)  # only recorded (the coordinator's inputs and answers per source)
LAYER_TICK = Codec(LayerTick, 0x4E)  # only recorded


class GridCodec:
    """The network rig's per-sample message to the coordinator (schemas.messages.GridSample): a header and arrays
    whose lengths it states."""

    name = "GridSample"
    magic = 0x47
    head = struct.Struct("<BBQdHHH")
    ranges = field_ranges(GridSample)  # seq and t, as every message's (schemas.messages)

    def encode(self, seq: int, t: float, v, i_out, connected, bus_v, load_P) -> bytes:
        ns, nb, nl = len(v), len(bus_v), len(load_P)
        vals = [*v, *i_out, *(1.0 if c else 0.0 for c in connected), *bus_v, *load_P]
        return self.head.pack(self.magic, VERSION, seq, t, ns, nb, nl) + struct.pack(f"<{len(vals)}d", *vals)

    def decode(self, payload: bytes) -> tuple:
        """(seq, t, v, i_out, connected, bus_v, load_P); raises DecodeError naming the field."""
        h = self.head.size
        if len(payload) < h:
            raise DecodeError(self.name, "<payload>", f"{len(payload)} bytes, shorter than its {h}-byte header")
        magic, version, seq, t, ns, nb, nl = self.head.unpack_from(payload)
        if magic != self.magic:
            raise DecodeError(self.name, "<magic>", f"0x{magic:02x}, expected 0x{self.magic:02x}")
        if version != VERSION:
            raise DecodeError(self.name, "<version>", f"{version}, expected {VERSION}")
        n = 3 * ns + nb + nl
        if len(payload) != h + 8 * n:
            raise DecodeError(self.name, "<payload>", f"{len(payload)} bytes, expected {h + 8 * n} for {ns} sources, "
                                                      f"{nb} buses and {nl} loads")
        vals = struct.unpack_from(f"<{n}d", payload, h)
        if not isfinite(t):
            raise DecodeError(self.name, "t", f"not finite ({t!r})")
        for name, x in (("seq", seq), ("t", t)):
            if not admits(self.ranges[name], x):
                raise out_of_range(self.name, name, self.ranges[name], x)
        if not isfinite(sum(vals)):  # (finite values can overflow the sum: then every one is looked at, and pass)
            names = ["v"] * ns + ["i_out"] * ns + ["connected"] * ns + ["bus_v"] * nb + ["load_P"] * nl
            for k, x in enumerate(vals):
                if not isfinite(x):
                    raise DecodeError(self.name, names[k], f"not finite ({x!r})")
        v, i_out = list(vals[:ns]), list(vals[ns:2 * ns])
        connected = [x != 0.0 for x in vals[2 * ns:3 * ns]]
        return seq, t, v, i_out, connected, list(vals[3 * ns:3 * ns + nb]), list(vals[3 * ns + nb:])


GRID = GridCodec()

# the codec of each message model that has a binary form (energyctl.Event has none: JSON text in recordings only)
BY_MODEL: dict[type[BaseModel], Codec] = {c.model: c for c in (MEAS, CMD, Z, TICK_IN, EST, LOOP, PLANT, ALLOC,
                                                                    WINDOW, LAYER_SRC, LAYER_TICK)}
