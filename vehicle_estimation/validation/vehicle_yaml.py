"""A vehicle params file written from another simulator's data, each value with its origin."""

from __future__ import annotations


def format_vehicle_yaml(header: list[str], values: dict, notes: dict[str, str]) -> str:
    """``/**: ros__parameters: vehicle:`` with ``values``, each line commented by ``notes[key]``.

    ``header``: comment lines (with their ``#``) that say where the data come from. A value
    that is a string is written as it is.
    """
    lines = [*header, "/**:", "  ros__parameters:", "    vehicle:"]
    for key, value in values.items():
        if isinstance(value, str):
            text = value
        elif isinstance(value, list):
            # repr keeps "1.0" a float: a ROS params file refuses an array of mixed types.
            text = "[" + ", ".join(repr(float(x)) for x in value) + "]"
        else:
            text = repr(round(float(value), 6))
        note = notes.get(key, "")
        lines.append(f"      {key}: {text}" + (f"   # {note}" if note else ""))
    return "\n".join(lines) + "\n"
