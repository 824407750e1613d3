"""How hbm runs: worker processes and dask (:mod:`.parallel`, :mod:`.dask_worker`), the Ctrl-C policy
(:mod:`.process`), BLAS threads (:mod:`.blas`), the seed table (:mod:`.seeds`), files written atomically
and locked (:mod:`.files`), memory checks (:mod:`.memory`), progress lines (:mod:`.progress`) and the
validation rules of settings (:mod:`.validation`).  Imports only the standard library at package level:
:mod:`.process` is imported first thing by ``hbm``."""
