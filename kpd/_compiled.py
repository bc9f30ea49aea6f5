"""Compiled kernels made on their first call, so that importing a module that defines them does not import numba."""

from __future__ import annotations

import functools
from typing import Callable

__all__ = ["compiled_on_first_call"]


def compiled_on_first_call(function: Callable) -> Callable:
    """``numba.njit(cache=True, nogil=True)(function)``, made on the first call: importing a module whose kernels
    are defined this way (every mesh reader imports this one) does not import numba, which takes half a second.

    The kernel is compiled once per machine and cached next to its source file, as numba's ``cache=True`` does.
    """
    dispatcher = None

    @functools.wraps(function)
    def call(*args):
        nonlocal dispatcher
        if dispatcher is None:
            import numba

            dispatcher = numba.njit(cache=True, nogil=True)(function)
        return dispatcher(*args)

    return call
