"""The ``cm2cl`` command: :mod:`.main` parses and reports errors; one module per sub-command
(devices, demo, simulate, reconstruct). Only this package writes to the terminal."""

from .main import main  # noqa: F401
