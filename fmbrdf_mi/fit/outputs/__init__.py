"""What fits write: the fit-and-write functions, ``reproduce`` records and reruns, figures, stdout summaries."""
