"""wallcull: a culling server for tiled display walls.

The object hierarchy of a scene (:mod:`wallcull.scene`, :mod:`wallcull.bounds`) is culled to the
frustum hierarchy of a wall (:mod:`wallcull.wall`) by the traversals of :mod:`wallcull.cull`;
:class:`wallcull.pipeline.Session` runs it frame after frame.
"""

__version__ = "0.1.0"
