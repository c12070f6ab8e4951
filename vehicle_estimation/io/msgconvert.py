"""Convert a deserialised message to the same-named type of another typestore (ROS 1 <-> ROS 2).

A ROS 1 bag holds ROS 1 serialisation, not CDR, and its types differ from ROS 2's in small
ways (``std_msgs/Header`` has a ``seq``; ``time`` is ``builtin_interfaces/Time``). The nodes
only understand ROS 2 Jazzy CDR, so the replay player converts every message of a ROS 1 bag,
and the bag tools convert the other way to write ROS 1 bags. Both use :func:`convert_message`:
a recursive copy of fields by name, driven by the target typestore's field definitions, so
that what the target lacks is dropped and what the source lacks gets the target's default.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import numpy as np
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.base import Nodetype, normalize_fieldname
from rosbags.typesys.store import Typestore


@functools.lru_cache(maxsize=None)
def cached_typestore(store: Stores) -> Typestore:
    """A rosbags typestore, built once per process: building one costs tens of milliseconds."""
    return get_typestore(store)


def jazzy_typestore() -> Typestore:
    """The ROS 2 Jazzy typestore: the types the nodes speak."""
    return cached_typestore(Stores.ROS2_JAZZY)


def _dtype(base: str) -> np.dtype:
    # rosbags keeps char and byte arrays as uint8; bool arrays as bool.
    return np.dtype("uint8" if base in ("char", "byte", "octet") else base)


def default_value(typestore: Typestore, desc: tuple) -> Any:
    """The value a field of type ``desc`` (a rosbags field description) has when nothing set it."""
    kind, rest = desc
    if kind == Nodetype.BASE:
        if rest[0] == "string":
            return ""
        return False if rest[0] == "bool" else (0.0 if rest[0].startswith("float") else 0)
    if kind == Nodetype.NAME:
        return default_message(typestore, rest)
    sub, size = rest
    size = size if kind == Nodetype.ARRAY else 0
    if sub[0] == Nodetype.BASE:
        if sub[1][0] == "string":
            return [""] * size
        return np.zeros(size, dtype=_dtype(sub[1][0]))
    return [default_value(typestore, sub) for _ in range(size)]


def default_message(typestore: Typestore, msgtype: str) -> Any:
    """A message of ``msgtype`` with every field at its default (zeros, empty strings, no items)."""
    _, fields = _fielddefs(typestore, msgtype)
    return typestore.types[msgtype](**{normalize_fieldname(name): default_value(typestore, desc)
                                       for name, desc in fields})


def _fielddefs(typestore: Typestore, msgtype: str) -> tuple:
    try:
        return typestore.fielddefs[msgtype]
    except KeyError:
        raise ValueError(f"message type {msgtype} is not in the target typestore, so a message of it cannot "
                         "be converted (only types of the same name in both ROS versions can)") from None


_Converter = Callable[[Any, str], Any]
#: (typestore id, msgtype) -> [(field attribute, value converter)]: built once per type, as a
#: bag converts thousands of messages of the same few types.
_PLANS: dict[tuple[int, str], list[tuple[str, _Converter]]] = {}


def _value_converter(typestore: Typestore, desc: tuple, name: str) -> _Converter:
    """A function (source value, where) -> value of the target field ``name`` of type ``desc``."""
    kind, rest = desc
    default = default_value(typestore, desc) if kind == Nodetype.BASE else None
    if kind == Nodetype.BASE:
        if rest[0] == "string":
            return lambda value, where: value if isinstance(value, str) else default
        cast: Callable[[Any], Any] = bool if rest[0] == "bool" else (
            float if rest[0].startswith("float") else int)
        # a string where the target has a number: not the same field, so the default
        return lambda value, where: default if isinstance(value, str) else cast(value)
    if kind == Nodetype.NAME:
        return lambda value, where: convert_message(value, typestore, rest, f"{where}.{name}")
    sub, size = rest
    fixed = size if kind == Nodetype.ARRAY else None

    def check(items: Any, where: str) -> None:
        if fixed is not None and len(items) != fixed:
            raise ValueError(f"{where}.{name}: the target type has a fixed array of {fixed} items, the "
                             f"message has {len(items)}")

    if sub[0] == Nodetype.BASE and sub[1][0] == "string":
        def strings(items: Any, where: str) -> Any:
            check(items, where)
            return [str(item) for item in items]
        return strings
    if sub[0] == Nodetype.BASE:
        dtype = _dtype(sub[1][0])

        def numbers(items: Any, where: str) -> Any:
            check(items, where)
            if isinstance(items, (bytes, bytearray, memoryview)):
                items = np.frombuffer(bytes(items), dtype=np.uint8)
            return np.asarray(items).astype(dtype)
        return numbers
    subtype = sub[1]

    def messages(items: Any, where: str) -> Any:
        check(items, where)
        return [convert_message(item, typestore, subtype, f"{where}.{name}[{i}]") for i, item in enumerate(items)]
    return messages


def _plan(typestore: Typestore, msgtype: str) -> list[tuple[str, _Converter]]:
    key = (id(typestore), msgtype)
    plan = _PLANS.get(key)
    if plan is None:
        _, fields = _fielddefs(typestore, msgtype)
        plan = [(normalize_fieldname(name), _value_converter(typestore, desc, name)) for name, desc in fields]
        _PLANS[key] = plan
    return plan


def convert_message(msg: Any, typestore: Typestore, msgtype: str, where: str | None = None) -> Any:
    """Copy ``msg`` (a message object of any typestore) into ``typestore``'s type ``msgtype``.

    Fields are matched by name, recursively through nested messages, arrays and sequences;
    a field the target lacks (ROS 1 ``Header.seq``) is dropped, a field the source lacks gets
    the target's default (``seq`` = 0 the other way round). Raises ``ValueError`` naming the
    field when a value cannot be carried over (a fixed-size array of another length, a type the
    target typestore does not know).
    """
    where = where or msgtype
    values = {}
    for attr, convert in _plan(typestore, msgtype):
        value = getattr(msg, attr, _MISSING)
        values[attr] = default_value(typestore, _field_desc(typestore, msgtype, attr)) if value is _MISSING \
            else convert(value, where)
    return typestore.types[msgtype](**values)


_MISSING = object()


def _field_desc(typestore: Typestore, msgtype: str, attr: str) -> tuple:
    return next(desc for name, desc in typestore.fielddefs[msgtype][1] if normalize_fieldname(name) == attr)


def ros1_to_cdr(msg: Any, msgtype: str, typestore: Typestore | None = None) -> bytes:
    """A deserialised ROS 1 message as ROS 2 (Jazzy unless ``typestore`` says otherwise) CDR bytes."""
    typestore = typestore or jazzy_typestore()
    return bytes(typestore.serialize_cdr(convert_message(msg, typestore, msgtype), msgtype))
