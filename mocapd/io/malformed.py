"""One rule for the text file readers (BVH, ASF/AMC): whatever a damaged file makes the parser trip over (a number
that does not parse, a line with too few words) is an :class:`~mocapd.errors.InputError` naming the file, never a
bare ``ValueError`` from deep inside."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

from mocapd.errors import InputError, MocapdError


@contextlib.contextmanager
def malformed_file(what: str) -> Iterator[None]:
    """Re-raise a parser's ``ValueError``/``IndexError``/``KeyError``/``OverflowError``/``TypeError`` as
    ``InputError(f"{what}: malformed: ...")``; the project's own errors pass through unchanged."""
    try:
        yield
    except MocapdError:
        raise
    except (ValueError, IndexError, KeyError, OverflowError, TypeError) as exc:
        raise InputError(f"{what}: malformed: {exc}") from None
