"""``python -m hbm``: the command line."""

import sys

# Guarded: dask worker processes re-import __main__ and must not run the CLI again.
if __name__ == "__main__":
    from .cli import main

    sys.exit(main())
