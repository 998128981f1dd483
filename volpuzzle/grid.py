"""The grid's vocabulary, shared by every stage: the parameter axes, piece ids and a frame around a direction.

Kept free of the package's other modules so that anything (spline/ included) can import it without a cycle.
"""
import numpy as np

AXES = "uvw"  # parameter axes in order; index k of a (3,) uvw array is AXES[k]


def piece_id(index):
    """The id of the piece cut from cell `index` (i, j, k) -> "pi-j-k", as in file names and the report."""
    return "p" + "-".join(str(int(i)) for i in index)


def frame_from_direction(n):
    """Unit direction n (3,) -> (e1, e2, n), a right-handed orthonormal frame (e1 x e2 = n).

    e1 is taken across the world axis least aligned with n, so the frame is stable for any direction. n is used as
    given (callers normalise it), so that the result is the same to the bit whether or not n was normalised here.
    """
    helper = np.eye(3)[int(np.argmin(np.abs(n)))]
    e1 = _cross(helper, n)
    e1 /= np.linalg.norm(e1)
    return e1, _cross(n, e1), n


def _cross(a, b):
    """np.cross of two (3,) vectors, the same products in the same order: np.cross spends ~70 us a call on
    broadcasting its axes, and the joint check alone builds a frame for each of its ~5,000 test cylinders."""
    a0, a1, a2 = float(a[0]), float(a[1]), float(a[2])
    b0, b1, b2 = float(b[0]), float(b[1]), float(b[2])
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def other_axes(axis):
    """The two axes (b, c), b < c, other than `axis`: a face across `axis` is spanned by them."""
    b, c = (k for k in range(3) if k != axis)
    return b, c
