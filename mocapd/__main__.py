"""``python -m mocapd``: the ``mocapd`` command."""

from mocapd.service.cli import entry

entry()
