"""Ctrl-C inside Dr.Jit: a KeyboardInterrupt raised in one of its callbacks arrives as a RuntimeError."""
from __future__ import annotations


def interrupted(exc):
    """Whether ``exc`` is a Ctrl-C in disguise: Dr.Jit re-raises a KeyboardInterrupt raised inside one of
    its callbacks (a Python BSDF's ``eval`` during ``mi.render``, a ``dr.custom`` operation) as a
    RuntimeError caused by it (``drjit.custom(...): error while performing a custom differentiable
    operation``)."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return True
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return False
