"""The pure core: numpy in, numpy out, no network, no files.

Geometry, segment extraction (paper III-D), the transformations of two maps and their value
(paper III, Algorithms 2-4), INTEGRATE and its validity rules, fusion (Algorithm 5), the seen free
space, scan-to-submap tracking and the wall grids it registers on.
"""
