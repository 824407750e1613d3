"""What the data identify: the identifiable combinations and their exact priors (:mod:`.combinations`),
combinations found from the samples (:mod:`.identify`), the VOLF–T1 manifolds (:mod:`.manifolds`) and the
views of results that tables and figures read (:mod:`.views`)."""
