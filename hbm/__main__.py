"""``python -m hbm``: the command line."""

import sys

if __name__ == "__main__":
    from .cli import main

    # dask spawns its workers with multiprocessing, which re-runs the parent's main module in each
    # worker -- except a package's __main__.  Without a module spec the worker runs this file (as
    # __mp_main__, below) first thing, so that it imports hbm and so ignores Ctrl-C before
    # anything else (hbm.runtime.process); the command shuts its workers down itself.
    sys.modules["__main__"].__spec__ = None
    sys.exit(main())
elif __name__ == "__mp_main__":  # a worker process of `python -m hbm`
    import hbm  # noqa: F401
