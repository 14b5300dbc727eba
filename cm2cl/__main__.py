"""``python -m cm2cl``: the same as the ``cm2cl`` command."""

from .cli import run

run()
