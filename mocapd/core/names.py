"""Names that cross a door: cameras, suits, persons, hosts named in files and on the command line.

One rule, the config schema's for camera names (``[[cameras]] name``): 1 to 32 letters, digits, ``_``, ``.`` or
``-``. A name ends up in file names (``<person>.imu.json``), manifests, ``/status`` and log lines, so a newline,
a ``/`` (``../../etc``), a NUL or a kilobyte of text in one is refused where it enters, with the rule in the
message.
"""

from __future__ import annotations

import re

from mocapd.errors import InputError

MAX_NAME_CHARS = 32
NAME_RULE = f"1 to {MAX_NAME_CHARS} letters, digits, '_', '.' or '-'"
_NAME = re.compile(rf"^[A-Za-z0-9_.-]{{1,{MAX_NAME_CHARS}}}$")


def is_name(value: object) -> bool:
    """Whether ``value`` is a string following :data:`NAME_RULE`."""
    return isinstance(value, str) and _NAME.match(value) is not None and value not in (".", "..")


def check_name(value: object, what: str, error: type[Exception] = InputError) -> str:
    """``value`` if it is a name (:func:`is_name`), else ``error`` naming ``what`` and the rule."""
    if not is_name(value):
        shown = repr(value)[:60] + ("..." if len(repr(value)) > 60 else "")
        raise error(f"{what} {shown}: allowed: {NAME_RULE}")
    return str(value)
