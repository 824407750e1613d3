"""The ``hbm`` parser class, apart from :mod:`hbm.cli._common` so that the top-level parser
(``hbm --version``, ``hbm --help``) is built without importing what the subcommands use."""

from __future__ import annotations

import argparse

from ..errors import SettingError


class HbmArgumentParser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are one line ``hbm: error: <command>: <message>``, exit 2.

    ``error`` raises :class:`SettingError` (the ``hbm`` entry point prints it) instead of
    printing a usage block; sub-parsers inherit the class.
    """

    def error(self, message: str):  # type: ignore[override]
        command = self.prog.partition(" ")[2]
        raise SettingError(f"{command}: {message}" if command else message)
