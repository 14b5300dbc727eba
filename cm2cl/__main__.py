"""``python -m cm2cl``: the same as the ``cm2cl`` command."""

import sys

from .cli import main

sys.exit(main())
