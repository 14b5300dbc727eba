"""The ``cm2cl`` command: :mod:`.main` parses and reports errors (a parameter named in a library error
becomes the option the user typed); one module per sub-command (devices, demo, simulate, reconstruct,
prepare-psf). ``reconstruct`` is built from :mod:`.options` (its option groups), :mod:`.inputs` (the input
preparation its frame and series jobs share), :mod:`.plan` (header checks, --dry-run), :mod:`.frame`,
:mod:`.series` and :mod:`.progress`. Only this package writes to the terminal."""

from .main import main, run  # noqa: F401
