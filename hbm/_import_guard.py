"""Imported first by ``hbm/__init__.py``, before numpy, scipy and xarray: in the process of the
``hbm`` command, Ctrl-C during the package's imports prints ``hbm: interrupted`` and exits 130
(:func:`hbm.errors.exit_on_interrupt`); ``restore_sigint()`` ends that once the imports are done."""

from .errors import exit_on_interrupt

restore_sigint = exit_on_interrupt()
