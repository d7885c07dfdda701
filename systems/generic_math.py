"""Scalar functions that work on floats and on ``pydrake.symbolic`` expressions alike.

The plants' and the controller's equations are written once with these helpers; called with
floats they are the readable reference, called with symbolic variables they build the
``SymbolicVectorSystem`` whose derivatives Drake evaluates in C++.
"""

import numpy as np
import pydrake.math as dmath
import pydrake.symbolic as sym


def where(condition, if_true, if_false):
    """``if_true`` when ``condition`` holds else ``if_false`` (``if_then_else`` for symbolic)."""
    if isinstance(condition, (bool, np.bool_)):
        return if_true if condition else if_false
    return sym.if_then_else(condition, if_true, if_false)


def logical_and(a, b):
    """Conjunction of two conditions (Python bools or symbolic Formulas)."""
    if isinstance(a, (bool, np.bool_)) and isinstance(b, (bool, np.bool_)):
        return bool(a and b)
    return sym.logical_and(a, b)


def sign(x):
    """-1, 0 or 1 for x < 0, x == 0, x > 0."""
    return where(x > 0, 1.0, where(x < 0, -1.0, 0.0))


atan = dmath.atan
tan = dmath.tan
sin = dmath.sin
cos = dmath.cos
exp = dmath.exp
absolute = dmath.abs


def dot(a, b):
    """Inner product of two 1-D sequences (numpy's object matmul warns on symbolic entries)."""
    return sum((a[i] * b[i] for i in range(len(a))), 0.0)


def matvec(m, v):
    """``m @ v`` for a float matrix and a float or symbolic vector."""
    return np.array([dot(row, v) for row in np.asarray(m)])


def scaled(v, c):
    """``c * v`` entrywise for a float vector and a float or symbolic scalar."""
    return np.array([vi * c for vi in np.asarray(v)])
