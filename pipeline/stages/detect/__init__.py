"""Detection: the circular target's image ellipse, sub-pixel.

``detector`` (the detector's steps), ``blob`` (step 1, the coarse blob search),
``edges`` (the sub-pixel edge stage), ``ellipse`` (conic and ellipse geometry),
``ellipse_distance`` (signed distance of points to an ellipse), ``saturation`` (where
the contour lies on a clipped plate), ``_jit`` (the compiled kernel) and ``precompile``
(compiling it before the first image).
"""
