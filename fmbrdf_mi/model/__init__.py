"""The FMBRDF model's mathematics in Dr.Jit, free of Mitsuba plumbing.

Every function here takes and returns Dr.Jit arrays of any backend (or Python
floats), so the same code runs inside a Mitsuba kernel, in table builds and
under automatic differentiation.
"""
