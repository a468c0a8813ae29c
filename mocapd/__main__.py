"""``python -m mocapd``: the ``mocapd`` command."""

import sys

from mocapd.service.cli import main

sys.exit(main())
