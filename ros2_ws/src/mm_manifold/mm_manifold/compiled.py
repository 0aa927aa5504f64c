"""numba compilation of the learners' inner loops (virtual_space's Euler integration, grid's projection)."""
from numba import njit


def compiled(function):
    """`function` compiled with numba, numpy's error model (a division by zero gives inf or NaN instead of raising,
    as the numpy code did) and an on-disk cache beside the module or in the user's cache directory, so a process
    loads the machine code instead of compiling it again (about 5 s). Where neither is writable (a read-only install
    with no writable home), numba refuses to cache: the function is then compiled in each process instead of the
    import failing."""
    try:
        return njit(cache=True, error_model='numpy')(function)
    except RuntimeError:            # "cannot cache function ...: no locator available for file ..."
        return njit(error_model='numpy')(function)
