"""Synthetic captures for tests and benchmarks, made with the model and the sensor model: spheres (uniform,
textured, several materials; mono and colour mosaics) and a mesh object written in the paper authors' layout; the
documentation's example data (:mod:`fmbrdf_mi.synthetic.examples`)."""
