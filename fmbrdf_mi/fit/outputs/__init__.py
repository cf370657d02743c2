"""What fits write: the one writer, ``reproduce`` records and reruns, plots, stdout summaries, the
fit-and-write functions."""
