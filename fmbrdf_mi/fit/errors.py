"""The error every input check of the fits raises: one line naming the parameter or file."""
from __future__ import annotations


class InputError(ValueError):
    """An input of the fit is missing, unreadable or malformed."""
