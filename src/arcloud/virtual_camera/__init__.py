"""A virtual RGB-D camera in a triangle mesh: what it sees and where a user carries it.

- ``render``: ``MeshRenderer`` ray-casts any triangle mesh (a generated room or a real scan) into colour,
  z-depth and per-pixel instance ids with Open3D's ``RaycastingScene``.
- ``walk``: ``plan_walk`` plans one user's smooth walk over free floor looking at targets, the default
  walk or one in a ``WalkStyle`` (eye height, speed, coverage, glances, fast turns, jitter).

Both know meshes, floors and targets only, so the simulator (``arcloud.sim``) and the ScanNet mesh
renderer (``arcloud.datasets.render_scannet``) share them. Import the submodules; Open3D loads only
when a renderer is built.
"""
