"""``fmbrdf-mi fit``: its arguments, their checks and the dispatch to the fit-and-write functions."""
